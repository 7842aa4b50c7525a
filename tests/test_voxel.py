"""Voxel hash, downsampling and pyramid against Open3D / numpy references.

Every call goes through one jitted function per capacity on (N, 3) clouds with features, so the
whole file compiles a handful of programs (eager while loops are slow).
"""

import jax
import jax.numpy as jnp
import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree

from cm3d.ops.voxel import adaptive_voxel_size, hash_insert, hash_lookup, voxel_downsample, voxel_pyramid

N = 4000
_down = jax.jit(voxel_downsample, static_argnames=("capacity",))


def _o3d_down(p, colors, v):
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p.astype(np.float64)))
    pc.colors = o3d.utility.Vector3dVector(colors.astype(np.float64))
    d = pc.voxel_down_sample(v)
    return np.asarray(d.points), np.asarray(d.colors)


def _same_up_to_order(a, b, tol):
    assert len(a) == len(b)
    d, i = cKDTree(b[:, :3]).query(a[:, :3])
    assert d.max() < tol and len(set(i)) == len(b)
    np.testing.assert_allclose(a, b[i], atol=tol)


def _cloud(seed, lo=-2.0, hi=3.0):
    rng = np.random.default_rng(seed)
    return rng.uniform(lo, hi, (N, 3)).astype(np.float32), rng.random((N, 3)).astype(np.float32)


def test_voxel_downsample_equals_open3d():
    p, c = _cloud(0)
    for v in (0.05, 0.3):  # the voxel size is traced: one compilation
        out = _down(jnp.asarray(p), jnp.float32(v), jnp.ones(N, bool), jnp.asarray(c))
        ours = np.concatenate([np.asarray(out.points), np.asarray(out.features)], 1)[np.asarray(out.valid)]
        dp, dc = _o3d_down(p, c, v)
        assert int(out.count) == len(dp) and int(out.overflow) == 0
        _same_up_to_order(ours, np.concatenate([dp, dc], 1), 2e-5)
        assert float(jnp.sum(out.weight)) == N


def test_voxel_mask_nonfinite_and_overflow():
    p, c = _cloud(1, 0.0, 1.0)
    p[:10] = np.nan
    valid = np.random.default_rng(1).random(N) > 0.2
    out = _down(jnp.asarray(p), jnp.float32(0.1), jnp.asarray(valid), jnp.asarray(c))
    keep = valid & np.all(np.isfinite(p), 1)
    dp, dc = _o3d_down(p[keep], c[keep], 0.1)
    _same_up_to_order(np.asarray(out.points)[np.asarray(out.valid)], dp, 2e-5)
    small = _down(jnp.asarray(p), jnp.float32(0.1), jnp.asarray(valid), jnp.asarray(c), capacity=500)
    assert len(dp) > 500
    assert int(small.count) == len(dp) and int(small.overflow) == len(dp) - 500
    assert int(jnp.sum(small.valid)) == 500 and np.all(np.isfinite(np.asarray(small.points)))
    # the voxels that fit are exact voxels of the reference
    _same_up_to_order(np.asarray(small.points)[np.asarray(small.valid)],
                      dp[cKDTree(dp).query(np.asarray(small.points)[np.asarray(small.valid)])[1]], 2e-5)


def test_voxel_empty_and_bad_size():
    p, c = _cloud(2)
    out = _down(jnp.asarray(p), jnp.float32(0.1), jnp.zeros(N, bool), jnp.asarray(c))
    assert int(out.count) == 0 and not bool(jnp.any(out.valid)) and np.all(np.isfinite(np.asarray(out.points)))
    for bad in (-1.0, 0.0, np.nan):  # traced: an empty result, not NaN
        out = _down(jnp.asarray(p), jnp.float32(bad), jnp.ones(N, bool), jnp.asarray(c))
        assert int(out.count) == 0 and np.all(np.isfinite(np.asarray(out.points)))
    out0 = voxel_downsample(jnp.zeros((0, 3)), 0.1)
    assert out0.points.shape == (0, 3) and int(out0.count) == 0
    with pytest.raises(ValueError):
        voxel_downsample(jnp.zeros((5, 3)), 0.0)
    with pytest.raises(ValueError):
        voxel_downsample(jnp.zeros((5, 2)), 0.1)


def test_pyramid_levels_equal_direct_downsample():
    p, c = _cloud(3, 0.0, 2.0)
    levels = jax.jit(lambda p, c: voxel_pyramid(p, 0.05, 3, features=c))(jnp.asarray(p), jnp.asarray(c))
    origin = levels[0].origin
    for lv, v in zip(levels, (0.05, 0.1, 0.2)):
        direct = _down(jnp.asarray(p), jnp.float32(v), jnp.ones(N, bool), jnp.asarray(c), origin=origin)
        a = np.concatenate([np.asarray(lv.points), np.asarray(lv.features)], 1)[np.asarray(lv.valid)]
        b = np.concatenate([np.asarray(direct.points), np.asarray(direct.features)], 1)[np.asarray(direct.valid)]
        _same_up_to_order(a, b, 1e-5)
        np.testing.assert_allclose(float(jnp.sum(lv.weight)), N)


def test_hash_lookup_and_jit_vmap_invariance():
    rng = np.random.default_rng(4)
    keys = jnp.asarray(rng.integers(-50, 50, (N, 3)).astype(np.int32))

    @jax.jit
    def insert_lookup(keys):
        h, slot = hash_insert(keys, jnp.ones(keys.shape[0], bool))
        return h, slot, hash_lookup(h, keys), hash_lookup(h, keys + 1000)

    h, slot, found, absent = insert_lookup(keys)
    assert int(h.overflow) == 0
    np.testing.assert_array_equal(found, slot)
    assert bool(jnp.all(absent == -1))
    # equal keys share a slot, distinct keys do not
    k = np.asarray(keys)
    _, inv = np.unique(k, axis=0, return_inverse=True)
    s = np.asarray(slot)
    assert len(np.unique(s)) == inv.max() + 1 and all(len(set(inv[s == u])) == 1 for u in np.unique(s)[:50])
    p = jnp.asarray(np.stack([_cloud(5)[0], _cloud(6)[0]]))
    c = jnp.asarray(np.stack([_cloud(5)[1], _cloud(6)[1]]))
    batched = jax.jit(jax.vmap(lambda x, f: voxel_downsample(x, jnp.float32(0.2), jnp.ones(N, bool), f)))(p, c)
    for b in range(2):
        one = _down(p[b], jnp.float32(0.2), jnp.ones(N, bool), c[b])
        np.testing.assert_array_equal(batched.points[b], one.points)
        np.testing.assert_array_equal(batched.features[b], one.features)
        np.testing.assert_array_equal(batched.valid[b], one.valid)


def test_adaptive_voxel_size():
    p = jnp.asarray(np.array([[0, 0, 0], [4, 1, 2], [9, 9, 9]], np.float32))
    assert float(adaptive_voxel_size(p, jnp.array([True, True, False]), 100.0)) == pytest.approx(0.04)
