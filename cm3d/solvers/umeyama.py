"""Closed-form least-squares point-set fits: Umeyama's similarity (or rigid) transform."""

from __future__ import annotations

import jax.numpy as jnp

from cm3d.ops import sim3


def umeyama(src, dst, weights=None, with_scale: bool = True):
    """Least-squares similarity ``dst ≈ s R src + t`` (Umeyama 1991, reflection-safe).

    src, dst: (N, 3); weights: None, or (N,) non-negative weights / boolean valid mask.
    Returns (s scalar, R (3, 3), t (3,)); ``s = 1`` when ``with_scale`` is False. With a 0/1 mask this
    equals evo's ``umeyama_alignment`` on the valid points. Degenerate inputs (no weight, or all
    valid points equal) give ``s = 1`` and a finite R, never NaN; fewer than 3 non-collinear points
    leave the rotation about the degenerate axis arbitrary.
    """
    src = jnp.asarray(src)
    dst = jnp.asarray(dst, dtype=src.dtype)
    w = jnp.ones(src.shape[:1], src.dtype) if weights is None else jnp.asarray(weights).astype(src.dtype)
    w = w / jnp.maximum(jnp.sum(w), jnp.finfo(src.dtype).tiny)
    mu_s = jnp.sum(w[:, None] * src, axis=0)
    mu_d = jnp.sum(w[:, None] * dst, axis=0)
    xs = src - mu_s
    xd = dst - mu_d
    var_s = jnp.sum(w * jnp.sum(xs * xs, axis=-1))
    cov = jnp.einsum("n,ni,nj->ij", w, xd, xs)
    U, D, Vt = jnp.linalg.svd(cov)
    sign = jnp.where(jnp.linalg.det(U) * jnp.linalg.det(Vt) < 0, -1.0, 1.0).astype(src.dtype)
    S = jnp.array([1.0, 1.0, 0.0], src.dtype) + jnp.array([0.0, 0.0, 1.0], src.dtype) * sign
    R = (U * S[None, :]) @ Vt
    if with_scale:
        ok = var_s > 0
        s = jnp.where(ok, jnp.sum(D * S) / jnp.where(ok, var_s, 1.0), 1.0)
    else:
        s = jnp.ones((), src.dtype)
    t = mu_d - s * (R @ mu_s)
    return s, R, t


similarity_matrix = sim3.from_parts  # 4x4 ``[s R, t; 0, 1]`` from (s, R (3, 3), t (3,))


def umeyama_transform(src, dst, weights=None, with_scale: bool = False):
    """:func:`umeyama` as a 4x4 matrix mapping src to dst (scale folded into the rotation block)."""
    return similarity_matrix(*umeyama(src, dst, weights, with_scale))
