"""Damped Schur-complement solves of the LM normal equations ``(H + λI) δ = −g``.

The 3x3 landmark blocks are eliminated, ``S = H_pp + λI − Σ_j E_j^T C_j^{-1} E_j`` is solved and
the landmarks back-substituted. dense: ``S`` from the landmarks' observation pairs, Jacobi-scaled
Cholesky; pcg: matrix-free ``S v`` with block-Jacobi preconditioned CG (large pose counts).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from cm3d.solvers.factors import mm, mtv, mv
from cm3d.solvers.lm_options import LMOptions, use_dense
from cm3d.solvers.normal_equations import PAIR_CHUNK

def _inv3(C):
    """Closed-form inverse of SPD 3x3 blocks (..., 3, 3)."""
    a, b, c = C[..., 0, 0], C[..., 0, 1], C[..., 0, 2]
    d, e, f = C[..., 1, 0], C[..., 1, 1], C[..., 1, 2]
    g, h, i = C[..., 2, 0], C[..., 2, 1], C[..., 2, 2]
    A_, B_, C_ = e * i - f * h, -(d * i - f * g), d * h - e * g
    det = a * A_ + b * B_ + c * C_
    adj = jnp.stack([
        jnp.stack([A_, -(b * i - c * h), b * f - c * e], -1),
        jnp.stack([B_, a * i - c * g, -(a * f - c * d)], -1),
        jnp.stack([C_, -(a * h - b * g), a * e - b * d], -1),
    ], -2)
    return adj / det[..., None, None]


@struct.dataclass
class SchurSystem:
    """A damped system with its landmark blocks eliminated: ``Cinv`` (M, 3, 3), ``F = W C^{-1}``
    (K, 6, 3), the pose diagonal blocks of ``S`` (N, 6, 6), and (dense) the Cholesky factor."""

    Cinv: jnp.ndarray
    F: jnp.ndarray
    W: jnp.ndarray  # (K, 6, 3) the pose-landmark blocks F was formed from
    D_pose: jnp.ndarray  # (N, 6, 6) damped H_pose diagonal (identity for inactive poses)
    chol: jnp.ndarray  # (6N, 6N) Cholesky factor of the Jacobi-scaled S (dense) or (1, 1)
    scale: jnp.ndarray  # (6N,) Jacobi scaling
    precond: jnp.ndarray  # (N, 6, 6) block-Jacobi inverse (pcg) or (1, 6, 6)
    lam: jnp.ndarray


def _eliminate(graph, lin, st, lam):
    f = graph.projection
    dt = lin.H_point.dtype
    eye3 = jnp.eye(3, dtype=dt)
    C = lin.H_point + lam * eye3
    tr = jnp.trace(lin.H_point, axis1=-2, axis2=-1)
    C = C + (1e-12 * tr + 1e-300)[:, None, None] * eye3  # round-off floor, never NaN
    C = jnp.where(st.point_active[:, None, None], C, eye3)
    Cinv = _inv3(C)
    F = mm(lin.W, jax.lax.optimization_barrier(Cinv[f.point_idx]))
    eye6 = jnp.eye(6, dtype=dt)
    D_pose = jnp.where(st.pose_active[:, None, None], lin.H_pose + lam * eye6, eye6)
    return Cinv, F, D_pose


def reduced_rhs(graph, g_pose, g_point, sys):
    """Right-hand side ``−g_p + E C^{-1} g_l`` of the reduced system for ``H δ = −g``."""
    f = graph.projection
    N = g_pose.shape[0]
    return -g_pose + jax.ops.segment_sum(mv(sys.F, g_point[f.point_idx]), f.pose_idx, N)


def back_substitute(graph, g_point, sys, st, dp):
    """Landmark steps ``δ_l = C^{-1} (−g_l − E^T δ_p)``."""
    f = graph.projection
    M = g_point.shape[0]
    Et = jax.ops.segment_sum(mtv(sys.W, dp[f.pose_idx]), f.point_idx, M)
    dl = mv(sys.Cinv, -g_point - Et)
    return jnp.where(st.point_active[:, None], dl, 0.0)


def schur_solve(graph, st, sys, g_pose, g_point):
    """``(dp, dl)`` solving the factored (dense) damped system for gradient ``(g_pose, g_point)``."""
    dp = apply_dense(sys, reduced_rhs(graph, g_pose, g_point, sys))
    dp = jnp.where(st.pose_active[:, None], dp, 0.0)
    return dp, back_substitute(graph, g_point, sys, st, dp)


def _pair_sum(F, Wk, st, N, differentiable):
    """``Z[N a + b] = −Σ_pairs F_k1 W_k2^T`` over the landmark observation pairs, chunk by chunk
    (only the chunks holding valid pairs run, unless ``differentiable``)."""
    C = st.pair_k1.shape[0]
    ch = min(PAIR_CHUNK, C)
    n = C // ch
    k1, k2 = st.pair_k1.reshape(n, ch), st.pair_k2.reshape(n, ch)
    tg, ok = st.pair_target.reshape(n, ch), st.pair_valid.reshape(n, ch)

    def body(i, Z):
        a, b, t, v = k1[i], k2[i], tg[i], ok[i]
        Fa, Wb = jax.lax.optimization_barrier((F[a], Wk[b]))
        Fa = jnp.where(v[:, None, None], -Fa, 0.0)
        blocks = jax.lax.optimization_barrier(mm(Fa, jnp.swapaxes(Wb, -1, -2)))
        return Z.at[t].add(blocks)

    Z = jnp.zeros((N * N, 6, 6), F.dtype)
    if differentiable:
        return jax.lax.fori_loop(0, n, body, Z)
    used = jnp.minimum((st.pair_count + ch - 1) // ch, n)
    return jax.lax.fori_loop(0, used, body, Z)


def dense_reduced_matrix(graph, lin, st, F, D_pose, differentiable: bool = False):
    """The reduced camera matrix ``S`` (6N, 6N) from diagonal blocks, motion blocks and pairs."""
    f = graph.projection
    N = D_pose.shape[0]
    Wk = lin.W
    # same-observation (diagonal) pairs: S_ii -= F_k W_k^T
    diag = D_pose - jax.ops.segment_sum(mm(F, jnp.swapaxes(Wk, -1, -2)), f.pose_idx, N)
    Z = _pair_sum(F, Wk, st, N, differentiable)
    mf = graph.motion
    Z = Z.at[mf.idx_a * N + mf.idx_b].add(lin.H_motion)
    Z = Z.reshape(N, N, 6, 6)
    Z = Z + jnp.transpose(Z, (1, 0, 3, 2))
    Z = Z.reshape(N * N, 6, 6).at[jnp.arange(N) * (N + 1)].add(diag).reshape(N, N, 6, 6)
    return jnp.transpose(Z, (0, 2, 1, 3)).reshape(6 * N, 6 * N)


def factor_dense(graph, lin, st, lam, differentiable: bool = False) -> SchurSystem:
    """Eliminate landmarks and Cholesky-factor the Jacobi-scaled reduced camera system."""
    Cinv, F, D_pose = _eliminate(graph, lin, st, lam)
    S = dense_reduced_matrix(graph, lin, st, F, D_pose, differentiable)
    d = jnp.diagonal(S)
    scale = jnp.where(d > 0, jax.lax.rsqrt(jnp.where(d > 0, d, 1.0)), 1.0)
    Ss = S * scale[:, None] * scale[None, :]
    Ss = Ss + 1e-13 * jnp.eye(Ss.shape[0], dtype=Ss.dtype)
    chol = jnp.linalg.cholesky(Ss)
    return SchurSystem(Cinv, F, lin.W, D_pose, chol, scale, jnp.zeros((1, 6, 6), S.dtype), lam)


def apply_dense(sys: SchurSystem, rhs):
    b = (rhs.reshape(-1) * sys.scale)
    y = jax.scipy.linalg.cho_solve((sys.chol, True), b)
    return (y * sys.scale).reshape(-1, 6)


def factor_pcg(graph, lin, st, lam) -> SchurSystem:
    """Eliminate landmarks and build the block-Jacobi preconditioner of the reduced system."""
    f = graph.projection
    Cinv, F, D_pose = _eliminate(graph, lin, st, lam)
    N = D_pose.shape[0]
    P = D_pose - jax.ops.segment_sum(mm(F, jnp.swapaxes(lin.W, -1, -2)), f.pose_idx, N)
    P = 0.5 * (P + jnp.swapaxes(P, -1, -2))
    P = jnp.where(st.pose_active[:, None, None], P, jnp.eye(6, dtype=P.dtype))
    Pinv = jnp.linalg.inv(P)
    dt = lin.H_point.dtype
    return SchurSystem(Cinv, F, lin.W, D_pose, jnp.zeros((1, 1), dt), jnp.ones((1,), dt), Pinv, lam)


def reduced_matvec(graph, lin, sys: SchurSystem, v):
    """``S v`` without forming ``S``: ``D v + motion blocks − E C^{-1} E^T v`` (v: (N, 6))."""
    f, mf = graph.projection, graph.motion
    N, M = v.shape[0], sys.Cinv.shape[0]
    out = mv(sys.D_pose, v)
    out = out.at[mf.idx_a].add(mv(lin.H_motion, v[mf.idx_b]))
    out = out.at[mf.idx_b].add(mtv(lin.H_motion, v[mf.idx_a]))
    u = jax.ops.segment_sum(mtv(lin.W, v[f.pose_idx]), f.point_idx, M)
    return out - jax.ops.segment_sum(mv(sys.F, u[f.point_idx]), f.pose_idx, N)


def pcg(matvec, precond, b, max_iterations: int, tol: float, differentiable: bool = False):
    """Preconditioned conjugate gradients for SPD ``matvec`` (arrays of any shape).

    Stops when ``|r| <= tol |b|`` or on a non-positive curvature; returns (x, iterations).
    ``differentiable`` runs exactly ``max_iterations`` masked steps in a ``scan``.
    """
    dot = lambda a, c: jnp.sum(a * c)  # noqa: E731
    bn = jnp.sqrt(dot(b, b))
    x0 = jnp.zeros_like(b)
    r0 = b
    z0 = precond(r0)
    state = (x0, r0, z0, z0, dot(r0, z0), jnp.zeros((), jnp.int32), bn <= 0)

    def step(s):
        x, r, z, p, rz, it, done = s
        Ap = matvec(p)
        pAp = dot(p, Ap)
        ok = (pAp > 0) & ~done
        alpha = jnp.where(ok, rz / jnp.where(ok, pAp, 1.0), 0.0)
        x = x + alpha * p
        r = r - alpha * Ap
        z = precond(r)
        rz_new = dot(r, z)
        beta = jnp.where(ok, rz_new / jnp.where(rz != 0, rz, 1.0), 0.0)
        p = jnp.where(ok, z + beta * p, p)
        conv = jnp.sqrt(dot(r, r)) <= tol * bn
        return (x, r, z, p, jnp.where(ok, rz_new, rz), it + ok.astype(jnp.int32), done | ~ok | conv)

    if differentiable:
        state, _ = jax.lax.scan(lambda s, _: (step(s), None), state, None, length=max_iterations)
    else:
        state = jax.lax.while_loop(lambda s: (~s[6]) & (s[5] < max_iterations), step, state)
    return state[0], state[5]



def damped_step(graph, lin, st, lam, options: LMOptions, differentiable: bool = False):
    """Solve ``(H + λI) δ = −g`` by the Schur complement -> (dp (N, 6), dl (M, 3))."""
    N = lin.H_pose.shape[0]
    if use_dense(N, options):
        sys = factor_dense(graph, lin, st, lam, differentiable)
        return schur_solve(graph, st, sys, lin.g_pose, lin.g_point)
    else:
        sys = factor_pcg(graph, lin, st, lam)
        rhs = reduced_rhs(graph, lin.g_pose, lin.g_point, sys)
        dp, _ = pcg(lambda v: reduced_matvec(graph, lin, sys, v),
                    lambda r: mv(sys.precond, r), rhs,
                    options.pcg_max_iterations, options.pcg_tol, differentiable)
    dp = jnp.where(st.pose_active[:, None], dp, 0.0)
    return dp, back_substitute(graph, lin.g_point, sys, st, dp)
