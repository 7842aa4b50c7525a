"""Long videos (cm3d.long_video): Sim(3) alignment, chaining, naive baseline, frame graph, loops, chunk files."""

import dataclasses

import jax
import numpy as np
import pytest

from cm3d import long_video as stitch
from cm3d.long_video.overlap import shared_frames
from cm3d.solvers.chain_pose_graph import solve_chain
from cm3d.data import io, synthetic
from cm3d.eval import metrics

CFG = synthetic.WorldConfig(height=48, width=64, supersample=1)
FRAMES, CHUNK, OVERLAP = 40, 14, 4


@pytest.fixture(scope="module")
def video():
    scene = synthetic.make_scene(0, CFG)
    images, gt = synthetic.render_ground_truth(scene, 0, FRAMES, CFG)
    return images, gt


@pytest.fixture(scope="module")
def noise_free(video):
    chunks = chunks_at(video, "none")
    return chunks, stitch.stitch_chunks(chunks, refine=False)


def chunks_at(video, level, seed=0):
    images, gt = video
    return synthetic.make_chunk_priors(images, gt, CHUNK, OVERLAP, level, seed=seed,
                                       timestamps=np.arange(FRAMES) / CFG.fps)


def random_similarity(rng):
    from scipy.spatial.transform import Rotation

    Q = np.eye(4)
    s = float(np.exp(rng.normal(0, 0.5)))
    Q[:3, :3] = s * Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    Q[:3, 3] = rng.normal(size=3)
    return Q, s


def test_chunk_ranges():
    assert synthetic.chunk_ranges(200, 40, 10) == [(0, 40), (30, 70), (60, 100), (90, 130), (120, 160),
                                                   (150, 190), (180, 200)]
    with pytest.raises(ValueError, match="overlap"):
        synthetic.chunk_ranges(100, 40, 40)


def test_align_overlap_recovers_known_similarity(video):
    """A chunk and a copy moved by a known Sim(3) (depth scaled by its scale): the fit is that Sim(3)."""
    c = chunks_at(video, "none")[1]
    Q, s = random_similarity(np.random.default_rng(3))
    moved = stitch.place_poses(Q, c.cam_to_world)
    o = OVERLAP
    with jax.enable_x64(True):  # float64 inputs: the fit is exact up to the float32 depth maps
        prev = shared_frames(c, slice(0, o))
        nxt = shared_frames(c.replace(depth=c.depth * s, cam_to_world=moved), slice(0, o))
        fit = stitch.align_overlap(prev, nxt)
    np.testing.assert_allclose(np.asarray(fit.transform), np.linalg.inv(Q), atol=1e-6)
    assert abs(float(fit.scale) * s - 1) < 1e-6
    assert float(fit.rmse_points) < 1e-6 and float(fit.inlier_fraction) > 0.99


def test_noise_free_stitch_equals_ground_truth(video, noise_free):
    chunks, res = noise_free
    gt = video[1].cam_to_world
    assert res.sequence.num_frames == FRAMES
    assert res.ranges == tuple(synthetic.chunk_ranges(FRAMES, CHUNK, OVERLAP))
    assert float(metrics.ate(res.sequence.cam_to_world, gt)) < 1e-6
    # chunk 0's frame and scale: its poses are unchanged
    np.testing.assert_allclose(res.sequence.cam_to_world[:CHUNK - OVERLAP], chunks[0].cam_to_world[:CHUNK - OVERLAP],
                               atol=1e-9)
    for b in res.boundaries:
        true = chunks[b.chunk - 1].meta["prior_scale"] / chunks[b.chunk].meta["prior_scale"]
        assert abs(b.scale / true - 1) < 1e-6
    # depths of later chunks are in chunk 0's scale: depth / gt depth is chunk 0's prior scale
    d, g = res.sequence.depth, res.sequence.gt.depth
    ok = g > 0
    np.testing.assert_allclose(d[ok] / g[ok], chunks[0].meta["prior_scale"], rtol=1e-5)
    np.testing.assert_array_equal(res.sequence.images, video[0])
    io.validate_sequence(res.sequence)


