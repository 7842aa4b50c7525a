"""Symmetric positive definite block-tridiagonal systems in O(N): solve and the inverse's blocks."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def block_tridiagonal(D, B, g):
    """Solve ``H x = g`` for SPD block-tridiagonal ``H`` (diagonal blocks D (N, b, b), upper blocks
    ``H[i, i+1]`` B (N-1, b, b)); also the diagonal (N, b, b) and upper (N-1, b, b) blocks of
    ``H^{-1}``. Forward Schur complements, back substitution and the covariance recursion of a
    Rauch–Tung–Striebel smoother, one ``lax.scan`` each way. Returns (x (N, b), Pd, C)."""
    N, b = D.shape[0], D.shape[-1]
    Bp = jnp.concatenate([jnp.zeros_like(D[:1]), B[:N - 1]])  # Bp[i] = H[i-1, i]

    def fwd(carry, x):
        Si_prev, y_prev = carry
        Di, Bi, gi = x
        K = Bi.T @ Si_prev  # B_{i-1}^T S_{i-1}^{-1}
        Si = jnp.linalg.inv(Di - K @ Bi)
        y = gi - K @ y_prev
        return (Si, y), (Si, y)

    zero = jnp.zeros((b, b), D.dtype)
    _, (Sinv, y) = jax.lax.scan(fwd, (zero, jnp.zeros(b, D.dtype)), (D, Bp, g))
    Bn = jnp.concatenate([B[:N - 1], jnp.zeros_like(D[:1])])  # Bn[i] = H[i, i+1] (0 for the last)

    def bwd(carry, x):
        x_next, P_next = carry
        Si, yi, Bi = x
        xi = Si @ (yi - Bi @ x_next)
        C = -Si @ Bi @ P_next  # H^{-1}[i, i+1]
        Pi = Si - C @ Bi.T @ Si
        return (xi, Pi), (xi, Pi, C)

    _, (xs, Pd, C) = jax.lax.scan(bwd, (jnp.zeros(b, D.dtype), zero), (Sinv, y, Bn), reverse=True)
    return xs, Pd, C[:N - 1]
