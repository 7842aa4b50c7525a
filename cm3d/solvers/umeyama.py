"""Closed-form least-squares point-set fits: Umeyama's similarity (or rigid) transform."""

from __future__ import annotations

from cm3d.ops import sim3


def umeyama(src, dst, weights=None, with_scale: bool = True):
    """Least-squares similarity ``dst ≈ s R src + t`` (Umeyama 1991, reflection-safe).

    src, dst: (N, 3); weights: None, or (N,) non-negative weights / boolean valid mask.
    Returns (s scalar, R (3, 3), t (3,)); ``s = 1`` when ``with_scale`` is False. With a 0/1 mask this
    equals evo's ``umeyama_alignment`` on the valid points. Degenerate inputs (no weight, or all
    valid points equal) give ``s = 1`` and a finite R, never NaN; fewer than 3 non-collinear points
    leave the rotation about the degenerate axis arbitrary.

    NumPy inputs (every argument NumPy: host code, :func:`cm3d.ops.sim3.array_module`) are fitted with
    NumPy in their own precision, with no JAX dispatch (a process pays no compilation for a one-off host
    fit); anything else with ``jax.numpy`` (jittable, vmappable, differentiable).
    """
    xp = sim3.array_module(src, dst, *(() if weights is None else (weights,)))
    src = xp.asarray(src)
    dst = xp.asarray(dst, dtype=src.dtype)
    w = xp.ones(src.shape[:1], src.dtype) if weights is None else xp.asarray(weights).astype(src.dtype)
    w = w / xp.maximum(xp.sum(w), xp.finfo(src.dtype).tiny)
    mu_s = xp.sum(w[:, None] * src, axis=0)
    mu_d = xp.sum(w[:, None] * dst, axis=0)
    xs = src - mu_s
    xd = dst - mu_d
    var_s = xp.sum(w * xp.sum(xs * xs, axis=-1))
    cov = xp.einsum("n,ni,nj->ij", w, xd, xs)
    U, D, Vt = xp.linalg.svd(cov)
    sign = xp.where(xp.linalg.det(U) * xp.linalg.det(Vt) < 0, -1.0, 1.0).astype(src.dtype)
    S = xp.array([1.0, 1.0, 0.0], src.dtype) + xp.array([0.0, 0.0, 1.0], src.dtype) * sign
    R = (U * S[None, :]) @ Vt
    if with_scale:
        ok = var_s > 0
        s = xp.where(ok, xp.sum(D * S) / xp.where(ok, var_s, 1.0), 1.0)
    else:
        s = xp.ones((), src.dtype)
    t = mu_d - s * (R @ mu_s)
    return s, R, t


similarity_matrix = sim3.from_parts  # 4x4 ``[s R, t; 0, 1]`` from (s, R (3, 3), t (3,))


def umeyama_transform(src, dst, weights=None, with_scale: bool = False):
    """:func:`umeyama` as a 4x4 matrix mapping src to dst (scale folded into the rotation block)."""
    return similarity_matrix(*umeyama(src, dst, weights, with_scale))
