"""The z-buffer point renderer (cm3d.eval.render) against a brute-force NumPy render."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cm3d.eval import render

H, W = 24, 32
K = np.array([[30.0, 0.0, 15.5], [0.0, 30.0, 11.5], [0.0, 0.0, 1.0]])


def _pose(seed):
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(0, 0.2, 3)).as_matrix()
    T[:3, 3] = rng.normal(0, 0.3, 3)
    return T


def _cloud(seed, n, pose):
    """Points in front of the camera (a few behind it and outside the image too), in the world."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform([-4, -4], [W + 4, H + 4], (n, 2))
    z = rng.uniform(-0.5, 4.0, n)
    pc = np.concatenate([(uv - K[:2, 2]) / K[0, 0] * np.abs(z)[:, None], z[:, None]], -1)
    return pc @ pose[:3, :3].T + pose[:3, 3]


def brute_force(points, valid, pose, K, radius, tolerance=0.0):
    """Loop over points and splat offsets: per pixel the list of camera z written, then the mean
    of those within (1 + tolerance) of the minimum."""
    writes = [[[] for _ in range(W)] for _ in range(H)]
    pc = (points - pose[:3, 3]) @ pose[:3, :3]
    for p, ok in zip(pc, valid):
        if not ok or p[2] <= 1e-6:
            continue
        u = (K[0, 0] * p[0] + K[0, 1] * p[1]) / p[2] + K[0, 2]
        v = K[1, 1] * p[1] / p[2] + K[1, 2]
        cu, cv = int(np.round(u)), int(np.round(v))
        for dv in range(-radius, radius + 1):
            for du in range(-radius, radius + 1):
                r, c = cv + dv, cu + du
                if 0 <= r < H and 0 <= c < W:
                    writes[r][c].append(p[2])
    depth = np.zeros((H, W))
    for r in range(H):
        for c in range(W):
            z = np.array(writes[r][c])
            if len(z):
                depth[r, c] = z[z <= z.min() * (1 + tolerance)].mean()
    return depth, depth > 0


def test_zbuffer_keeps_the_nearest_point():
    pose = _pose(0)
    ray = np.array([0.1, -0.05, 1.0])
    pc = np.stack([ray * 2.0, ray * 1.0, ray * 3.0])  # same pixel, the middle one is nearest
    pts = pc @ pose[:3, :3].T + pose[:3, 3]
    for order in ([0, 1, 2], [2, 1, 0], [1, 0, 2]):
        depth, covered = render.render_depth(pts[order].astype(np.float32), np.ones(3, bool), pose, K, height=H, width=W)
        assert int(covered.sum()) == 1
        assert float(depth.max()) == pytest.approx(1.0, rel=1e-6)
        soft, _ = render.render_depth(pts[order].astype(np.float32), np.ones(3, bool), pose, K, height=H, width=W,
                                      tolerance=1.5)  # 1 and 2 within 2.5x of the nearest, 3 not
        assert float(soft.max()) == pytest.approx(1.5, rel=1e-6)
    # an invalid (padding) point never wins, even when nearest
    depth, _ = render.render_depth(pts.astype(np.float32), np.array([True, False, True]), pose, K, height=H, width=W)
    assert float(depth.max()) == pytest.approx(2.0, rel=1e-6)


@pytest.mark.parametrize("radius,tolerance", [(0, 0.0), (1, 0.0), (1, 0.3)])
def test_matches_brute_force_numpy(radius, tolerance):
    pose = _pose(1)
    pts = _cloud(2, 400, pose)
    valid = np.random.default_rng(3).random(len(pts)) > 0.1
    want, want_cov = brute_force(pts, valid, pose, K, radius, tolerance)
    with jax.enable_x64(True):
        got, cov = render.render_depth(jnp.asarray(pts), jnp.asarray(valid), pose, K, height=H, width=W,
                                       radius=radius, tolerance=tolerance)
        got, cov = np.asarray(got), np.asarray(cov)
    assert want_cov.sum() > 50 and (~want_cov).sum() > 10  # the test sees both filled and empty pixels
    np.testing.assert_array_equal(cov, want_cov)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=0)
    if tolerance > 0:  # the soft z-buffer really averaged several writes somewhere
        hard, _ = brute_force(pts, valid, pose, K, radius)
        assert np.sum(~np.isclose(want, hard)) > 5


def test_jit_equals_eager_and_batch_equals_loop():
    poses = np.stack([_pose(s) for s in (4, 5, 6)])
    pts, valid = render.pad_points(_cloud(7, 300, poses[0]).astype(np.float32), 512)
    assert valid.sum() == 300 and pts.shape == (512, 3)
    depth, covered = render.render_depths(pts, valid, poses, K, height=H, width=W, radius=1)
    with jax.disable_jit():  # the single-camera function, op by op, one camera at a time
        eager = [render.render_depth(pts, valid, p, K, height=H, width=W, radius=1) for p in poses]
    np.testing.assert_array_equal(np.asarray(depth), np.stack([np.asarray(d) for d, _ in eager]))
    np.testing.assert_array_equal(np.asarray(covered), np.stack([np.asarray(c) for _, c in eager]))
    assert np.asarray(covered[0]).sum() > 0


def test_bad_input_names_the_field():
    with pytest.raises(ValueError, match="points must be"):
        render.render_depth(np.zeros((5, 2)), np.ones(5, bool), np.eye(4), K, height=H, width=W)
    with pytest.raises(ValueError, match="valid must be"):
        render.render_depth(np.zeros((5, 3)), np.ones(4, bool), np.eye(4), K, height=H, width=W)
    with pytest.raises(ValueError, match="capacity"):
        render.pad_points(np.zeros((5, 3)), 4)
