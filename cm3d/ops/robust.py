"""Robust statistics at fixed shapes: masked median, MAD scale, χ² quantile.

One meaning each for the package: :func:`masked_median` is the ordinary median (mean of the two
middle values for an even count), :func:`masked_median_low` the low median (the lower of the two,
always a sample: Python's ``statistics.median_low``; the motion cues are tuned on it); :data:`MAD_TO_SIGMA` turns a median absolute deviation into a
Gaussian σ; :func:`chi2_quantile` is jittable (Wilson–Hilferty, ~1 % for dof >= 3).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

MAD_TO_SIGMA = 1.4826  # σ = 1.4826 · MAD for Gaussian data (1 / Φ⁻¹(3/4))


def masked_median(x, valid, axis: int = -1):
    """Median of ``x`` over ``valid`` along ``axis`` (0 where nothing is valid)."""
    x = jnp.asarray(x)
    valid = jnp.broadcast_to(jnp.asarray(valid, bool), x.shape)
    x = jnp.moveaxis(x, axis, -1)
    valid = jnp.moveaxis(valid, axis, -1)
    n = jnp.sum(valid, -1)
    s = jnp.sort(jnp.where(valid, x, jnp.inf), -1)
    size = x.shape[-1]
    lo = jnp.clip((n - 1) // 2, 0, size - 1)[..., None]
    hi = jnp.clip(n // 2, 0, size - 1)[..., None]
    med = 0.5 * (jnp.take_along_axis(s, lo, -1) + jnp.take_along_axis(s, hi, -1))[..., 0]
    return jnp.where(n > 0, med, jnp.zeros_like(med))


def masked_median_low(x, valid):
    """Low median of ``x[valid]`` over all elements (the lower middle value; 0 when nothing is valid)."""
    x = jnp.asarray(x).reshape(-1)
    valid = jnp.broadcast_to(jnp.asarray(valid, bool).reshape(-1), x.shape)
    n = jnp.sum(valid)
    s = jnp.sort(jnp.where(valid, x, jnp.inf))
    return jnp.where(n > 0, s[jnp.clip((n - 1) // 2, 0, x.shape[0] - 1)], 0.0)


def robust_sigma(r, valid, axis: int = -1):
    """``1.4826 · median(|r|)`` over ``valid``: the σ of zero-centred residuals ``r``."""
    return MAD_TO_SIGMA * masked_median(jnp.abs(r), valid, axis)


def mad_sigma(x, valid, axis: int = -1):
    """``1.4826 · median(|x - median(x)|)`` over ``valid``: the σ of ``x`` about its median."""
    med = masked_median(x, valid, axis)
    return MAD_TO_SIGMA * masked_median(jnp.abs(x - jnp.expand_dims(med, axis)), valid, axis)


def chi2_quantile(q, dof):
    """The ``q`` quantile of χ²(dof) (Wilson–Hilferty; ~1 % accurate for dof >= 3), jittable."""
    z = jax.scipy.special.ndtri(jnp.asarray(q, jnp.result_type(float)))
    k = jnp.maximum(jnp.asarray(dof, z.dtype), 1.0)
    return k * (1.0 - 2.0 / (9.0 * k) + z * jnp.sqrt(2.0 / (9.0 * k))) ** 3
