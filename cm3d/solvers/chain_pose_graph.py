"""Levenberg–Marquardt on a chain pose graph: SE(3) priors plus motion factors between consecutive
poses only, so the normal equations are block-tridiagonal and each step is an O(N) solve.

The graph is a landmark-free :class:`cm3d.solvers.factors.FactorGraph`; residuals are exact,
Jacobians first order (``J_r^{-1} ≈ I``). The result carries each factor component's leverage
``h = diag(J (JᵀJ)⁻¹ Jᵀ)`` for variance component estimation (redundancy ``1 − h``).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from flax import struct

from cm3d.ops import se3
from cm3d.solvers import factors
from cm3d.solvers.block_tridiagonal import block_tridiagonal


@struct.dataclass
class ChainSolution:
    """poses (N, 4, 4); whitened residuals and leverages of the priors (P, 6) and the motion factors
    (Q, 6) at the optimum; cost_initial, cost: ``½ Σ w |e|²`` before and after."""

    poses: jnp.ndarray
    e_prior: jnp.ndarray
    h_prior: jnp.ndarray
    e_motion: jnp.ndarray
    h_motion: jnp.ndarray
    cost_initial: jnp.ndarray
    cost: jnp.ndarray


def normal_equations(graph: factors.FactorGraph, poses):
    """(D (N, 6, 6) diagonal blocks, B (N-1, 6, 6) blocks ``H[i, i+1]``, g (N, 6), cost, Jacobians
    (e_prior, J_prior, e_motion, J_a, J_b)) of the graph at ``poses`` (N, 4, 4)."""
    N = poses.shape[0]
    ep, em = factors.pose_residuals(graph, poses)
    X = se3.inverse(poses[graph.motion.idx_a]) @ poses[graph.motion.idx_b]
    eye6 = jnp.eye(6, dtype=poses.dtype)
    Jp = eye6 / graph.prior.sigma[:, :, None]
    Jb = eye6 / graph.motion.sigma[:, :, None]
    Ja = -factors.mm(Jb, factors.adjoint(se3.inverse(X)))
    wp, wm = graph.prior.weight, graph.motion.weight
    ip, ia, ib = graph.prior.pose_idx, graph.motion.idx_a, graph.motion.idx_b
    JtJ = lambda A, C, w: w[:, None, None] * jnp.einsum("fki,fkj->fij", A, C)  # noqa: E731
    D = jnp.zeros((N, 6, 6), poses.dtype).at[ip].add(JtJ(Jp, Jp, wp))
    D = D.at[ia].add(JtJ(Ja, Ja, wm)).at[ib].add(JtJ(Jb, Jb, wm))
    B = jnp.zeros((max(N - 1, 1), 6, 6), poses.dtype).at[jnp.minimum(ia, N - 2)].add(JtJ(Ja, Jb, wm))
    Jtr = lambda A, e, w: w[:, None] * jnp.einsum("fki,fk->fi", A, e)  # noqa: E731
    g = jnp.zeros((N, 6), poses.dtype).at[ip].add(Jtr(Jp, ep, wp))
    g = g.at[ia].add(Jtr(Ja, em, wm)).at[ib].add(Jtr(Jb, em, wm))
    cost = 0.5 * (jnp.sum(wp * jnp.sum(ep * ep, -1)) + jnp.sum(wm * jnp.sum(em * em, -1)))
    return D, B, g, cost, (ep, Jp, em, Ja, Jb)


@functools.partial(jax.jit, static_argnames=("iterations",))
def solve_chain(graph: factors.FactorGraph, poses, iterations: int = 10) -> ChainSolution:
    """Levenberg–Marquardt (Marquardt damping, λ from 1e-4, ×10 / ÷10) from ``poses`` (N, 4, 4);
    every weighted motion factor must join ``idx_b = idx_a + 1``. Returns :class:`ChainSolution`."""
    N = poses.shape[0]

    def step(carry, _):
        # evaluate the candidate; keep it when it lowers the cost; propose the next from the best
        # (one evaluation of the normal equations per step: one copy in the compiled program)
        cand, best, lam, cost0 = carry
        ne = normal_equations(graph, cand)
        better = jnp.isfinite(ne[3]) & (ne[3] < best[4])
        best = jax.tree_util.tree_map(lambda a, b: jnp.where(better, a, b), (cand,) + ne, best)
        lam = jnp.where(better, lam / 10.0, lam * 10.0)
        cost0 = jnp.where(jnp.isinf(cost0), ne[3], cost0)
        D, B, g = best[1], best[2], best[3]
        damp = lam * (jnp.diagonal(D, axis1=-2, axis2=-1) + 1e-9)
        d, _, _ = block_tridiagonal(D + jax.vmap(jnp.diag)(damp), B, -g)
        return (best[0] @ jax.vmap(se3.exp)(d), best, lam, cost0), None

    shapes = jax.eval_shape(lambda T: normal_equations(graph, T), poses)
    empty = jax.tree_util.tree_map(lambda x: jnp.zeros(x.shape, x.dtype), shapes)
    inf = jnp.asarray(jnp.inf, poses.dtype)
    best0 = (poses, empty[0], empty[1], empty[2], inf, empty[4])
    (_, best, _, cost0), _ = jax.lax.scan(step, (poses, best0, jnp.asarray(1e-4, poses.dtype), inf), None,
                                          length=iterations + 1)
    T, D, B, g, cost, (ep, Jp, em, Ja, Jb) = best
    _, Pd, C = block_tridiagonal(D, B, g)
    ip, ia, ib = graph.prior.pose_idx, graph.motion.idx_a, graph.motion.idx_b
    quad = lambda A, M, Bm: jnp.einsum("fki,fij,fkj->fk", A, M, Bm)  # noqa: E731  diag(A M Bᵀ)
    Cab = C[jnp.minimum(ia, N - 2)]
    hp = graph.prior.weight[:, None] * quad(Jp, Pd[ip], Jp)
    hm = graph.motion.weight[:, None] * (quad(Ja, Pd[ia], Ja) + quad(Jb, Pd[ib], Jb) + quad(Ja, Cab, Jb)
                                         + quad(Jb, jnp.swapaxes(Cab, -1, -2), Ja))
    return ChainSolution(T, ep, hp, em, hm, cost0, cost)