def test_cm3d_beats_naive_on_noisy_chunks(video):
    chunks = chunks_at(video, "moderate")
    gt = video[1].cam_to_world
    naive = stitch.naive_stitch(chunks)
    res = stitch.stitch_chunks(chunks, refine=False)
    e_naive = float(metrics.ate(naive.sequence.cam_to_world, gt))
    e_cm3d = float(metrics.ate(res.sequence.cam_to_world, gt))
    assert e_cm3d < e_naive
    for b in res.boundaries:  # scales recovered within a few percent despite depth and pose noise
        true = chunks[b.chunk - 1].meta["prior_scale"] / chunks[b.chunk].meta["prior_scale"]
        assert abs(b.scale / true - 1) < 0.05
    assert np.mean([b.rel_rmse_points for b in res.boundaries]) < np.mean([b.rel_rmse_points for b in naive.boundaries])
    s = res.summary()
    assert s["num_chunks"] == len(chunks) and "boundary1_scale" in s


def test_single_chunk_is_returned_as_is(video):
    c = chunks_at(video, "moderate")[0]
    res = stitch.stitch_chunks([c], refine=False)
    np.testing.assert_allclose(res.sequence.cam_to_world, c.cam_to_world, atol=1e-12)
    np.testing.assert_allclose(res.sequence.depth, c.depth)
    assert res.boundaries == () and res.chunk_transforms.shape == (1, 4, 4)


def test_bad_input(video):
    chunks = chunks_at(video, "moderate")
    with pytest.raises(stitch.StitchError, match="empty"):
        stitch.stitch_chunks([])
    with pytest.raises(stitch.StitchError, match="list of Sequence"):
        stitch.stitch_chunks(chunks[0])
    gap = chunks[1].slice(OVERLAP + 1, chunks[1].num_frames)  # starts after chunk 0 ends
    with pytest.raises(stitch.StitchError, match=r"chunks\[1\]: does not overlap"):
        stitch.stitch_chunks([chunks[0], gap], refine=False)
    small = chunks[1].replace(images=chunks[1].images[:, :32], depth=chunks[1].depth[:, :32],
                              depth_conf=chunks[1].depth_conf[:, :32], gt=None)
    with pytest.raises(stitch.StitchError, match=r"chunks\[1\]: images are 32x64.*same image size"):
        stitch.stitch_chunks([chunks[0], small], refine=False)
    bad_k = chunks[1].replace(intrinsic=chunks[1].intrinsic[:, :2])
    with pytest.raises(io.SequenceFormatError, match=r"chunks\[1\].*'intrinsic'"):
        stitch.stitch_chunks([chunks[0], bad_k], refine=False)
    with pytest.raises(stitch.StitchError, match="must add at least one new frame"):
        stitch.stitch_chunks(chunks[:2], overlap=CHUNK, refine=False)
    with pytest.raises(stitch.StitchError, match="three chunks"):
        stitch.stitch_chunks(chunks, overlap=8, refine=False)
    with pytest.raises(stitch.StitchError, match="static"):
        stitch.stitch_chunks(chunks, static=np.ones((3, 48, 64), bool), refine=False)
    # per-chunk frame indices as timestamps: inference refuses, an explicit overlap works
    local = [c.replace(timestamps=np.arange(c.num_frames, dtype=float)) for c in chunks]
    with pytest.raises(stitch.StitchError, match="pass overlap="):
        stitch.stitch_chunks(local, refine=False)
    res = stitch.stitch_chunks(local, overlap=OVERLAP, refine=False)
    np.testing.assert_array_equal(res.sequence.timestamps, np.arange(FRAMES))


