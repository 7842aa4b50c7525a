"""PointNet++ scene descriptor: sampling/grouping against NumPy, masks, jit/vmap, the shipped
weights' robustness to rigid motion and scale, weight files and gradients."""

import numpy as np
import jax
import jax.numpy as jnp
import pytest

from cm3d.data import synthetic
from cm3d.models import pointnet2 as pn

WORLD = synthetic.WorldConfig(height=30, width=40, supersample=1, fps=1.0)
CAP = 2048
single = jax.jit(pn.cloud_descriptor)  # one cloud (CAP, 3): compiled once for the module


def _ray_scene(scene, o, d):
    """Distance along unit-z rays d (R, 3) from o (3,) to the first static surface of ``scene``."""
    best = np.full(len(d), np.inf)
    for kind, half, pose in zip(scene.kind, scene.size, scene.pose):
        R, t = pose[:3, :3], pose[:3, 3]
        ol, dl = R.T @ (o - t), d @ R
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (-half - ol) / dl, (half - ol) / dl
        near, far = np.minimum(t1, t2).max(1), np.maximum(t1, t2).min(1)
        if kind == synthetic.ROOM:  # seen from inside: the exit
            hit = far
        else:
            hit = np.where((near <= far) & (near > 0), near, np.inf)
        best = np.minimum(best, hit)
    return best


def scene_cloud(seed, visit, frames=6, scale=1.0):
    """A stored-map-like cloud of a synthetic room: static surfaces seen by a visit's cameras (ray
    cast in NumPy at 30x40), in the first camera's frame times ``scale``, voxelised at extent / 40."""
    scene = synthetic.make_scene(seed, WORLD)
    cams = synthetic.camera_trajectory(scene, visit, frames, WORLD)
    Kinv = np.linalg.inv(synthetic.intrinsics(WORLD))
    v, u = np.mgrid[0:WORLD.height, 0:WORLD.width]
    rays = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1) @ Kinv.T
    pts = []
    for c in cams:
        d = rays @ c[:3, :3].T
        pts.append(c[:3, 3] + _ray_scene(scene, c[:3, 3], d)[:, None] * d)
    pts = np.concatenate(pts)
    first = np.linalg.inv(cams[0])
    pts = scale * (pts @ first[:3, :3].T + first[:3, 3])
    vs = np.max(pts.max(0) - pts.min(0)) / 40
    _, inv = np.unique(np.floor(pts / vs).astype(np.int64), axis=0, return_inverse=True)
    inv = inv.ravel()
    vox = np.zeros((inv.max() + 1, 3))
    np.add.at(vox, inv, pts)
    return (vox / np.bincount(inv)[:, None]).astype(np.float32)


def pad(points, cap=CAP, rng=None):
    """(cap, 3) points and mask; with ``rng`` the rows are scattered among garbage invalid rows."""
    n = len(points)
    assert n <= cap
    out = np.full((cap, 3), 1e6, np.float32) if rng is not None else np.zeros((cap, 3), np.float32)
    valid = np.zeros(cap, bool)
    rows = np.sort(rng.choice(cap, n, replace=False)) if rng is not None else np.arange(n)
    out[rows], valid[rows] = points, True
    return out, valid


def yaw_tilt(yaw_deg, tilt_deg):
    """Yaw about the camera y axis (gravity in a first-camera frame), then a tilt about x."""
    a, b = np.deg2rad(yaw_deg), np.deg2rad(tilt_deg)
    Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return Rx @ Ry


@pytest.fixture(scope="module")
def batch():
    """One batched, jitted call on: a room, the same room padded among garbage rows, the same room
    moved (yaw 100 deg about gravity, tilt 5 deg, translation) at another scale, another visit of that room,
    another room, and an empty cloud."""
    rng = np.random.default_rng(0)
    a = scene_cloud(3, 0)
    moved = 3.7 * a @ yaw_tilt(100, 5).T + np.array([2.0, -1.0, 5.0])
    clouds = [pad(a), pad(a, rng=rng), pad(moved.astype(np.float32)), pad(scene_cloud(3, 1, scale=0.6)),
              pad(scene_cloud(4, 0)), (np.zeros((CAP, 3), np.float32), np.zeros(CAP, bool))]
    pts, val = (np.stack(x) for x in zip(*clouds))
    out = np.asarray(jax.jit(jax.vmap(pn.cloud_descriptor))(pts, val))
    return pts, val, out


