"""A Sim(3) pose graph: constraints ``G_a^{-1} G_b ≈ M`` on transforms ``G_k = G0_k Exp(δ_k)``
(chart ``(ω, t, log s)``, :mod:`cm3d.ops.sim3`; δ_0 = 0 is the gauge), solved by optimistix's
Levenberg–Marquardt (dense: 7 (K-1) unknowns). Scale is a variable, so a loop corrects scale drift."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import optimistix as optx
from flax import struct

from cm3d.ops import sim3


@jax.jit
def residuals(delta, G0, idx_a, idx_b, measured, sigma):
    """Whitened residuals (E, 7) ``log(M^{-1} G_a^{-1} G_b) / σ``. delta (K-1, 7); G0 (K, 4, 4);
    idx_a, idx_b (E,); measured (E, 4, 4); sigma (E, 7)."""
    d = jnp.concatenate([jnp.zeros((1, 7), delta.dtype), delta])
    G = G0 @ sim3.exp(d)
    E = sim3.inverse(measured) @ sim3.inverse(G[idx_a]) @ G[idx_b]
    return sim3.log(E) / sigma


@struct.dataclass
class PoseGraphSolution:
    """transforms (K, 4, 4); cost_initial, cost: ``½ |r|²`` at G0 and at the solution; steps."""

    transforms: jnp.ndarray
    cost_initial: jnp.ndarray
    cost: jnp.ndarray
    steps: jnp.ndarray


@functools.partial(jax.jit, static_argnames=("max_steps",))
def solve(G0, idx_a, idx_b, measured, sigma, max_steps: int = 100) -> PoseGraphSolution:
    """Levenberg–Marquardt (rtol = atol = 1e-10) on the increments δ from zero."""
    fn = lambda y, args: residuals(y, G0, idx_a, idx_b, measured, sigma)  # noqa: E731
    y0 = jnp.zeros((G0.shape[0] - 1, 7), G0.dtype)
    sol = optx.least_squares(fn, optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10), y0, max_steps=max_steps,
                             throw=False)
    d = jnp.concatenate([jnp.zeros((1, 7), G0.dtype), sol.value])
    r0, r = fn(y0, None), fn(sol.value, None)
    return PoseGraphSolution(G0 @ sim3.exp(d), 0.5 * jnp.sum(r0 * r0), 0.5 * jnp.sum(r * r), sol.stats["num_steps"])
