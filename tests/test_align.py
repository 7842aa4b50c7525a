"""Umeyama (shared with the metrics), FPFH against Open3D, RANSAC, and global registration + ICP
from far-off poses (> 90 deg) on partial-overlap visits of the synthetic world, rigid and with an
unknown scale."""

import jax
import jax.numpy as jnp
import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

import cm3d.eval.metrics
from cm3d.data import synthetic
from cm3d.ops.neighbors import build_target_index, radius_neighbors
from cm3d.solvers import align
from cm3d.solvers.align import GlobalOptions, fpfh, global_registration, ransac, umeyama_transform
from cm3d.solvers.icp import ICPOptions, icp

N, R_MAX, L = 3000, 0.3, 8192  # ICP clouds and radius as tests/test_icp.py (shared compilations)
P2L = ICPOptions(max_correspondence_distance=R_MAX, max_iterations=100)
SIM_P2L = ICPOptions(with_scale=True, kernel="tukey", kernel_scale=0.1, max_correspondence_distance=R_MAX,
                     max_iterations=100)
_build = jax.jit(build_target_index, static_argnames=("radius",))
_icp = jax.jit(icp, static_argnames="options")
_global = jax.jit(global_registration, static_argnames="options")
_ransac = jax.jit(ransac, static_argnames="options")
WORLD = synthetic.WorldConfig(height=48, width=64, fps=5.0)  # 20 frames = 4 s of camera path


def pose_err(T, T_gt):
    """(rotation error deg, translation error, scale) of a similarity 4x4 against the truth."""
    T = np.asarray(T, np.float64)
    s = np.cbrt(np.linalg.det(T[:3, :3]))
    dR = np.rad2deg(Rotation.from_matrix(T[:3, :3] / s @ T_gt[:3, :3].T).magnitude())
    return dR, np.linalg.norm(T[:3, 3] - T_gt[:3, 3]), s


@pytest.fixture(scope="module")
def visits():
    """Static points of two visits of two synthetic scenes (their views overlap partially:
    scene 4 visits 1/2 share ~88%/66% of their points, scene 5 visits 0/1 ~72%/54%)."""
    out = {}
    for scene, v in ((4, 1), (4, 2), (5, 0), (5, 1)):
        p = synthetic.generate(scene, v, 20, "none", WORLD).gt.static_points(1)
        out[scene, v] = p[np.random.default_rng(v).permutation(len(p))[:L]].astype(np.float32)
    return out


def far_pose(yaw, scale=1.0):
    """A source -> target similarity: > 90 deg about z, tilted, shifted."""
    T = np.eye(4)
    T[:3, :3] = scale * Rotation.from_euler("zyx", [yaw, 8, -6], degrees=True).as_matrix()
    T[:3, 3] = [1.5, -0.7, 0.4]
    return T


def to_source_frame(points, T):
    A = T[:3, :3]
    return ((points - T[:3, 3]) @ np.linalg.inv(A).T).astype(np.float32)


def test_one_umeyama_and_degenerate_inputs():
    assert cm3d.eval.metrics.umeyama is align.umeyama
    T = umeyama_transform(jnp.zeros((4, 3)), jnp.ones((4, 3)), None, True)
    assert np.all(np.isfinite(np.asarray(T)))
    T = umeyama_transform(jnp.ones((4, 3)), jnp.ones((4, 3)), jnp.zeros(4), False)
    assert np.all(np.isfinite(np.asarray(T)))


def test_fpfh_equals_open3d(visits):
    """Same points, normals and neighbourhood (hybrid: radius, 64 neighbours + the point): the
    histograms equal Open3D's ``compute_fpfh_feature`` (compared in float64: in float32 ~1.5% of
    the points move a pair feature that sits exactly on a bin edge; the global registration tests
    below run in float32)."""
    v = 0.1
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(visits[5, 0].astype(np.float64))).voxel_down_sample(v)
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * v, max_nn=30))
    pc.orient_normals_towards_camera_location(np.asarray(pc.points).mean(0))  # no +-pi ambiguity
    ref = np.asarray(o3d.pipelines.registration.compute_fpfh_feature(
        pc, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * v, max_nn=65)).data).T
    P, Nrm = np.asarray(pc.points), np.asarray(pc.normals)

    def ours(P, Nrm):
        nb = radius_neighbors(P, radius=5 * v, max_nn=64, max_candidates=2048)
        return fpfh(P, Nrm, nb), nb.truncated

    with jax.enable_x64(True):
        f, truncated = jax.jit(ours)(jnp.asarray(P), jnp.asarray(Nrm))
        # vmap invariance; flipped normal signs give other features (hence cm3d's oriented normals)
        Pj, Nj = jnp.asarray(P), jnp.asarray(Nrm)
        fb, _ = jax.jit(jax.vmap(ours))(jnp.stack([Pj, Pj]), jnp.stack([Nj, -Nj]))
    f, fb = np.asarray(f), np.asarray(fb)
    assert f.dtype == np.float64 and int(truncated) == 0 and len(ref) > 500
    np.testing.assert_allclose(f, ref, atol=1e-6)
    np.testing.assert_allclose(f.sum(1), 600.0)  # three histograms of 200 each
    np.testing.assert_allclose(fb[0], f, atol=1e-9)
    assert np.abs(fb[1] - f).max() > 1.0