def test_chunk_files_round_trip(video, tmp_path):
    chunks = chunks_at(video, "slight")
    stitch.save_chunks(tmp_path / "all.npz", chunks)
    for back in (stitch.load_chunks(tmp_path / "all.npz"), stitch.load_chunks([tmp_path / "all.npz"])):
        assert len(back) == len(chunks)
        for a, b in zip(chunks, back):
            for k in ("images", "depth", "depth_conf", "intrinsic", "cam_to_world", "timestamps"):
                np.testing.assert_allclose(getattr(b, k), getattr(a, k), rtol=1e-6, atol=1e-12)
            np.testing.assert_allclose(b.gt.flow, a.gt.flow)
            assert b.meta == a.meta
    paths = []
    for k, c in enumerate(chunks):
        paths.append(tmp_path / f"c{k}.npz")
        io.save_sequence(paths[-1], c)
    back = stitch.load_chunks(paths)
    np.testing.assert_allclose(back[2].cam_to_world, chunks[2].cam_to_world)
    r1 = stitch.stitch_chunks(back, refine=False)
    r2 = stitch.stitch_chunks(chunks, refine=False)
    np.testing.assert_allclose(r1.sequence.cam_to_world, r2.sequence.cam_to_world, atol=1e-9)
    # a bad chunk index names the file and the key
    seq, idx = stitch.concat_chunks(chunks)
    with pytest.raises(stitch.StitchError, match="key 'chunk'"):
        stitch.split_chunks(seq, idx[::-1].copy(), source="x.npz")
    with pytest.raises(FileNotFoundError):
        stitch.load_chunks([tmp_path / "missing.npz"])


def _sim3(rng, rot=0.3, trans=1.0, logs=0.2):
    from scipy.spatial.transform import Rotation

    G = np.eye(4)
    G[:3, :3] = np.exp(rng.normal(0, logs)) * Rotation.from_rotvec(rng.normal(0, rot, 3)).as_matrix()
    G[:3, 3] = rng.normal(0, trans, 3)
    return G


def test_sim3_pose_graph_closes_a_loop():
    """Chunk transforms chained from drifting overlap constraints (rotation, translation and scale
    drift): with a loop constraint between the last and the first chunk the pose graph spreads the
    drift back (the loop chunk's error falls), and with exact constraints it returns the truth."""
    with jax.enable_x64(True):  # float64 inputs: the exact-constraint optimum is checked to 1e-12
        rng = np.random.default_rng(0)
        K = 6
        G_true = [np.eye(4)]
        for _ in range(1, K):
            G_true.append(G_true[-1] @ _sim3(rng, 0.2, 0.5, 0.1))
        G_true = np.stack(G_true)
        A_true = np.stack([np.eye(4)] + [np.linalg.inv(G_true[k - 1]) @ G_true[k] for k in range(1, K)])
        drift = _sim3(rng, 0.01, 0.02, 0.02)  # the same small error at every boundary: a drift
        A = np.stack([np.eye(4)] + [A_true[k] @ drift for k in range(1, K)])
        G0 = np.stack([np.linalg.multi_dot([np.eye(4)] + [A[j] for j in range(1, k + 1)]) if k else np.eye(4)
                       for k in range(K)])
        loop = stitch.LoopClosure(chunk=K - 1, other=0, frames=(0, 20), transform=G_true[K - 1], inliers=100, rmse=0.01)
        G, facts = stitch.sim3_pose_graph(G0, A, [loop], stitch.PoseGraphConfig(loop_quantile=1.0, loop_factor=2.0))
        err = lambda X: float(np.linalg.norm(X[K - 1][:3, 3] - G_true[K - 1][:3, 3]))  # noqa: E731
        assert facts["loops"] == 1 and facts["cost"] < facts["cost_initial"]
        assert err(G) < 0.5 * err(G0)
        np.testing.assert_allclose(G[0], np.eye(4), atol=1e-12)  # the gauge
        # exact constraints: the truth is the optimum
        G, facts = stitch.sim3_pose_graph(G0, A_true, [loop])
        np.testing.assert_allclose(G, G_true, atol=1e-6)
        assert facts["cost"] < 1e-12
        # the consistency check: with the default (coarse) loop noise this drift is plausible and the loop
        # is kept with a small weight; a loop to the wrong place (30°, 3 units off) is refused, chain kept
        G, facts = stitch.sim3_pose_graph(G0, A, [loop])
        assert facts["loops_kept"] == 1 and facts["loop_kept"] == [True] and err(G) < err(G0)
        wrong = dataclasses.replace(loop, transform=G_true[K - 1] @ _sim3(rng, 0.5, 3.0, 0.0))
        G, facts = stitch.sim3_pose_graph(G0, A, [wrong])
        assert facts["loops_kept"] == 0 and facts["loop_discrepancy_max"] > facts["loop_limit"]
        np.testing.assert_allclose(G, G0, atol=1e-9)
        with pytest.raises(stitch.StitchError, match="distinct chunks"):
            stitch.sim3_pose_graph(G0, A, [stitch.LoopClosure(2, 2, (0, 1), np.eye(4), 0, 0.0)])


