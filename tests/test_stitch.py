"""Long-video stitching (cm3d.stitch): Sim(3) alignment, chaining, naive baseline, errors, chunk files."""

import jax
import numpy as np
import pytest

from cm3d import stitch
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
    with jax.enable_x64(True):
        moved = np.asarray(stitch.place_poses(stitch._f(Q), stitch._f(c.cam_to_world)))
        o = OVERLAP
        prev = stitch._shared(c, slice(0, o))
        nxt = (stitch._f(c.depth[:o] * s), stitch._f(c.intrinsic[:o]), stitch._f(moved[:o]))
        A, diag = stitch.align_overlap(prev, nxt)
    # exact up to the float32 depth maps
    np.testing.assert_allclose(np.asarray(A), np.linalg.inv(Q), atol=1e-6)
    assert abs(float(diag["scale"]) * s - 1) < 1e-6
    assert float(diag["rmse_points"]) < 1e-6 and float(diag["inlier_fraction"]) > 0.99


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


def test_refine_check_refuses_a_drifting_refinement(noise_free, monkeypatch):
    """The factor graph's result is kept only when it stays within the overlap-measured noise."""
    seq = noise_free[1].sequence
    P = seq.cam_to_world

    def fake(distort):
        def refine_poses(s, static=None, cfg=None, pad_to=None):
            Q = P.copy()
            Q[:, :3, 3] *= 1 + distort * np.linspace(0, 1, len(Q))[:, None]  # scale drift
            return Q, True, {"observations": 1}
        return refine_poses

    monkeypatch.setattr(stitch, "refine_poses", fake(0.0))
    poses, refined, kept, facts = stitch.refine_checked(seq, noise=1e-3)
    assert kept and facts["deviation"] < 1e-9
    monkeypatch.setattr(stitch, "refine_poses", fake(0.5))
    poses, refined, kept, facts = stitch.refine_checked(seq, noise=1e-3)
    assert not kept and facts["deviation"] > facts["deviation_limit"]
    np.testing.assert_array_equal(poses, P)


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
