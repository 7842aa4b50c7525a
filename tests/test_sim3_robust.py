"""ops.sim3, ops.robust and camera back-projection against NumPy / SciPy references."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from cm3d.ops import camera, robust, sim3


def _random_sim3(rng, n):
    R = Rotation.random(n, random_state=rng).as_matrix()
    s = np.exp(rng.uniform(-1, 1, n))
    t = rng.normal(size=(n, 3))
    return sim3.from_parts(s, R, t), s, R, t


def test_sim3_parts_apply_inverse():
    rng = np.random.default_rng(0)
    A, s, R, t = _random_sim3(rng, 5)
    x = rng.normal(size=(5, 7, 3))
    np.testing.assert_allclose(sim3.scale(A), s, rtol=1e-12)
    np.testing.assert_allclose(sim3.rotation(A), R, atol=1e-12)
    np.testing.assert_allclose(sim3.apply(A, x), s[:, None, None] * np.einsum("kij,knj->kni", R, x) + t[:, None], atol=1e-12)
    np.testing.assert_allclose(sim3.inverse(A), np.linalg.inv(A), atol=1e-10)
    np.testing.assert_allclose(sim3.to_rigid(A)[:, :3, :3], R, atol=1e-12)
    assert isinstance(sim3.inverse(A), np.ndarray) and sim3.inverse(A).dtype == np.float64
    # the JAX path gives the same numbers, under jit too
    Aj = jnp.asarray(A, jnp.float32)
    np.testing.assert_allclose(jax.jit(sim3.inverse)(Aj), np.linalg.inv(A), atol=1e-4)
    np.testing.assert_allclose(jax.jit(sim3.apply)(Aj, jnp.asarray(x, jnp.float32)), sim3.apply(A, x), atol=1e-4)


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 10_000))
def test_sim3_exp_log_round_trip(seed):
    rng = np.random.default_rng(seed)
    w = rng.normal(size=3)
    w *= rng.uniform(0.0, 3.0) / np.linalg.norm(w)  # log is the inverse of exp only for |w| < pi
    p = np.concatenate([w, rng.normal(size=3), rng.uniform(-1, 1, 1)]).astype(np.float32)
    A = sim3.exp(p)
    np.testing.assert_allclose(sim3.log(A), p, atol=2e-5)
    np.testing.assert_allclose(sim3.scale(A), np.exp(p[6]), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(A[:3, :3]) / np.exp(p[6]), Rotation.from_rotvec(p[:3]).as_matrix(), atol=1e-5)
    batch = np.stack([p, -p])
    np.testing.assert_allclose(jax.vmap(sim3.log)(sim3.exp(batch)), batch, atol=2e-5)


@settings(max_examples=30, deadline=None)
@given(st.integers(1, 40), st.integers(0, 10_000))
def test_masked_median_matches_numpy(n, seed):
    rng = np.random.default_rng(seed)
    # n values in a row padded to 40 (one shape, one compilation for every example)
    x = rng.normal(size=(3, 40)).astype(np.float32)
    valid = (rng.random((3, 40)) < 0.6) & (np.arange(40) < n)
    got = np.asarray(_median(x, valid))
    for row in range(3):
        want = np.median(x[row][valid[row]]) if valid[row].any() else 0.0
        np.testing.assert_allclose(got[row], want, rtol=1e-6, atol=1e-6)
    # along another axis
    np.testing.assert_allclose(_median_axis0(x.T, valid.T), got, atol=1e-6)


_median = jax.jit(robust.masked_median)
_median_axis0 = jax.jit(lambda x, v: robust.masked_median(x, v, 0))


def test_mad_sigma_and_robust_sigma():
    rng = np.random.default_rng(1)
    x = rng.normal(3.0, 2.0, 20_001)
    valid = np.ones_like(x, bool)
    assert abs(float(robust.mad_sigma(x, valid)) - 2.0) < 0.05
    r = rng.normal(0.0, 0.5, 20_001)
    assert abs(float(robust.robust_sigma(r, valid)) - 0.5) < 0.02


@pytest.mark.parametrize("dof", [3, 6, 7, 60, 600])
@pytest.mark.parametrize("q", [0.9, 0.99, 0.999])
def test_chi2_quantile_matches_scipy(q, dof):
    np.testing.assert_allclose(float(robust.chi2_quantile(q, dof)), chi2.ppf(q, dof), rtol=0.02)


def test_backproject_inverts_project():
    rng = np.random.default_rng(2)
    K = np.array([[300.0, 0, 160], [0, 310, 120], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.normal(size=3)
    uv = rng.uniform(0, 300, (50, 2))
    z = rng.uniform(0.5, 5, 50)
    pw = camera.backproject(uv, z, K, T)
    uv2, z2 = camera.project(jnp.asarray(pw, jnp.float32), jnp.asarray(K, jnp.float32), jnp.asarray(T, jnp.float32))
    np.testing.assert_allclose(uv2, uv, atol=2e-2)
    np.testing.assert_allclose(z2, z, rtol=1e-5)
    assert isinstance(pw, np.ndarray)
    # the dense grid version agrees with the pixel-list version
    depth = rng.uniform(1, 2, (4, 5))
    grid = np.asarray(camera.pixel_grid(4, 5, jnp.float32)).reshape(-1, 2)
    dense = np.asarray(camera.unproject_camera(jnp.asarray(depth, jnp.float32), jnp.asarray(K, jnp.float32))).reshape(-1, 3)
    np.testing.assert_allclose(camera.backproject(grid.astype(np.float64), depth.reshape(-1), K), dense, rtol=1e-5)


@settings(max_examples=30, deadline=None)
@given(st.integers(1, 40), st.integers(0, 10_000))
def test_masked_median_low_matches_statistics(n, seed):
    import statistics

    rng = np.random.default_rng(seed)
    x = rng.normal(size=(4, 40)).astype(np.float32)
    valid = (rng.random((4, 40)) < 0.6) & (np.arange(40) < n)  # n values per row, padded to one shape
    want = statistics.median_low(x[valid].tolist()) if valid.any() else 0.0
    assert float(_MEDIAN_LOW(x, valid)) == want


_MEDIAN_LOW = jax.jit(robust.masked_median_low)


_KTH = jax.jit(robust.kth_smallest)


@pytest.mark.parametrize("seed", range(4))
def test_kth_smallest_equals_the_sorted_value(seed):
    """Radix select returns exactly the sorted array's k-th value: ties, both infinities, NaN (sorted
    last), -0.0, magnitudes over 10 decades, rows with few or no valid entries."""
    rng = np.random.default_rng(seed)
    x = (rng.normal(size=(6, 257)) * 10.0 ** rng.uniform(-5, 5, (6, 257))).astype(np.float32)
    x[0] = np.round(x[0] * 1e-3)  # many ties, zeros of both signs
    x[0, :5] = -0.0
    x[1, rng.random(257) < 0.1] = np.inf
    x[2, rng.random(257) < 0.1] = -np.inf
    x[3, rng.random(257) < 0.05] = np.nan
    valid = rng.random((6, 257)) < 0.7
    valid[4] = rng.random(257) < 0.02
    valid[5] = False
    k = rng.integers(0, 257, 6)
    want = np.take_along_axis(np.sort(np.where(valid, x, np.inf), -1), k[:, None], -1)[:, 0]
    got = np.asarray(_KTH(x, valid, k))
    assert np.array_equal(got, want, equal_nan=True)  # -0.0 == 0.0 here, as in the sort
    g = jax.grad(lambda a: robust.kth_smallest(a, valid[:1], 7)[0])(jnp.asarray(np.abs(x[4:5]) + 1))
    assert float(g.sum()) == 1.0 and int((g != 0).sum()) == 1  # the gradient reaches the element chosen
