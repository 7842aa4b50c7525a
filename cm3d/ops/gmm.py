"""Gaussian mixture on 2D vectors (optical flow), fitted by EM in JAX (the paper's flow cue).

Full 2x2 covariances, seeded k-means++ initialisation, at most ``max_iters`` EM iterations in one
``lax.while_loop`` (early stop at ``tol``; ``tol=0`` runs all, as scikit-learn). Matches
``sklearn.mixture.GaussianMixture(covariance_type="full")`` from the same start. The E and M steps
are contractions over the quadratic features ``phi = [1, x, y, x^2, xy, y^2]`` (6, N); points are
normalised by their mean and RMS spread first. Degenerate input never gives NaN (docs/motion.md).
Entry points: :func:`fit_gmm`, :func:`slowest_component_mask`.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
from flax import struct

_EPS = 10.0 * float(jnp.finfo(jnp.float32).eps)
_LOG_2PI = math.log(2.0 * math.pi)
_REL_FLOOR = 1e-6


@dataclasses.dataclass(frozen=True)
class GMMConfig:
    """num_components K (static), max_iters, tol on the mean log-likelihood change, reg_covar
    (added to covariance diagonals, input units squared), seed of the k-means++ initialisation."""

    num_components: int = 3
    max_iters: int = 50
    tol: float = 1e-3
    reg_covar: float = 1e-6
    seed: int = 0

    def __post_init__(self):
        if self.num_components < 1:
            raise ValueError("GMMConfig.num_components: must be >= 1")
        if self.max_iters < 0:
            raise ValueError("GMMConfig.max_iters: must be >= 0")
        if self.tol < 0 or self.reg_covar < 0:
            raise ValueError("GMMConfig.tol and reg_covar: must be >= 0")


@struct.dataclass
class GMMResult:
    """labels (N,) int32 argmax responsibility; means (K, 2); covariances (K, 2, 2); weights (K,);
    log_likelihood: mean per valid point (scalar); iterations run (int32); converged (bool)."""

    labels: jnp.ndarray
    means: jnp.ndarray
    covariances: jnp.ndarray
    weights: jnp.ndarray
    log_likelihood: jnp.ndarray
    iterations: jnp.ndarray
    converged: jnp.ndarray


def _features(x, y):
    return jnp.stack([jnp.ones_like(x), x, y, x * x, x * y, y * y])


def _params_from_moments(S: jnp.ndarray, total: jnp.ndarray, reg: jnp.ndarray):
    """Weights, means, covariances from per-component moment sums S (K, 6) (M step). Variances are
    clipped at 0 and floored at ``reg + 1e-6 E[x^2]`` (float32 cancellation), so every covariance is
    positive definite."""
    nk = S[:, 0] + _EPS
    mx, my = S[:, 1] / nk, S[:, 2] / nk
    exx, eyy = S[:, 3] / nk, S[:, 5] / nk
    cxx = jnp.maximum(exx - mx * mx, 0.0) + reg + _REL_FLOOR * exx
    cyy = jnp.maximum(eyy - my * my, 0.0) + reg + _REL_FLOOR * eyy
    lim = 0.999 * jnp.sqrt(cxx * cyy)
    cxy = jnp.clip(S[:, 4] / nk - mx * my, -lim, lim)
    weights = nk / jnp.maximum(total + S.shape[0] * _EPS, _EPS)
    means = jnp.stack([mx, my], -1)
    cov = jnp.stack([jnp.stack([cxx, cxy], -1), jnp.stack([cxy, cyy], -1)], -2)
    return weights, means, cov


def _log_density_coefficients(weights, means, cov):
    """(K, 6) coefficients W with ``W . phi(x) = log(pi_k) + log N(x | mu_k, cov_k)``."""
    cxx, cxy, cyy = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    det = jnp.maximum(cxx * cyy - cxy * cxy, 1e-30)
    pxx, pxy, pyy = cyy / det, -cxy / det, cxx / det
    mx, my = means[:, 0], means[:, 1]
    bx, by = pxx * mx + pxy * my, pxy * mx + pyy * my
    a = jnp.log(jnp.maximum(weights, 1e-30)) - 0.5 * (mx * bx + my * by) - 0.5 * jnp.log(det) - _LOG_2PI
    return jnp.stack([a, bx, by, -0.5 * pxx, -pxy, -0.5 * pyy], -1)


def _e_step(coef, phi):
    """Log-densities ``coef @ phi`` (K, N) -> (responsibilities (K, N), per-point log-likelihood (N,)).
    The log-sum-exp over K is unrolled row by row (faster on XLA:CPU)."""
    logp = coef @ phi
    rows = [logp[k] for k in range(logp.shape[0])]
    m = rows[0]
    for r in rows[1:]:
        m = jnp.maximum(m, r)
    e = [jnp.exp(r - m) for r in rows]
    s = e[0]
    for r in e[1:]:
        s = s + r
    inv = 1.0 / s
    return jnp.stack([r * inv for r in e]), m + jnp.log(s)


def _argmax_rows(resp):
    """argmax over the leading (K) axis, unrolled (first maximum wins, like ``jnp.argmax``)."""
    best, arg = resp[0], jnp.zeros(resp.shape[1:], jnp.int32)
    for k in range(1, resp.shape[0]):
        better = resp[k] > best
        best, arg = jnp.where(better, resp[k], best), jnp.where(better, k, arg)
    return arg


def _kmeans_pp(x, y, w, K: int, key):
    """Seeded k-means++ centres (K, 2) of points given as rows x, y (N,): D^2 sampling by inverse
    CDF, one uniform number per centre."""
    u = jax.random.uniform(key, (K,))
    N = x.shape[0]

    def pick(p, ui):
        tot = jnp.sum(p)
        p = jnp.where(tot > 0, p, w)  # every remaining distance is zero: sample uniformly
        tot = jnp.where(tot > 0, tot, jnp.sum(w))
        i = jnp.searchsorted(jnp.cumsum(p), ui * tot, side="right")
        return jnp.clip(i, 0, N - 1)

    def dist2(c):
        return (x - c[0]) ** 2 + (y - c[1]) ** 2

    i0 = pick(w, u[0])
    first = jnp.stack([x[i0], y[i0]])
    centres = jnp.zeros((K, 2), x.dtype).at[0].set(first)

    def body(k, carry):
        centres, d2 = carry
        i = pick(d2 * w, u[k])
        c = jnp.stack([x[i], y[i]])
        return centres.at[k].set(c), jnp.minimum(d2, dist2(c))

    centres, _ = jax.lax.fori_loop(1, K, body, (centres, dist2(first)))
    return centres


def _standardize(x, w):
    """Rows (2, N) of the points (N, 2) shifted by their weighted mean and divided by their RMS
    spread (1 when they do not spread); returns (rows, mean (2,), scale)."""
    rows = x.T
    tot = jnp.maximum(jnp.sum(w), 1.0)
    mu = jnp.sum(rows * w, 1) / tot
    c = rows - mu[:, None]
    var = jnp.sum(c * c * w) / (2.0 * tot)
    scale = jnp.where(var > 1e-20, jnp.sqrt(var), 1.0)
    return c / scale, mu, scale


def initial_parameters(x, cfg: GMMConfig = GMMConfig(), valid=None):
    """Parameters after the k-means++ initialisation (weights (K,), means (K, 2), covariances (K, 2, 2))
    in input units: hard assignment to the nearest seeded k-means++ centre, then one M step."""
    x = jnp.asarray(x, jnp.float32)
    w = jnp.ones(x.shape[:1], x.dtype) if valid is None else jnp.asarray(valid).astype(x.dtype)
    z, mu, scale = _standardize(x, w)
    wts, means, cov = _init_standardized(z, w, cfg, cfg.reg_covar / scale**2)
    return wts, means * scale + mu, cov * scale**2


def _init_standardized(z, w, cfg, reg):
    K = cfg.num_components
    x, y = z[0], z[1]
    centres = _kmeans_pp(x, y, w, K, jax.random.PRNGKey(cfg.seed))
    d2 = jnp.stack([(x - centres[k, 0]) ** 2 + (y - centres[k, 1]) ** 2 for k in range(K)])
    hard = jax.nn.one_hot(_argmax_rows(-d2), K, dtype=z.dtype, axis=0) * w
    return _params_from_moments(hard @ _features(x, y).T, jnp.sum(w), reg)


def fit_gmm(x, cfg: GMMConfig = GMMConfig(), valid=None, init=None) -> GMMResult:
    """Fit a K-component full-covariance GMM to points x (N, 2) by EM; labels for every point.

    valid: optional (N,) bool; invalid points are labelled but do not enter the fit. init: optional
    (weights (K,), means (K, 2), covariances (K, 2, 2)) replacing k-means++. Jittable (``cfg``
    static); under ``vmap`` a custom batching rule maps the single-frame program over the frames.
    """
    x = jnp.asarray(x, jnp.float32)
    if x.ndim != 2 or x.shape[-1] != 2:
        raise ValueError(f"fit_gmm: x must be (N, 2), got {x.shape}")
    K = cfg.num_components
    w = jnp.ones(x.shape[:1], x.dtype) if valid is None else jnp.asarray(valid).astype(x.dtype)
    if init is None:
        init_arrays = (jnp.zeros((K,)), jnp.zeros((K, 2)), jnp.zeros((K, 2, 2)))
    else:
        init_arrays = tuple(jnp.asarray(a, jnp.float32) for a in init)

    @jax.custom_batching.custom_vmap
    def core(x, w, wi, mi, ci):
        return _fit(x, w, (wi, mi, ci) if init is not None else None, cfg)

    @core.def_vmap
    def _core_vmap(axis_size, in_batched, *args):
        args = [a if b else jnp.broadcast_to(a, (axis_size,) + a.shape) for a, b in zip(args, in_batched)]
        out = jax.lax.map(lambda a: core(*a), tuple(args))
        return out, jax.tree.map(lambda _: True, out)

    return core(x, w, *init_arrays)


def _fit(x, w, init, cfg: GMMConfig) -> GMMResult:
    z, mu, scale = _standardize(x, w)
    reg = cfg.reg_covar / scale**2
    phi = _features(z[0], z[1])
    phi_wt = (phi * w).T  # (N, 6)
    total = jnp.sum(w)
    if init is None:
        params = _init_standardized(z, w, cfg, reg)
    else:
        wi, mi, ci = init
        params = (wi, (mi - mu) / scale, ci / scale**2)

    def mean_ll(ll):
        return jnp.sum(ll * w) / jnp.maximum(total, 1.0)

    def cond(state):
        _, prev, cur, it = state
        return (it < cfg.max_iters) & ((it < 1) | ~(jnp.abs(cur - prev) < cfg.tol))

    def body(state):
        params, _, cur, it = state
        resp, ll = _e_step(_log_density_coefficients(*params), phi)
        return _params_from_moments(resp @ phi_wt, total, reg), cur, mean_ll(ll), it + 1

    inf = jnp.asarray(jnp.inf, x.dtype)
    params, prev, cur, it = jax.lax.while_loop(cond, body, (params, -inf, -inf, jnp.int32(0)))
    resp, ll = _e_step(_log_density_coefficients(*params), phi)
    weights, means, cov = params
    return GMMResult(
        labels=_argmax_rows(resp),
        means=means * scale + mu,
        covariances=cov * scale**2,
        weights=weights,
        log_likelihood=mean_ll(ll) - 2.0 * jnp.log(scale),
        iterations=it,
        converged=jnp.abs(cur - prev) < cfg.tol,
    )


def slowest_component_mask(result: GMMResult, valid=None) -> jnp.ndarray:
    """(N,) bool: points NOT in the component of smallest mean magnitude ``|mu_k|`` (the moving ones).

    Components that own no valid point are ignored when choosing the slowest one.
    """
    K = result.means.shape[0]
    owned = jax.nn.one_hot(result.labels, K, dtype=jnp.float32)
    if valid is not None:
        owned = owned * jnp.asarray(valid, jnp.float32)[:, None]
    present = jnp.sum(owned, 0) > 0
    mag = jnp.where(present, jnp.linalg.norm(result.means, axis=-1), jnp.inf)
    mask = result.labels != jnp.argmin(mag)
    return mask if valid is None else mask & jnp.asarray(valid, bool)