def test_shape_unit_norm_and_empty(batch):
    _, _, out = batch
    assert out.shape == (6, pn.OUT_DIM) and out.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(out[:5], axis=1), 1.0, atol=1e-5)
    np.testing.assert_array_equal(out[5], 0.0)  # empty cloud: the zero vector (matches nothing)


def test_padding_and_invalid_rows_do_not_change_the_output(batch):
    _, _, out = batch
    np.testing.assert_allclose(out[1], out[0], atol=1e-6)


def test_shipped_weights_robust_to_rigid_motion_and_scale(batch):
    _, _, out = batch
    a = scene_cloud(3, 0)
    same = out[0] @ out[2]
    assert same > 0.9, same  # yaw 100 deg + tilt 5 deg + translation + scale 3.7
    assert same > out[0] @ out[4] + 0.1 and same > out[2] @ out[4] + 0.1  # closer to itself than to another room
    assert same > out[0] @ out[3]  # the same cloud moved beats another visit of its room
    # yaw about the camera y axis alone is removed by construction (cylindrical inputs)
    yaw_only = pad((a @ yaw_tilt(-70, 0).T).astype(np.float32))
    np.testing.assert_allclose(np.asarray(single(*yaw_only)), out[0], atol=1e-4)


def test_vmap_matches_loop(batch):
    pts, val, out = batch
    for i in (0, 4):
        np.testing.assert_allclose(np.asarray(single(pts[i], val[i])), out[i], atol=1e-5)


def test_sampling_and_grouping_jit_match_eager():
    rng = np.random.default_rng(4)
    p = jnp.asarray(rng.normal(size=(60, 3)), jnp.float32)
    v = jnp.asarray(rng.random(60) < 0.8)
    q, ok = pn.resample(p, v, 32)
    qj, okj = jax.jit(pn.resample, static_argnums=2)(p, v, 32)
    np.testing.assert_allclose(np.asarray(q), np.asarray(qj), atol=1e-6)
    assert bool(ok) and bool(okj)
    idx = pn.farthest_point_sampling(pn.normalise(q), jnp.ones(32, bool), 8)
    idxj = jax.jit(lambda a: pn.farthest_point_sampling(pn.normalise(a), jnp.ones(32, bool), 8))(q)
    np.testing.assert_array_equal(np.asarray(idx), np.asarray(idxj))
    g, n = pn.ball_group(q[idx], q, jnp.ones(32, bool), 0.8, 4)
    gj, nj = jax.jit(pn.ball_group, static_argnums=(3, 4))(q[idx], q, jnp.ones(32, bool), 0.8, 4)
    np.testing.assert_array_equal(np.asarray(g), np.asarray(gj))
    np.testing.assert_array_equal(np.asarray(n), np.asarray(nj))


def _fps_numpy(p, valid, n):
    c = p[valid].mean(0)
    d0 = np.where(valid, ((p - c) ** 2).sum(1), -1.0)
    idx = [int(np.argmax(d0))]
    dist = np.where(valid, np.inf, -1.0)
    for _ in range(n - 1):
        dist = np.minimum(dist, ((p - p[idx[-1]]) ** 2).sum(1))
        idx.append(int(np.argmax(dist)))
    return np.array(idx)


def test_farthest_point_sampling_matches_numpy():
    rng = np.random.default_rng(1)
    p = rng.normal(size=(80, 3)).astype(np.float32)
    valid = rng.random(80) < 0.7
    got = np.asarray(jax.jit(pn.farthest_point_sampling, static_argnums=2)(p, valid, 20))
    np.testing.assert_array_equal(got, _fps_numpy(p.astype(np.float64), valid, 20))
    assert valid[got].all() and len(set(got.tolist())) == 20
    # fewer valid points than picks: all valid ones are picked, then repeats, never an invalid one
    few = np.zeros(80, bool)
    few[[3, 17, 40]] = True
    got = np.asarray(pn.farthest_point_sampling(jnp.asarray(p), jnp.asarray(few), 6))
    assert set(got.tolist()) == {3, 17, 40}


