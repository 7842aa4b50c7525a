"""Landmark selection, flow tracks, association and trajectory refinement on the synthetic world."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cm3d import trajectory
from cm3d.data import synthetic
from cm3d.eval import metrics
from cm3d.solvers import factors

# compile fast (LLVM -O0): these programs run on tiny problems, compile time dominates
FAST = {"xla_backend_optimization_level": 0}

CFG = synthetic.WorldConfig(height=96, width=128)
TRACK = trajectory.TrackConfig(cell=8, keyframe_every=2, track_length=5, border=3)
S = 6


@pytest.fixture(scope="module")
def world():
    scene = synthetic.make_scene(0, CFG)
    images, gt = synthetic.render_ground_truth(scene, 1, S, CFG)
    return images, gt


def test_select_landmark_pixels_static_confident_only(world):
    _, gt = world
    depth = jnp.asarray(gt.depth[0], jnp.float32)
    conf = jnp.asarray(np.random.default_rng(0).uniform(1, 10, depth.shape), jnp.float32)
    static = jnp.asarray(~gt.dynamic_mask[0])
    static = static.at[:, :40].set(False)  # a dynamic band: no landmark there
    select = jax.jit(lambda d, c, s: trajectory.select_landmark_pixels(d, c, s, TRACK), compiler_options=FAST)
    uv, ok = select(depth, conf, static)
    C = (96 // 8) * (128 // 8)
    assert uv.shape == (C, 2) and ok.shape == (C,)
    u, v = np.asarray(uv[ok]).astype(int).T
    assert np.all(np.asarray(static)[v, u]) and np.all(np.asarray(depth)[v, u] > 0)
    thr = np.quantile(np.asarray(conf)[np.asarray(static) & (np.asarray(depth) > 0)], TRACK.conf_quantile)
    assert np.all(np.asarray(conf)[v, u] >= thr - 1e-5)
    assert np.all(u >= 40) and ok.sum() > C // 3
    # one candidate per cell, inside its cell
    cells = (v // 8) * (128 // 8) + (u // 8)
    np.testing.assert_array_equal(cells, np.flatnonzero(np.asarray(ok)))


def test_tracks_follow_ground_truth_flow_and_lift_to_world_points(world):
    _, gt = world
    with jax.enable_x64(True):
        static = jnp.asarray(~gt.dynamic_mask)
        depth = jnp.asarray(gt.depth, jnp.float64)
        conf = jnp.ones_like(depth)
        K = jnp.asarray(gt.intrinsic)
        poses = jnp.asarray(gt.cam_to_world)
        prepare = jax.jit(lambda *a: trajectory.prepare_landmarks(*a, track_cfg=TRACK), compiler_options=FAST)
        pts, obs, tracks, d_scene = prepare(depth, conf, static, K, poses, jnp.asarray(gt.flow, jnp.float64))
        valid = np.asarray(obs.valid)
        assert valid.sum() > 100
        # lifted landmarks are the true world points: they project onto every tracked position
        graph = factors.build_graph(poses, K, obs.pose_idx, obs.point_idx, obs.uv, obs.valid)
        err = np.asarray(factors.reprojection_errors(graph, factors.Variables(poses, pts)))[valid]
        assert np.median(err) < 0.05 and np.quantile(err, 0.9) < 0.5
        # tracks never sit on moving objects and start at keyframes
        pid, uv = np.asarray(obs.pose_idx)[valid], np.asarray(obs.uv)[valid]
        r, c = np.round(uv[:, 1]).astype(int), np.round(uv[:, 0]).astype(int)
        assert not np.any(gt.dynamic_mask[pid, r, c])
        assert set(np.asarray(tracks.frame)) <= set(range(0, S, TRACK.keyframe_every))
        assert float(d_scene) == pytest.approx(np.median(gt.depth[~gt.dynamic_mask & (gt.depth > 0)]), rel=1e-6)


def test_forward_backward_check_cuts_inconsistent_tracks(world):
    _, gt = world
    flow = jnp.asarray(gt.flow, jnp.float32)
    static = jnp.ones(gt.depth.shape, bool)
    seeds = jnp.array([[[40.0, 40.0], [80.0, 50.0]]])
    ok = jnp.ones((1, 2), bool)
    kf = jnp.zeros(1, jnp.int32)
    # a backward flow that undoes the forward one passes; a wrong one (2 px off) fails
    good = trajectory.chain_tracks(flow, static, seeds, ok, kf, TRACK, flow_bwd=-flow)
    bad = trajectory.chain_tracks(flow, static, seeds, ok, kf, TRACK, flow_bwd=-flow + 2.0)
    assert np.asarray(good.valid).sum() > np.asarray(bad.valid).sum()
    assert not np.any(np.asarray(bad.valid)[:, 1:])


def test_align_to_seed_recovers_a_subpixel_shift_that_chaining_missed():
    """A smooth texture seen again shifted by a known sub-pixel amount: chained positions 0.6 px
    off are pulled back onto the true ones; on a flat patch (nothing to align) and where the true
    position is farther than ``klt_max_px`` the chained positions stay. Reference: the shift by
    construction. jit gives the same positions."""
    rng = np.random.default_rng(0)
    H, W = 64, 80
    k = rng.uniform(0.2, 0.6, (6, 2)) * rng.choice([-1, 1], (6, 2))
    ph = rng.uniform(0, 2 * np.pi, 6)

    def texture(x, y):
        return 0.5 + 0.08 * sum(np.sin(k[i, 0] * x + k[i, 1] * y + ph[i]) for i in range(6))

    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    shift = np.array([0.8, -0.45])
    ref = texture(u, v)
    cur = texture(u - shift[0], v - shift[1])  # the texture moved by +shift
    cur[:, 60:] = 0.5  # a flat region
    seed = np.array([[20.0, 20.0], [35.5, 30.25], [50.0, 44.0], [30.0, 50.0], [65.0, 30.0]])
    chained = seed + shift + np.array([[0.6, 0.0], [0.0, -0.6], [-0.4, 0.45], [3.0, 0.0], [0.5, 0.0]])
    cfg = trajectory.TrackConfig()
    patches = trajectory.seed_patches(jnp.asarray(ref, jnp.float32)[..., None], jnp.asarray(seed, jnp.float32), cfg)
    args = (patches, jnp.asarray(cur, jnp.float32)[..., None], jnp.asarray(chained, jnp.float32))
    out = np.asarray(trajectory.align_to_seed(*args, cfg))
    np.testing.assert_allclose(out[:3], seed[:3] + shift, atol=0.05)  # chained: 0.6 px off
    np.testing.assert_allclose(out[3:], chained[3:], atol=1e-6)  # beyond klt_max_px; a flat patch
    np.testing.assert_allclose(np.asarray(jax.jit(trajectory.align_to_seed, static_argnums=3)(*args, cfg)), out,
                               atol=1e-5)
    off = trajectory.TrackConfig(klt_radius=0)
    with pytest.raises(ValueError, match="klt_rcond"):
        trajectory.TrackConfig(klt_rcond=1.5)
    np.testing.assert_array_equal(np.asarray(trajectory.align_to_seed(*args, off)), chained.astype(np.float32))


def test_keypoint_chains_equal_flow_chains(world):
    """Matches that re-detect each keypoint where the previous match sent it chain like the flow."""
    _, gt = world
    flow = np.asarray(gt.flow, np.float64)
    static = jnp.ones(gt.depth.shape, bool)
    rng = np.random.default_rng(0)
    N = 64
    uv0 = np.zeros((S - 1, N, 2))
    uv0[0] = rng.uniform(20, [108, 76], (N, 2))
    uv1 = np.zeros_like(uv0)
    for t in range(S - 1):
        if t:
            uv0[t] = uv1[t - 1]
        sample = trajectory.bilinear(jnp.asarray(flow), jnp.full(N, t), jnp.asarray(uv0[t]))
        uv1[t] = uv0[t] + np.asarray(sample)
    valid = np.ones((S - 1, N), bool)
    valid[2, :8] = False  # broken chains
    perm = rng.permutation(N)  # matches come in any order
    uv0, uv1, valid = uv0[:, perm], uv1[:, perm], valid[:, perm]
    seeds = jnp.asarray(uv0[:1][:, np.argsort(perm)])
    ok = jnp.ones((1, N), bool)
    kf = jnp.zeros(1, jnp.int32)
    with jax.enable_x64(True):
        kp = trajectory.chain_keypoint_tracks(jnp.asarray(uv0), jnp.asarray(uv1), jnp.asarray(valid), static,
                                              seeds, ok, kf, TRACK, radius=0.01)
        fl = trajectory.chain_tracks(jnp.asarray(flow), static, seeds, ok, kf, TRACK)
    both = np.asarray(kp.valid) & np.asarray(fl.valid)
    assert both.sum() > 0.8 * np.asarray(fl.valid).sum() - 8 * 3
    np.testing.assert_allclose(np.asarray(kp.uv)[both], np.asarray(fl.uv)[both], atol=1e-4)
    assert not np.any(np.asarray(kp.valid)[:8, 3:])  # chain cut where the match is missing
    keep = trajectory.keypoint_seeds(jnp.asarray([[5.0, 5.0], [1.0, 1.0]]), jnp.array([True, True]),
                                     jnp.ones((96, 128)), jnp.ones((96, 128)), jnp.ones((96, 128), bool), TRACK)
    np.testing.assert_array_equal(keep, [True, False])  # the second is inside the border


def test_association_threshold_and_memory_landmarks():
    with jax.enable_x64(True):
        cfg = trajectory.AssociationConfig(tau_min=0.05, ratio=0.02)
        assert float(trajectory.association_threshold(1.0, cfg)) == pytest.approx(0.05)
        assert float(trajectory.association_threshold(10.0, cfg)) == pytest.approx(0.2)
        bank = jnp.array([[0.0, 0, 0], [1, 0, 0], [5, 5, 5]])
        pts = jnp.array([[0.03, 0, 0], [1.0, 0.1, 0], [5, 5, 5.01], [9, 9, 9]])
        valid = jnp.array([True, True, True, True])
        bank_valid = jnp.array([True, True, False])
        idx, matched, tau = trajectory.associate_landmarks(pts, valid, bank, bank_valid, 1.0, cfg)
        np.testing.assert_array_equal(matched, [True, False, False, False])  # 0.1 > τ; bank 2 invalid
        _, matched10, _ = trajectory.associate_landmarks(pts, valid, bank, bank_valid, 10.0, cfg)
        np.testing.assert_array_equal(matched10, [True, True, False, False])  # τ = 0.2 at d_scene 10
        new, mem = trajectory.add_memory_landmarks(pts, valid, bank, bank_valid, 10.0, cfg)
        np.testing.assert_allclose(new[:2], bank[:2])
        np.testing.assert_allclose(new[2:], pts[2:])
        np.testing.assert_array_equal(mem, [True, True, False, False])


def _refine_sequence(gt, level):
    seq = synthetic.make_priors(np.zeros((S, 96, 128, 3), np.uint8), gt, level, seed=3)
    f64 = lambda a: jnp.asarray(a, jnp.float64)  # noqa: E731
    with jax.enable_x64(True):
        return seq, RUN(f64(seq.depth), f64(seq.depth_conf), jnp.asarray(~gt.dynamic_mask), f64(seq.intrinsic),
                        f64(seq.cam_to_world), f64(gt.flow))


@functools.partial(jax.jit, compiler_options=FAST)
def RUN(depth, conf, static, K, poses, flow):
    pts, obs, _, _ = trajectory.prepare_landmarks(depth, conf, static, K, poses, flow, track_cfg=TRACK)
    return trajectory.refine_trajectory(poses, K, pts, obs)


def test_refinement_lowers_ate_and_keeps_exact_priors(world):
    _, gt = world
    ate = lambda seq, est: metrics.evaluate_trajectories(seq.timestamps, gt.cam_to_world, seq.timestamps,  # noqa: E731
                                                         np.asarray(est))["ate"]
    seq, ref = _refine_sequence(gt, "moderate")
    assert bool(ref.refined)
    assert ate(seq, ref.poses) < 0.6 * ate(seq, seq.cam_to_world)
    R = np.asarray(ref.poses[:, :3, :3])
    np.testing.assert_allclose(np.swapaxes(R, 1, 2) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    # exact priors: the gate finds no significant improvement and returns them unchanged
    seq, ref = _refine_sequence(gt, "none")
    assert not bool(ref.refined)
    np.testing.assert_allclose(ref.poses, seq.cam_to_world, atol=1e-12)
    assert np.all(np.isfinite(np.asarray(ref.points)))


# ----------------------------------------------------------------------------------------------
# Memory landmarks: point priors on a remembered surface (issue #7)


def _surface_problem(seed=0):
    graph, init, truth = factors.random_problem(seed, 6, 60, obs_per_point=6, pixel_noise=0.3, outlier_frac=0.0,
                                                pose_noise=0.02, point_noise=0.05)
    f = graph.projection
    obs = trajectory.Observations(pose_idx=f.pose_idx, point_idx=f.point_idx, uv=f.z, valid=f.weight > 0,
                                  memory=jnp.zeros_like(f.weight, bool))
    n = np.random.default_rng(seed).normal(size=(60, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    surface = trajectory.MemorySurface(points=truth.points, normals=jnp.asarray(n, truth.points.dtype),
                                       valid=jnp.ones(60, bool), voxel=jnp.asarray(0.2), d_scene=jnp.asarray(4.5))
    return graph, init, truth, obs, surface


def test_point_prior_gradient_matches_autodiff_of_the_objective():
    """The LM's landmark-prior terms (gradient and Gauss-Newton blocks) against ``jax.grad`` of the
    objective (reference: autodiff of the plain cost), at a point off the optimum."""
    from cm3d.solvers import lm

    graph, init, truth, _, surface = _surface_problem(1)
    S = jnp.zeros((60, 3, 3)).at[:, 0, :].set(surface.normals / 0.01).at[:, 1, 1].set(3.0)
    g = factors.with_point_prior(graph, truth.points, S, jnp.arange(60) % 3 > 0)

    @functools.partial(jax.jit, compiler_options=FAST)
    def blocks(g, graph, init):
        st = lm.structure(g, 60)
        _, gl = lm.gradient(g, init, st)
        ref = jax.grad(lambda pts: factors.total_cost(g, init.replace(points=pts), st.obs_active))(init.points)
        H_ref = jax.hessian(lambda p: factors.point_prior_cost(g, init.points.at[5].set(p)))(init.points[5])
        H_plain = lm.linearize(graph, init, lm.structure(graph, 60)).H_point[5]
        return gl, jnp.where(st.point_active[:, None], ref, 0.0), lm.linearize(g, init, st).H_point[5] - H_plain, H_ref

    gl, ref, H, H_ref = blocks(g, graph, init)
    # float32: an entry that is a difference of terms ~1000 (the priors' 1/0.01 normals) carries their round-off
    np.testing.assert_allclose(gl, ref, rtol=1e-4, atol=1e-6 * float(np.abs(ref).max()))
    np.testing.assert_allclose(H, H_ref, rtol=1e-5, atol=1e-6)
    assert float(factors.point_prior_cost(graph, init.points)) == 0.0  # no priors: the paper's graph


def test_remembered_surface_lowers_the_pose_error():
    """Landmarks held on the true surface pin the poses: the refined poses' error falls well below the
    refinement without memory (reference: the true poses); a surface placed 5 % too large and shifted is
    re-fitted (``realign``) and the recovered placement undoes that similarity."""
    graph, init, truth, obs, surface = _surface_problem(0)
    cfg = trajectory.RefineConfig(gate=False)
    assoc = trajectory.AssociationConfig(ratio=0.02)
    run = jax.jit(lambda surface: trajectory.refine_trajectory(init.poses, graph.intrinsics, init.points, obs, cfg,
                                                               memory=surface, assoc=assoc), compiler_options=FAST)

    def err(poses):
        return float(np.mean(np.linalg.norm(np.asarray(poses)[:, :3, 3] - np.asarray(truth.poses)[:, :3, 3], axis=1)))

    plain = run(surface.replace(valid=jnp.zeros(60, bool)))  # an empty memory: the paper's graph without memory
    mem = run(surface)
    assert int(np.sum(mem.memory)) > 30 and not np.any(plain.memory)
    assert err(mem.poses) < 0.5 * err(plain.poses), (err(mem.poses), err(plain.poses))
    # a misplaced surface (similarity D applied): the re-fit recovers D
    D = np.eye(4)
    D[:3, :3] *= 1.05
    D[:3, 3] = [0.03, -0.02, 0.01]
    moved = surface.replace(points=surface.points @ jnp.asarray(D[:3, :3].T) + jnp.asarray(D[:3, 3]),
                            voxel=surface.voxel * 1.05)
    A = jax.jit(trajectory.align_to_surface, static_argnames=("cfg", "iterations"), compiler_options=FAST)(
        truth.points, jnp.ones(60, bool), moved, cfg=assoc, iterations=5)
    np.testing.assert_allclose(A, D, atol=2e-3)
