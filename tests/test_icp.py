"""ICP: recovery within the basin, agreement with Open3D, Sim(3), robust kernel, pyramid,
degenerate input, jit/vmap. Every call is jitted on (3000, 3) clouds (padded with validity masks)
with a few shared option sets, so the file compiles few programs."""

import jax
import jax.numpy as jnp
import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from cm3d.data import synthetic
from cm3d.ops.neighbors import build_target_index
from cm3d.solvers.icp import ICPOptions, icp, icp_batch, icp_coarse_to_fine, stack_indices

N, R_MAX = 3000, 0.3
P2L = ICPOptions(max_correspondence_distance=R_MAX, max_iterations=100)
P2P = ICPOptions(method="point_to_point", max_correspondence_distance=R_MAX, max_iterations=100)
SIM_P2P = ICPOptions(method="point_to_point", with_scale=True, max_correspondence_distance=R_MAX, max_iterations=100)
SIM_P2L = ICPOptions(with_scale=True, kernel="tukey", kernel_scale=0.1, max_correspondence_distance=R_MAX,
                     max_iterations=100)  # as tests/test_align.py
_build = jax.jit(build_target_index, static_argnames=("radius",))
_icp = jax.jit(icp, static_argnames="options")


def run_icp(src, index, init=None, valid=None, options=P2L):
    """The jitted ICP with explicit init and mask (one program per option set)."""
    init = np.eye(4) if init is None else init
    valid = np.ones(len(src), bool) if valid is None else valid
    return _icp(jnp.asarray(src, jnp.float32), index, jnp.asarray(init, jnp.float32), jnp.asarray(valid),
                options=options)


def build(points, valid=None):
    valid = np.ones(len(points), bool) if valid is None else valid
    return _build(jnp.asarray(points, jnp.float32), jnp.asarray(valid), radius=R_MAX)


def room(n, seed=0, size=(4.0, 3.0, 2.5)):
    """Room-like cloud: floor, ceiling, walls and three boxes, sampled uniformly by area."""
    return synthetic.room_cloud(n, seed, size, ((0.5, 0.4, 0.8, 0.5, 0.9), (2.4, 1.6, 0.6, 1.0, 0.5),
                                                (1.2, 2.0, 0.4, 0.4, 1.4)))


def random_pose(rng, deg, metres):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) / np.sqrt(3) * np.deg2rad(deg)).as_matrix()
    d = rng.normal(size=3)
    T[:3, 3] = d / np.linalg.norm(d) * metres
    return T


def make_pair(seed=0, deg=3.0, metres=0.1):
    """(source in its own frame, target, true source->target transform)."""
    rng = np.random.default_rng(seed + 100)
    tgt, src = room(N, 0), room(N, seed + 1)
    T = random_pose(rng, deg, metres)
    src_local = ((src - T[:3, 3]) @ T[:3, :3]).astype(np.float32)
    return src_local, tgt, T


def pose_err(T, T_gt):
    T = np.asarray(T, np.float64)
    s = np.cbrt(np.linalg.det(T[:3, :3]))
    dR = np.rad2deg(Rotation.from_matrix(T[:3, :3] / s @ T_gt[:3, :3].T).magnitude())
    return dR, np.linalg.norm(T[:3, 3] - T_gt[:3, 3])


@pytest.fixture(scope="module")
def target_index():
    return build(room(N, 0))


@pytest.mark.parametrize("options", [P2L, P2P], ids=["p2l", "p2p"])
def test_icp_recovers_random_transforms(options, target_index):
    for seed in range(3):
        src, _, T = make_pair(seed=seed, deg=4.0, metres=0.12)
        res = run_icp(src, target_index, options=options)
        dR, dt = pose_err(res.transform, T)
        assert dR < 0.5 and dt < 0.02, (seed, dR, dt)
        assert float(res.fitness) > 0.95 and 0 < float(res.inlier_rmse) < 0.12
        assert bool(res.converged) and 0 < int(res.iterations) < options.max_iterations


@pytest.mark.parametrize("options", [P2L, P2P], ids=["p2l", "p2p"])
def test_icp_matches_open3d(options, target_index):
    src, tgt, T = make_pair(seed=7)
    pt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt.astype(np.float64)))
    pt.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(16))
    ps = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src.astype(np.float64)))
    reg = o3d.pipelines.registration
    est = (reg.TransformationEstimationPointToPlane() if options.method == "point_to_plane"
           else reg.TransformationEstimationPointToPoint())
    ro = reg.registration_icp(ps, pt, R_MAX, np.eye(4), est, reg.ICPConvergenceCriteria(max_iteration=100))
    res = run_icp(src, target_index, options=options)
    dR, dt = pose_err(res.transform, ro.transformation)
    assert dR < 0.3 and dt < 0.01
    assert abs(float(res.fitness) - ro.fitness) < 0.01
    assert abs(float(res.inlier_rmse) - ro.inlier_rmse) < 0.002
    # the final statistics are exact: Open3D's evaluation at our transform gives the same numbers
    ev = reg.evaluate_registration(ps, pt, R_MAX, np.asarray(res.transform, np.float64))
    assert abs(float(res.fitness) - ev.fitness) < 1e-3
    assert abs(float(res.inlier_rmse) - ev.inlier_rmse) < 1e-4


@pytest.mark.parametrize("options", [SIM_P2P, SIM_P2L], ids=["p2p", "p2l_tukey"])
def test_sim3_recovers_scale(options, target_index):
    src, _, T = make_pair(seed=3)
    s = 1.07
    res = run_icp(src / s, target_index, options=options)
    assert float(res.scale) == pytest.approx(s, rel=3e-3)
    dR, dt = pose_err(res.transform, T)
    assert dR < 0.5 and dt < 0.02