def test_ball_group_matches_numpy():
    rng = np.random.default_rng(2)
    p = rng.uniform(size=(120, 3)).astype(np.float32)
    valid = rng.random(120) < 0.8
    centres = np.concatenate([p[:10], [[5.0, 5.0, 5.0]]]).astype(np.float32)  # the last has an empty ball
    r, k = 0.25, 8
    idx, count = (np.asarray(x) for x in jax.jit(pn.ball_group, static_argnums=(3, 4))(centres, p, valid, r, k))
    for m, c in enumerate(centres):
        d = np.linalg.norm(p - c, axis=1)
        inside = np.flatnonzero(valid & (d <= r))  # index order, as PointNet++'s ball query
        assert count[m] == len(inside)
        if len(inside):
            want = inside[:k] if len(inside) >= k else np.concatenate([inside, np.full(k - len(inside), inside[0])])
        else:
            want = np.full(k, np.flatnonzero(valid)[np.argmin(d[valid])])
        np.testing.assert_array_equal(idx[m], want)


def test_weights_file_roundtrip_checksum_and_errors(tmp_path):
    shipped = pn.load_params()  # the shipped file loads and passes its checksum
    meta = pn.read_meta()
    assert len(meta["sha256"]) == 64 and pn.DEFAULT_WEIGHTS.stat().st_size < 5e6
    params = jax.tree.map(lambda a: a * 0.5 + 0.25, shipped)
    path = tmp_path / "w.npz"
    pn.save_params(params, path, info={"note": "test"})
    back = pn.load_params(path)
    assert jax.tree.structure(back) == jax.tree.structure(shipped)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(back)):
        np.testing.assert_array_equal(np.asarray(a, np.float16).astype(np.float32), np.asarray(b))

    data = path.read_bytes()
    bad = tmp_path / "truncated.npz"
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(pn.WeightsError, match="truncated.npz"):
        pn.load_params(bad)
    flipped = bytearray(data)
    flipped[len(data) // 2] ^= 0xFF
    bad = tmp_path / "flipped.npz"
    bad.write_bytes(bytes(flipped))
    with pytest.raises(pn.WeightsError, match="flipped.npz"):
        pn.load_params(bad)
    with pytest.raises(pn.WeightsError, match="not found"):
        pn.load_params(tmp_path / "missing.npz")
    # a well-formed file whose arrays were altered after the checksum was written
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    name = next(k for k in arrays if k != "__meta__")
    arrays[name] = arrays[name] + np.float16(0.5)
    np.savez(tmp_path / "tampered.npz", **arrays)
    with pytest.raises(pn.WeightsError, match="checksum"):
        pn.load_params(tmp_path / "tampered.npz")
    other = pn.PointNet2Config(num_points=256, centroids=(64, 16, 4))
    with pytest.raises(pn.WeightsError, match="architecture"):
        pn.load_params(path, other)


def test_gradients_are_finite_and_match_finite_differences():
    cfg = pn.PointNet2Config(num_points=64, centroids=(32, 16, 4), neighbours=(8, 8, 4))
    rng = np.random.default_rng(3)
    shapes = jax.eval_shape(lambda: pn.init_params(jax.random.PRNGKey(0), cfg))
    params = jax.tree.map(lambda s: (rng.normal(size=s.shape) / np.sqrt(s.shape[0])).astype(np.float32), shapes)
    pts = rng.normal(size=(100, 3)).astype(np.float32)
    val = rng.random(100) < 0.8
    target = rng.normal(size=pn.OUT_DIM).astype(np.float32)

    def loss(prm, p):
        return pn.apply(prm, p, val, cfg) @ target

    vg = jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))
    _, (gp, gx) = vg(params, pts)
    leaves = jax.tree.leaves(gp)
    assert all(np.isfinite(np.asarray(g)).all() for g in leaves) and np.isfinite(np.asarray(gx)).all()
    assert all(np.abs(np.asarray(g)).max() > 0 for g in leaves)
    # central difference along random head weights (the descriptor is smooth in them)
    v = jax.tree.map(np.zeros_like, params)  # NumPy on the host: no eager JAX op to compile
    v["head"]["kernel"] = rng.normal(size=params["head"]["kernel"].shape).astype(np.float32)
    eps = 1e-3
    lp, _ = vg(jax.tree.map(lambda a, b: a + eps * b, params, v), pts)
    lm, _ = vg(jax.tree.map(lambda a, b: a - eps * b, params, v), pts)
    analytic = sum(float(np.sum(np.asarray(a) * b)) for a, b in zip(jax.tree.leaves(gp), jax.tree.leaves(v)))
    np.testing.assert_allclose(float(analytic), float((lp - lm) / (2 * eps)), rtol=2e-2, atol=1e-3)
