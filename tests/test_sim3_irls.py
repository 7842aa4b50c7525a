"""cm3d.solvers.sim3_irls: one robust Sim(3) fit recovers a known similarity through outliers."""

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from cm3d.solvers.sim3_irls import robust_sim3


def _problem(seed, n=400, outliers=0.2):
    rng = np.random.default_rng(seed)
    Q = np.eye(4)
    Q[:3, :3] = np.exp(rng.normal(0, 0.3)) * Rotation.random(random_state=seed).as_matrix()
    Q[:3, 3] = rng.normal(size=3)
    src = rng.normal(size=(n, 3)) + np.array([0.0, 0.0, 3.0])
    dst = src @ Q[:3, :3].T + Q[:3, 3] + rng.normal(0, 1e-3, (n, 3))
    bad = rng.random(n) < outliers
    dst[bad] += rng.normal(0, 1.0, (bad.sum(), 3))
    ok = np.ones(n, bool)
    ok[-20:] = False  # padding: ignored whatever it holds
    dst[-20:] = 1e3
    return Q, src, dst, ok, bad


def test_robust_sim3_recovers_a_known_similarity_through_outliers():
    Q, src, dst, ok, bad = _problem(0)
    fit = robust_sim3(jnp.asarray(src, jnp.float32), jnp.asarray(dst, jnp.float32), jnp.asarray(ok))
    np.testing.assert_allclose(np.asarray(fit.transform), Q, atol=2e-3)
    assert int(fit.num_valid) == ok.sum()
    assert abs(float(fit.inlier_fraction) - np.mean(~bad[ok])) < 0.05
    # vmap over problems = one fit each
    probs = [_problem(s) for s in (1, 2)]
    stack = lambda i, dt: jnp.asarray(np.stack([p[i] for p in probs]), dt)  # noqa: E731
    many = jax.vmap(robust_sim3)(stack(1, jnp.float32), stack(2, jnp.float32), stack(3, bool))
    for k, p in enumerate(probs):
        one = robust_sim3(jnp.asarray(p[1], jnp.float32), jnp.asarray(p[2], jnp.float32), jnp.asarray(p[3]))
        np.testing.assert_allclose(np.asarray(many.transform[k]), np.asarray(one.transform), atol=1e-5)
        np.testing.assert_allclose(np.asarray(one.transform), p[0], atol=2e-3)