def test_recall_loops_from_window_records(noise_free):
    """Only accepted recalls of maps the previous chunk did not write (create or merge into) are
    loop closures, tied to the creating chunk and window; the memory's transform (between the
    windows' refined frames) is re-expressed between the chunks' prior frames."""
    from types import SimpleNamespace

    def win(acc, rec, created, map_id, T=np.eye(4)):
        return SimpleNamespace(accepted=acc, recalled_map=rec, created_map=created, map_id=map_id, frames=(0, 20),
                               transform=T, inlier_count=50, rmse=0.01)

    T = np.diag([2.0, 2.0, 2.0, 1.0])
    results = [SimpleNamespace(windows=[win(False, -1, True, 0)]),
               SimpleNamespace(windows=[win(True, 0, False, 0), win(False, -1, True, 1)]),  # consecutive: no loop
               SimpleNamespace(windows=[win(False, -1, True, 2)]),
               SimpleNamespace(windows=[win(True, 1, False, 1, T), win(True, 3, False, 3)]),  # map 3 unknown
               # map 1 again: chunk 3 just merged into it, so this is the chain, not a loop; map 2 is one
               SimpleNamespace(windows=[win(True, 1, False, 1), win(True, 2, False, 2)])]
    loops = stitch.recall_loops(results)
    assert [(lc.chunk, lc.other) for lc in loops] == [(3, 1), (4, 2)]
    np.testing.assert_array_equal(loops[0].transform, T)
    assert loops[0].other_frames == (0, 20)
    # refined windows = the priors moved by known rigid motions Q (depth unchanged): the loop in prior
    # frames is Q_other^-1 T Q_chunk, whatever the window's refinement did
    chunks = noise_free[0][:2]
    rng = np.random.default_rng(1)
    Q = [_sim3(rng, 0.05, 0.1, 0.0) for _ in chunks]
    res = [SimpleNamespace(poses=stitch.place_poses(q, c.cam_to_world)) for q, c in zip(Q, chunks)]
    lc = stitch.LoopClosure(chunk=1, other=0, frames=(0, OVERLAP - 1), transform=T, inliers=50, rmse=0.01,
                            other_frames=(CHUNK - OVERLAP, CHUNK - 1))
    fixed = stitch.loop_to_prior_frames(lc, chunks, res)
    # the frame changes are float32 fits (align_overlap) of clouds ~1 unit across: a few float32 ulps
    # of the 2x-scaled rotation entries (~1.6e-6 seen in CI), far below any pose-graph effect
    np.testing.assert_allclose(fixed.transform, np.linalg.inv(Q[0]) @ T @ Q[1], atol=1e-5)
    np.testing.assert_array_equal(fixed.measured, T)
    with pytest.raises(stitch.StitchError, match="creating window"):
        stitch.loop_to_prior_frames(dataclasses.replace(lc, other_frames=None), chunks, res)


def test_memory_sequence_result_for_the_writers(video):
    """The whole-video result handed to the output writers: masks from the chunk each frame's image
    comes from, windows renumbered to global frames and tagged with their chunk."""
    from types import SimpleNamespace

    @dataclasses.dataclass(frozen=True)
    class Window:  # the fields of the pipeline's window record that the writers' renumbering touches
        frames: tuple
        accepted: bool = False
        chunk: int | None = None

    chunks = chunks_at(video, "moderate")
    base = stitch.stitch_chunks(chunks, refine=False)
    H, W = chunks[0].image_size
    fake = [SimpleNamespace(masks=np.full((c.num_frames, H, W), k % 2 == 1),
                            windows=[Window(frames=(0, c.num_frames - 1))])
            for k, c in enumerate(chunks)]
    res = dataclasses.replace(base, method="cm3d-memory", results=tuple(fake))
    out = stitch.memory_sequence_result(res, chunks)
    np.testing.assert_array_equal(out.masks.any(axis=(1, 2)), res.frame_chunk % 2 == 1)
    assert [w.chunk for w in out.windows] == list(range(len(chunks)))
    assert [w.frames[0] for w in out.windows] == [a for a, _ in res.ranges]
    np.testing.assert_allclose(out.prior, base.sequence.cam_to_world)
    with pytest.raises(stitch.StitchError, match="stitch_with_memory"):
        stitch.memory_sequence_result(base, chunks)