def test_robust_kernel_and_pyramid(target_index):
    src, _, T = make_pair(seed=4)
    src[::10] += np.random.default_rng(0).normal(scale=0.2, size=src[::10].shape).astype(np.float32)  # outliers
    rob = run_icp(src, target_index, options=SIM_P2L)  # Tukey kernel (Sim(3), the true scale is 1)
    dR, dt = pose_err(rob.transform, T)
    assert dR < 0.5 and dt < 0.02 and float(rob.scale) == pytest.approx(1.0, abs=3e-3)
    coarse = np.zeros_like(src)
    coarse[: N // 4] = src[::4]
    levels = [(jnp.asarray(coarse), jnp.asarray(np.arange(N) < N // 4)), (jnp.asarray(src), jnp.ones(N, bool))]
    c2f = icp_coarse_to_fine(levels, target_index, jnp.eye(4), [P2L, P2L], icp_fn=_icp)
    dR, dt = pose_err(c2f.transform, T)
    assert dR < 0.5 and dt < 0.02


@pytest.mark.parametrize("options", [P2L, P2P], ids=["p2l", "p2p"])
def test_degenerate_inputs_give_clear_results(options, target_index):
    cases = []
    for pts in (np.zeros((0, 3)), np.array([[1, 1, 1], [1.1, 1, 1]]), np.full((5, 3), 100.0),
                np.array([[np.nan, 0, 0], [1, 1, 0.01]])):
        src = np.zeros((N, 3), np.float32)
        src[: len(pts)] = pts
        cases.append((src, np.arange(N) < len(pts)))
    for src, valid in cases:
        res = run_icp(src, target_index, valid=valid, options=options)
        assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(res))
        assert 0.0 <= float(res.fitness) <= 1.0
    res = icp(jnp.zeros((0, 3)), target_index, None, None, options)  # an empty source: no loop, eager
    assert float(res.fitness) == 0.0 and np.allclose(res.transform, np.eye(4))
    empty_target = build(np.zeros((N, 3)), np.zeros(N, bool))
    res = run_icp(room(N, 1), empty_target, options=options)
    assert float(res.fitness) == 0.0 and np.allclose(res.transform, np.eye(4))
    with pytest.raises(ValueError):
        icp(jnp.ones((30, 3)), empty_target, None, None, ICPOptions(max_correspondence_distance=1.0))


def test_vmap_batch_equals_loop(target_index):
    pairs = [make_pair(seed=s) for s in range(3)]
    idx = [target_index] + [build(t) for _, t, _ in pairs[1:]]  # the same target room
    srcs = jnp.asarray(np.stack([s for s, _, _ in pairs]))
    batched = jax.jit(icp_batch, static_argnames="options")(srcs, stack_indices(idx), jnp.tile(jnp.eye(4), (3, 1, 1)),
                                                            jnp.ones((3, N), bool), options=P2L)
    for b in range(3):
        one = run_icp(srcs[b], idx[b], options=P2L)
        np.testing.assert_allclose(batched.transform[b], one.transform, atol=1e-6)
        assert int(batched.iterations[b]) == int(one.iterations)
        assert int(batched.inlier_count[b]) == int(one.inlier_count)
        assert pose_err(one.transform, pairs[b][2])[1] < 0.02


def test_icp_grid_recovers_a_similarity_and_reports_exact_statistics():
    """The fixed-iteration Sim(3) ICP on a sorted-grid target (the memory's): recovers scale and pose from
    a nearby start; its fitness, inlier count and RMSE equal a brute-force evaluation at its transform;
    vmap over a batch equals the loop."""
    from scipy.spatial import cKDTree

    from cm3d.ops.grid import sort_by_cell
    from cm3d.solvers.icp import icp_grid

    src, tgt, T = make_pair(seed=3, deg=2.0, metres=0.05)
    s = 1.05
    cell = R_MAX
    pts, ok = sort_by_cell(jnp.asarray(tgt, jnp.float32), jnp.ones(N, bool), cell)
    run = jax.jit(lambda p, v, init: icp_grid(p, v, pts, ok, init, distance=cell, iterations=30, cell=cell,
                                               per_cell=8))
    src_s = jnp.asarray(src / s, jnp.float32)
    res = run(src_s, jnp.ones(N, bool), jnp.eye(4, dtype=jnp.float32))
    assert float(res.scale) == pytest.approx(s, rel=3e-3)
    dR, dt = pose_err(res.transform, T)
    assert dR < 0.5 and dt < 0.02
    A = np.asarray(res.transform, np.float64)
    d, _ = cKDTree(tgt).query(np.asarray(src_s) @ A[:3, :3].T + A[:3, 3])
    inl = d < cell
    assert int(res.inlier_count) == inl.sum() and float(res.fitness) == pytest.approx(inl.mean(), abs=1e-6)
    assert float(res.inlier_rmse) == pytest.approx(np.sqrt(np.mean(d[inl] ** 2)), rel=1e-4)
    inits = jnp.stack([jnp.eye(4, dtype=jnp.float32), jnp.asarray(T, jnp.float32)])
    batch = jax.vmap(run, in_axes=(None, None, 0))(src_s, jnp.ones(N, bool), inits)
    np.testing.assert_allclose(np.asarray(batch.transform[0]), np.asarray(res.transform), atol=1e-5)
