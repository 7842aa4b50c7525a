"""GMM EM in JAX against scikit-learn, degenerate inputs, jit/vmap invariance."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from sklearn.metrics import adjusted_rand_score
from sklearn.mixture import GaussianMixture

from cm3d.ops import gmm

FIT = jax.jit(gmm.fit_gmm, static_argnums=1)


def _blobs(seed=0, n=1500):
    rng = np.random.default_rng(seed)
    centres = np.array([[0.0, 0.0], [8.0, 1.0], [-3.0, 9.0]])
    covs = [np.array([[1.0, 0.3], [0.3, 0.5]]), np.array([[0.4, -0.2], [-0.2, 1.2]]), np.eye(2) * 0.7]
    sizes = [n, n // 2, n // 3]
    x = np.concatenate([rng.multivariate_normal(c, s, size=k) for c, s, k in zip(centres, covs, sizes)])
    y = np.concatenate([np.full(k, i) for i, k in enumerate(sizes)])
    return x.astype(np.float32), y


def _sorted(means, *others):
    order = np.lexsort((np.asarray(means)[:, 1], np.asarray(means)[:, 0]))
    return [np.asarray(a)[order] for a in (means, *others)]


def test_same_clusters_as_sklearn_on_separable_data():
    x, y = _blobs()
    res = FIT(x, gmm.GMMConfig(num_components=3, max_iters=100, tol=1e-6))
    sk = GaussianMixture(3, covariance_type="full", random_state=0, tol=1e-6, max_iter=100).fit(x.astype(np.float64))
    assert adjusted_rand_score(sk.predict(x), np.asarray(res.labels)) == 1.0
    assert adjusted_rand_score(y, np.asarray(res.labels)) == 1.0
    m, c, w = _sorted(res.means, res.covariances, res.weights)
    ms, cs, ws = _sorted(sk.means_, sk.covariances_, sk.weights_)
    np.testing.assert_allclose(m, ms, atol=1e-3)
    np.testing.assert_allclose(c, cs, atol=1e-3)
    np.testing.assert_allclose(w, ws, atol=1e-4)
    np.testing.assert_allclose(float(res.log_likelihood), sk.score(x.astype(np.float64)), atol=1e-4)
    assert bool(res.converged) and int(res.iterations) < 100


def test_same_start_same_iterates_as_sklearn():
    """From the same initial parameters, 20 EM iterations with tol=0 land where scikit-learn does."""
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.normal([0, 0], 1.0, (800, 2)), rng.normal([2.5, 0.5], 0.7, (400, 2))]).astype(np.float32)
    cfg = gmm.GMMConfig(num_components=3, max_iters=20, tol=0.0, seed=1)
    w0, m0, c0 = (np.asarray(a, np.float64) for a in jax.jit(gmm.initial_parameters, static_argnums=1)(x, cfg))
    res = FIT(x, cfg)
    assert int(res.iterations) == 20
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sk = GaussianMixture(3, covariance_type="full", max_iter=20, tol=0.0, init_params="random_from_data",
                             weights_init=w0 / w0.sum(), means_init=m0, precisions_init=np.linalg.inv(c0),
                             random_state=0).fit(x.astype(np.float64))
    np.testing.assert_allclose(res.means, sk.means_, atol=2e-4)
    np.testing.assert_allclose(res.covariances, sk.covariances_, atol=2e-4)
    np.testing.assert_allclose(res.weights, sk.weights_, atol=2e-5)
    assert adjusted_rand_score(sk.predict(x.astype(np.float64)), np.asarray(res.labels)) == 1.0


@pytest.mark.parametrize("case", ["constant", "zeros", "two_values", "one_point_valid", "none_valid"])
def test_degenerate_input_is_finite(case):
    n = 400
    valid = np.ones(n, bool)
    if case == "constant":
        x = np.full((n, 2), [3.0, -1.5], np.float32)
    elif case == "zeros":
        x = np.zeros((n, 2), np.float32)
    elif case == "two_values":
        x = np.where(np.arange(n)[:, None] % 2 == 0, [1.0, 2.0], [5.0, 2.0]).astype(np.float32)
    elif case == "one_point_valid":
        x = np.random.default_rng(0).normal(size=(n, 2)).astype(np.float32)
        valid = np.arange(n) == 7
    else:
        x = np.random.default_rng(0).normal(size=(n, 2)).astype(np.float32)
        valid = np.zeros(n, bool)
    res = FIT(x, gmm.GMMConfig(num_components=3, max_iters=30), valid)
    for leaf in jax.tree.leaves(res):
        assert np.all(np.isfinite(np.asarray(leaf, np.float64))), (case, leaf)
    assert np.all((np.asarray(res.labels) >= 0) & (np.asarray(res.labels) < 3))
    if case != "none_valid":
        np.testing.assert_allclose(float(jnp.sum(res.weights)), 1.0, atol=1e-4)
    if case == "two_values":  # two distinct vectors never share a label
        lab = np.asarray(res.labels)
        assert len(set(lab[::2])) == 1 and len(set(lab[1::2])) == 1 and lab[0] != lab[1]
    mask = np.asarray(jax.jit(gmm.slowest_component_mask)(res, valid))
    assert mask.shape == (n,) and not mask[~valid].any()


def test_jit_vmap_invariance():
    xs = np.stack([_blobs(s, 300)[0] for s in range(3)])
    cfg = gmm.GMMConfig(num_components=3, max_iters=40, tol=1e-4)
    batched = jax.jit(jax.vmap(gmm.fit_gmm, in_axes=(0, None)), static_argnums=1)(xs, cfg)
    for i in range(3):
        single = FIT(xs[i], cfg)
        np.testing.assert_array_equal(batched.labels[i], single.labels)
        np.testing.assert_allclose(batched.means[i], single.means, atol=1e-4)
        np.testing.assert_allclose(batched.covariances[i], single.covariances, atol=1e-4)


def test_slowest_component_is_static():
    rng = np.random.default_rng(5)
    static = rng.normal(0.0, 0.2, (600, 2))
    movers = np.concatenate([rng.normal([6.0, 0.0], 0.3, (100, 2)), rng.normal([0.0, -7.0], 0.3, (80, 2))])
    x = np.concatenate([static, movers]).astype(np.float32)
    mask = np.asarray(jax.jit(gmm.slowest_component_mask)(FIT(x, gmm.GMMConfig(3))))
    np.testing.assert_array_equal(mask, np.arange(len(x)) >= 600)


def test_config_validation():
    with pytest.raises(ValueError):
        gmm.GMMConfig(num_components=0)
    with pytest.raises(ValueError):
        gmm.fit_gmm(np.zeros((5, 3), np.float32))
