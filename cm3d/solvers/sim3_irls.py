"""One robust Sim(3) fit of 3D-3D correspondences: weighted Umeyama, then IRLS with Cauchy weights.

``dst ≈ A src`` with ``A = [s R, t]`` (4, 4). Each round reweights the correspondences by
``w0 / (1 + (r / (k σ))²)`` (Cauchy at ``k`` robust sigmas) and refits by weighted Umeyama
(:func:`cm3d.solvers.align.umeyama_transform`); a round that gives a non-finite transform is undone.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from flax import struct

from cm3d.ops import robust, sim3
from cm3d.solvers.align import umeyama_transform


def irls_sim3(src, dst, w0, resid, iterations: int, k: float):
    """Weighted Umeyama Sim(3) of src, dst (N, 3) with base weights w0 (N,), then ``iterations``
    Cauchy IRLS rounds; ``resid(A)`` -> (residual norms (N,), robust σ > 0). Returns A (4, 4)."""
    A = umeyama_transform(src, dst, w0, with_scale=True)

    def irls(A, _):
        r, sigma = resid(A)
        An = umeyama_transform(src, dst, w0 / (1.0 + (r / (k * sigma)) ** 2), with_scale=True)
        return jnp.where(jnp.all(jnp.isfinite(An)), An, A), None

    return jax.lax.scan(irls, A, None, length=iterations)[0]


@struct.dataclass
class Sim3Fit:
    """A robust Sim(3) fit: transform (4, 4); inlier_fraction (within 3 robust sigmas of the valid
    correspondences); num_valid; rel_sigma: robust residual sigma over the median ``|dst|``."""

    transform: jnp.ndarray
    inlier_fraction: jnp.ndarray
    num_valid: jnp.ndarray
    rel_sigma: jnp.ndarray


@functools.partial(jax.jit, static_argnames=("iterations", "k"))
def robust_sim3(src, dst, ok, iterations: int = 8, k: float = 2.0) -> Sim3Fit:
    """Robust Sim(3) ``dst ≈ A src`` of padded correspondences (P, 3) with validity ``ok`` (P,):
    :func:`irls_sim3` with σ the robust sigma (MAD) of the valid residuals. ``vmap`` over pairs."""
    def resid(A):
        r = jnp.linalg.norm(sim3.apply(A, src) - dst, axis=-1)
        return r, jnp.maximum(robust.robust_sigma(r, ok), 1e-12)

    A = irls_sim3(src, dst, ok.astype(src.dtype), resid, iterations, k)
    r, sigma = resid(A)
    n = jnp.sum(ok)
    rel = sigma / jnp.maximum(robust.masked_median(jnp.linalg.norm(dst, axis=-1), ok), 1e-12)
    return Sim3Fit(A, jnp.sum(ok & (r <= 3.0 * sigma)) / jnp.maximum(n, 1), n, rel)
