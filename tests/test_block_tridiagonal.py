"""cm3d.solvers.block_tridiagonal: the O(N) solve and the inverse's blocks against dense NumPy."""

import jax
import jax.numpy as jnp
import numpy as np

from cm3d.solvers.block_tridiagonal import block_tridiagonal


def test_block_tridiagonal_equals_dense_numpy():
    rng = np.random.default_rng(2)
    n = 5
    band = np.abs(np.subtract.outer(np.arange(6 * n) // 6, np.arange(6 * n) // 6)) <= 1
    L = rng.normal(size=(6 * n, 6 * n)) * band
    H = (L @ L.T + 6 * n * np.eye(6 * n)) * band
    b = rng.normal(size=6 * n)
    blk = lambda i, j: H[6 * i:6 * i + 6, 6 * j:6 * j + 6]  # noqa: E731
    with jax.enable_x64(True):  # float64: checked against NumPy to 1e-9
        D = jnp.asarray(np.stack([blk(i, i) for i in range(n)]))
        U = jnp.asarray(np.stack([blk(i, i + 1) for i in range(n - 1)]))
        x, Pd, C = (np.asarray(v) for v in block_tridiagonal(D, U, jnp.asarray(b.reshape(n, 6))))
    Hi = np.linalg.inv(H)
    np.testing.assert_allclose(x.ravel(), np.linalg.solve(H, b), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(Pd, np.stack([Hi[6 * i:6 * i + 6, 6 * i:6 * i + 6] for i in range(n)]), atol=1e-12)
    np.testing.assert_allclose(C, np.stack([Hi[6 * i:6 * i + 6, 6 * i + 6:6 * i + 12] for i in range(n - 1)]),
                               atol=1e-12)
