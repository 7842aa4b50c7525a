"""The sorted-layout grid search (cm3d.ops.grid) against a k-d tree, and its first-argmin reduction."""

import jax
import jax.numpy as jnp
import numpy as np

from cm3d.ops import grid


def test_first_argmin_equals_numpy_argmin_with_ties_and_inf():
    rng = np.random.default_rng(7)
    x = rng.integers(0, 4, (9, 13)).astype(np.float32)  # many ties: the first index must win
    x[2] = np.inf  # a row without any valid entry: index 0, as argmin
    x[:, 5] = np.inf
    f = jax.jit(grid.first_argmin, static_argnums=1)
    for axis in (0, 1):
        np.testing.assert_array_equal(np.asarray(f(x, axis)), np.argmin(x, axis=axis))


def test_grid_nearest_is_exact_within_a_cell():
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(0)
    p = rng.uniform(-2, 2, (3000, 3)).astype(np.float32)
    v = rng.random(3000) < 0.9
    cell = 0.3
    ps, vs = grid.sort_by_cell(jnp.asarray(p), jnp.asarray(v), cell)
    q = rng.uniform(-2.2, 2.2, (500, 3)).astype(np.float32)
    i, d2 = jax.jit(grid.grid_nearest, static_argnums=(4, 5))(jnp.asarray(q), ps, vs, cell, 1, 8)
    d, _ = cKDTree(p[v]).query(q)
    close = d < cell
    np.testing.assert_allclose(np.sqrt(np.asarray(d2))[close], d[close], atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(ps)[np.asarray(i)] - q, axis=1)[close], d[close], atol=1e-5)
    assert np.all(np.asarray(vs)[np.asarray(i)[close]])
