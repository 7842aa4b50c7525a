"""Similarity transforms Sim(3) as 4x4 matrices ``[s R, t; 0 1]`` (``x' = s R x + t``).

One meaning for the package: ``scale`` is ``det(sR)^(1/3)``; the tangent chart is
``(ω, t, log s)`` (rotation vector first, then translation, then log scale: 7 numbers).
Every function broadcasts over leading axes and accepts NumPy (computed in NumPy, so host code
keeps float64) or JAX arrays (computed in JAX, jittable).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np


def array_module(*arrays):
    """NumPy when every argument is a NumPy array or scalar (host code keeps its precision and pays no
    JAX dispatch), else ``jax.numpy``."""
    return np if all(isinstance(a, (np.ndarray, np.generic, float, int)) for a in arrays) else jnp


def scale(A):
    """Scale ``s`` (...,) of Sim(3) matrices (..., 4, 4) or their linear parts (..., 3, 3)."""
    xp = array_module(A)
    return xp.cbrt(xp.linalg.det(A[..., :3, :3]))


def rotation(A):
    """Rotation (..., 3, 3) of Sim(3) matrices: ``sR / s``."""
    return A[..., :3, :3] / scale(A)[..., None, None]


def from_parts(s, R, t):
    """``[s R, t; 0 1]`` (..., 4, 4) from scale (...,), rotation (..., 3, 3), translation (..., 3)."""
    xp = array_module(s, R, t)
    s = xp.asarray(s)
    top = xp.concatenate([s[..., None, None] * R, t[..., :, None]], -1)
    bottom = xp.broadcast_to(xp.asarray([0.0, 0.0, 0.0, 1.0], dtype=top.dtype), top.shape[:-2] + (1, 4))
    return xp.concatenate([top, bottom], -2)


def apply(A, x):
    """``s R x + t`` for points x (..., N, 3) and a transform A (..., 4, 4)."""
    xp = array_module(A, x)
    return xp.einsum("...ij,...nj->...ni", A[..., :3, :3], x) + A[..., None, :3, 3]


def inverse(A):
    """Inverse (..., 4, 4): ``[R^T / s, -R^T t / s]``."""
    xp = array_module(A)
    s = scale(A)
    Ri = xp.swapaxes(A[..., :3, :3], -1, -2) / (s * s)[..., None, None]
    t = -xp.einsum("...ij,...j->...i", Ri, A[..., :3, 3])
    return from_parts(xp.ones_like(s), Ri, t)


def exp(p):
    """(..., 7) ``(ω, t, log s)`` -> (..., 4, 4) ``[e^{log s} Exp(ω), t]`` (translation not coupled)."""
    p = jnp.asarray(p)
    R = jax.vmap(lambda w: jaxlie.SO3.exp(w).as_matrix())(p.reshape(-1, 7)[:, :3]).reshape(p.shape[:-1] + (3, 3))
    return from_parts(jnp.exp(p[..., 6]), R, p[..., 3:6])


def log(A):
    """(..., 4, 4) -> (..., 7) ``(ω, t, log s)``: the chart of :func:`exp`."""
    A = jnp.asarray(A)
    s = scale(A)
    R = (A[..., :3, :3] / s[..., None, None]).reshape(-1, 3, 3)
    w = jax.vmap(lambda r: jaxlie.SO3.from_matrix(r).log())(R).reshape(A.shape[:-2] + (3,))
    return jnp.concatenate([w, A[..., :3, 3], jnp.log(s)[..., None]], -1)


def to_rigid(A):
    """The rigid part ``[R, t]`` of ``[s R, t]`` (..., 4, 4)."""
    xp = array_module(A)
    s = scale(A)
    return from_parts(xp.ones_like(s), rotation(A), A[..., :3, 3])