def test_whole_trajectory_refinement_lowers_error_and_survives_a_bad_chunk(video):
    """The frame-level pose graph (image-measured relative motions across chunk boundaries) lowers
    the stitched priors' ATE; a chunk whose images are shifted (its flow says wrong motions) has
    those frame pairs dropped instead of corrupting the trajectory; leverages sum to 6N."""
    chunks = chunks_at(video, "moderate")
    gt = video[1].cam_to_world
    res = stitch.stitch_chunks(chunks, refine=True)
    e_prior, e_ref = (float(metrics.ate(P, gt)) for P in (res.poses_aligned, res.sequence.cam_to_world))
    f = res.refinement
    assert res.refined and f["kept"] and f["pairs_used"] == FRAMES - 1
    assert e_ref < 0.85 * e_prior, (e_prior, e_ref)
    assert f["sigma_motion_rot_deg"] < f["sigma_prior_rot_deg"]  # estimated, no ground truth
    # chunk 1's images rolled by +-8 px, alternating: wrong motions of ~15°, dropped
    bad = chunks[1].replace(images=np.stack([np.roll(im, 8 * (-1) ** i, axis=1)
                                             for i, im in enumerate(chunks[1].images)]))
    res_bad = stitch.stitch_chunks([chunks[0], bad, *chunks[2:]], refine=True)
    assert res_bad.refinement["pairs_used"] < FRAMES - 1 - 3
    e_bad = float(metrics.ate(res_bad.sequence.cam_to_world, gt))
    assert e_bad < float(metrics.ate(res_bad.poses_aligned, gt)), (e_bad, e_prior)
    # the hat matrix's trace (leverages of every factor component) is 6N
    with jax.enable_x64(True):
        P = res.poses_aligned
        ia = np.arange(FRAMES - 1)
        g = stitch.frame_graph(P, ia, ia + 1, np.linalg.inv(P[ia]) @ P[ia + 1], np.full(6, 0.01), np.full(6, 0.1))
        out = solve_chain(g, jax.numpy.asarray(P))
        leverage = float(np.sum(np.asarray(out.h_prior)) + np.sum(np.asarray(out.h_motion)))
    np.testing.assert_allclose(leverage, 6 * FRAMES, rtol=1e-6)


def test_chunk_outputs_use_the_refined_chunk_poses(video):
    """stitch_with_memory stitches each chunk's *refined* poses (the pipeline's result), not its
    priors: given refinements that are the ground truth in each chunk's own frame and scale, the
    stitched video is (nearly) exact while the stitched priors keep their noise."""
    from types import SimpleNamespace

    from cm3d.solvers.umeyama import umeyama

    chunks = chunks_at(video, "moderate")
    gt = np.asarray(video[1].cam_to_world, np.float64)
    ranges = synthetic.chunk_ranges(FRAMES, CHUNK, OVERLAP)
    fake = []
    for c, (a, b) in zip(chunks, ranges):
        s, R, t = (np.asarray(v, np.float64) for v in umeyama(gt[a:b, :3, 3], np.asarray(c.cam_to_world)[:, :3, 3]))
        Q = np.eye(4)
        Q[:3, :3], Q[:3, 3] = s * R, t
        fake.append(SimpleNamespace(poses=stitch.place_poses(Q, gt[a:b]), windows=[],
                                    masks=np.zeros(c.depth.shape, bool)))
    res = stitch.stitch_with_memory(chunks, OVERLAP, results=fake, refine=False)
    e_prior = float(metrics.ate(res.refinement["poses_stitched_prior"], gt))
    e_stitched = float(metrics.ate(res.refinement["poses_stitched"], gt))
    np.testing.assert_allclose(res.sequence.cam_to_world, res.refinement["poses_stitched"])
    assert e_stitched < 0.3 * e_prior, (e_stitched, e_prior)