def test_ransac_recovers_transform_with_outliers():
    rng = np.random.default_rng(0)
    src = rng.uniform(-2, 2, (400, 3)).astype(np.float32)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zyx", [150, 40, -20], degrees=True).as_matrix()
    T[:3, 3] = [1, -2, 0.5]
    dst = src @ T[:3, :3].T + T[:3, 3]
    bad = rng.random(400) < 0.8
    dst[bad] = rng.uniform(-3, 3, (bad.sum(), 3))
    opts = GlobalOptions(inlier_distance=0.05, num_samples=8192, num_hypotheses=1024, num_candidates=4)
    Ts, inl = _ransac(jnp.asarray(src), jnp.asarray(dst, jnp.float32), jnp.ones(400, bool), jax.random.key(0),
                      options=opts)
    dR, dt, _ = pose_err(Ts[0], T)
    assert dR < 0.1 and dt < 1e-3 and int(inl[0]) == int((~bad).sum())
    assert np.all(np.diff(np.asarray(inl)) <= 0)  # best first
    none, ninl = _ransac(jnp.asarray(src), jnp.asarray(dst, jnp.float32), jnp.zeros(400, bool), jax.random.key(0),
                         options=opts)
    assert np.allclose(none, np.eye(4)) and not np.any(np.asarray(ninl))


def _register_and_refine(src, tgt, options, icp_options):
    g = _global(jnp.asarray(src), jnp.asarray(tgt), jnp.ones(L, bool), jnp.ones(L, bool), jax.random.key(0),
                options=options)
    index = _build(jnp.asarray(tgt[:N]), jnp.ones(N, bool), radius=R_MAX)
    res = _icp(jnp.asarray(src[:N]), index, g.transform, jnp.ones(N, bool), options=icp_options)
    return g, res


def test_global_registration_then_icp_recovers_large_rotation(visits):
    T = far_pose(135.0)
    src, tgt = to_source_frame(visits[4, 1], T), visits[4, 2]
    g, res = _register_and_refine(src, tgt, GlobalOptions(), P2L)
    dR0, dt0, s0 = pose_err(g.transform, T)
    assert dR0 < 3.0 and dt0 < 0.2 and s0 == pytest.approx(1.0, abs=1e-5)
    assert float(g.fitness) > 0.5 and 0 < float(g.inlier_rmse) < float(g.voxel_size) * 2
    dR, dt, _ = pose_err(res.transform, T)
    assert dR < 0.5 and dt < 0.02, (dR0, dt0, dR, dt)
    # an empty source: the identity with fitness 0 (same shapes, all masked out), never NaN
    empty = _global(jnp.asarray(src), jnp.asarray(tgt), jnp.zeros(L, bool), jnp.ones(L, bool), jax.random.key(0),
                    options=GlobalOptions())
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(empty))
    assert float(empty.fitness) == 0.0 and np.allclose(empty.transform, np.eye(4))


def test_global_registration_with_unknown_scale(visits):
    T = far_pose(-110.0, scale=1.35)  # the source is a 1 / 1.35 copy
    src, tgt = to_source_frame(visits[5, 0], T), visits[5, 1]
    g, res = _register_and_refine(src, tgt, GlobalOptions.sim3(), SIM_P2L)
    dR0, dt0, s0 = pose_err(g.transform, T)
    assert dR0 < 3.0 and dt0 < 0.3 and s0 == pytest.approx(1.35, rel=0.05)
    dR, dt, s = pose_err(res.transform, T)
    assert dR < 0.5 and dt < 0.03 and s == pytest.approx(1.35, rel=0.01), (dR0, dt0, s0, dR, dt, s)
