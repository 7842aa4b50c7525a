"""The normal equations of a factor graph: estimable variables, landmark observation pairs,
whitened residuals and Jacobians with IRLS weights, the assembled blocks, the exact gradient.

Huber-robust reprojection factors are robustified by reweighting as GTSAM does; the pose factors'
Jacobians are the analytic ``J_r^{-1}`` ones of :mod:`cm3d.solvers.factors`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from cm3d.ops import se3
from cm3d.solvers.factors import (
    FactorGraph, Variables, huber_loss, huber_weight, mtm, mtv, mv, point_prior_residual,
    pose_factor_jacobians, projection_linearize
)
from cm3d.solvers.lm_options import LMOptions


@struct.dataclass
class Structure:
    """obs_active (K,), point_active (M,), pose_active (N,) masks; pair_k1/pair_k2 (C,) observation
    pairs of the same landmark with k2 earlier than k1; pair_valid (C,); pair_target (C,) flat
    block index ``N pose(k1) + pose(k2)``; pair_count: pairs needed."""

    obs_active: jnp.ndarray
    point_active: jnp.ndarray
    pose_active: jnp.ndarray
    pair_k1: jnp.ndarray
    pair_k2: jnp.ndarray
    pair_valid: jnp.ndarray
    pair_target: jnp.ndarray
    pair_count: jnp.ndarray


PAIR_CHUNK = 2048  # pairs processed per step of the Schur assembly loop


def _pair_capacity(graph: FactorGraph, options: LMOptions) -> int:
    """Static pair capacity, rounded up to whole chunks."""
    K = graph.projection.pose_idx.shape[0]
    cap = max(1, options.pair_capacity if options.pair_capacity is not None else 8 * K)
    ch = min(PAIR_CHUNK, cap)
    return -(-cap // ch) * ch


def structure(graph: FactorGraph, num_points: int, options: LMOptions = LMOptions(),
              with_pairs: bool = True) -> Structure:
    """Active masks and the landmark observation pairs (jittable, fixed capacity). More pairs than the
    capacity make :func:`solve` take no step and report :data:`PAIR_OVERFLOW` (a result, not a host
    callback, so compiled programs stay cacheable and vmappable)."""
    f = graph.projection
    N = graph.intrinsics.shape[0]
    M = num_points
    K = f.pose_idx.shape[0]
    w_pos = f.weight > 0
    counts = jax.ops.segment_sum(w_pos.astype(jnp.int32), f.point_idx, M)
    point_active = counts >= options.min_observations
    obs_active = w_pos & point_active[f.point_idx]
    touched = jax.ops.segment_sum(obs_active.astype(jnp.int32), f.pose_idx, N)
    touched += jax.ops.segment_sum((graph.prior.weight > 0).astype(jnp.int32), graph.prior.pose_idx, N)
    mw = (graph.motion.weight > 0).astype(jnp.int32)
    touched += jax.ops.segment_sum(mw, graph.motion.idx_a, N) + jax.ops.segment_sum(mw, graph.motion.idx_b, N)
    pose_active = (touched > 0) & ~graph.pose_fixed
    if not with_pairs:
        z = jnp.zeros(1, jnp.int32)
        return Structure(obs_active, point_active, pose_active, z, z, jnp.zeros(1, bool), z,
                         jnp.zeros((), jnp.int32))
    cap = _pair_capacity(graph, options)
    key = jnp.where(obs_active, f.point_idx, M)
    order = jnp.argsort(key, stable=True).astype(jnp.int32)
    skey = key[order]
    n_j = jax.ops.segment_sum(obs_active.astype(jnp.int32), f.point_idx, M)
    start_j = jnp.cumsum(n_j) - n_j
    s = jnp.arange(K, dtype=jnp.int32)
    rank = s - start_j[jnp.minimum(skey, M - 1)]
    per = jnp.where(skey < M, rank, 0)  # pairs (s, earlier obs of the same landmark)
    cum = jnp.cumsum(per)
    total = cum[-1] if K else jnp.zeros((), jnp.int32)
    p = jnp.arange(cap, dtype=jnp.int32)
    sp = jnp.searchsorted(cum, p, side="right").astype(jnp.int32)
    sp = jnp.minimum(sp, K - 1)
    r = p - (cum[sp] - per[sp])
    partner = start_j[jnp.minimum(skey[sp], M - 1)] + r
    valid = p < total
    k1 = jnp.where(valid, order[sp], 0)
    k2 = jnp.where(valid, order[jnp.clip(partner, 0, K - 1)], 0)
    target = f.pose_idx[k1] * N + f.pose_idx[k2]
    return Structure(obs_active, point_active, pose_active, k1, k2, valid, target, total)


def schur_pair_count(graph: FactorGraph, num_points: int, min_observations: int = 2) -> int:
    """Exact ``pair_capacity`` the dense Schur assembly needs for this graph (host helper)."""
    f = graph.projection
    w = np.asarray(f.weight) > 0
    lid = np.asarray(f.point_idx)
    n = np.bincount(lid[w], minlength=num_points)
    n = np.where(n >= min_observations, n, 0)
    return int(np.sum(n * (n - 1) // 2))

@struct.dataclass
class Linearization:
    """Whitened residuals, Jacobians and the assembled (undamped) normal equations at a point."""

    e: jnp.ndarray  # (K, 2)
    A: jnp.ndarray  # (K, 2, 6)
    B: jnp.ndarray  # (K, 2, 3)
    w: jnp.ndarray  # (K,) IRLS weight (0 for inactive)
    e_p: jnp.ndarray
    J_p: jnp.ndarray
    e_m: jnp.ndarray
    J_a: jnp.ndarray
    J_b: jnp.ndarray
    H_pose: jnp.ndarray  # (N, 6, 6) diagonal blocks
    H_motion: jnp.ndarray  # (Q, 6, 6) off-diagonal (a, b) blocks
    W: jnp.ndarray  # (K, 6, 3) pose-landmark blocks
    H_point: jnp.ndarray  # (M, 3, 3)
    g_pose: jnp.ndarray  # (N, 6) gradient
    g_point: jnp.ndarray  # (M, 3)
    cost: jnp.ndarray
    lin_err: jnp.ndarray  # ½ Σ w |e|² (GTSAM's linearised error at δ = 0)
    r_point: jnp.ndarray | None = None  # (M, 3) landmark-prior residuals (graphs with point priors)
    w_point: jnp.ndarray | None = None  # (M,) their weights (0 for inactive landmarks)


def linearize(graph: FactorGraph, x: Variables, st: Structure, differentiable: bool = False) -> Linearization:
    """Residuals, Jacobians, IRLS weights and normal-equation blocks at ``x``.

    ``differentiable``: the caller differentiates through it (unrolled mode).
    """
    f = graph.projection
    N, M = x.poses.shape[0], x.points.shape[0]
    e, A, B, _ = projection_linearize(graph, x)
    sq = jnp.sum(e * e, -1)
    k = jnp.asarray(graph.huber_k, e.dtype)
    fw = jnp.where(st.obs_active, f.weight, 0.0)
    w = fw * huber_weight(sq, k)
    cost_proj = jnp.sum(fw * huber_loss(sq, k))
    e_p, J_p, e_m, J_a, J_b = pose_factor_jacobians(graph, x.poses)
    # fixed / inactive poses are constants: no Jacobian w.r.t. them
    act = st.pose_active
    A = jnp.where(act[f.pose_idx][:, None, None], A, 0.0)
    J_p = jnp.where(act[graph.prior.pose_idx][:, None, None], J_p, 0.0)
    J_a = jnp.where(act[graph.motion.idx_a][:, None, None], J_a, 0.0)
    J_b = jnp.where(act[graph.motion.idx_b][:, None, None], J_b, 0.0)
    wp, wm = graph.prior.weight, graph.motion.weight

    wA = w[:, None, None] * A
    wB = w[:, None, None] * B
    # materialise the per-observation blocks: XLA:CPU runs products fused into scatters serially
    HA, W, HB, gA, gB = jax.lax.optimization_barrier((mtm(wA, A), mtm(wA, B), mtm(wB, B), mtv(wA, e), mtv(wB, e)))
    H_pose = jax.ops.segment_sum(HA, f.pose_idx, N)
    H_pose += jax.ops.segment_sum(wp[:, None, None] * mtm(J_p, J_p), graph.prior.pose_idx, N)
    H_pose += jax.ops.segment_sum(wm[:, None, None] * mtm(J_a, J_a), graph.motion.idx_a, N)
    H_pose += jax.ops.segment_sum(wm[:, None, None] * mtm(J_b, J_b), graph.motion.idx_b, N)
    H_motion = wm[:, None, None] * mtm(J_a, J_b)
    H_point = jax.ops.segment_sum(HB, f.point_idx, M)
    g_pose = jax.ops.segment_sum(gA, f.pose_idx, N)
    g_pose += jax.ops.segment_sum(wp[:, None] * mtv(J_p, e_p), graph.prior.pose_idx, N)
    g_pose += jax.ops.segment_sum(wm[:, None] * mtv(J_a, e_m), graph.motion.idx_a, N)
    g_pose += jax.ops.segment_sum(wm[:, None] * mtv(J_b, e_m), graph.motion.idx_b, N)
    g_point = jax.ops.segment_sum(gB, f.point_idx, M)
    pose_sq = 0.5 * (jnp.sum(wp * jnp.sum(e_p * e_p, -1)) + jnp.sum(wm * jnp.sum(e_m * e_m, -1)))
    r_l = wl = None
    if graph.point_prior is not None:  # landmark priors: residual S (L - target), Jacobian S
        pp = graph.point_prior
        S = pp.sqrt_info.astype(e.dtype)
        r_l = point_prior_residual(graph, x.points)
        wl = jnp.where(st.point_active, pp.weight, 0.0)
        H_point += wl[:, None, None] * mtm(S, S)
        g_point += wl[:, None] * mtv(S, r_l)
        pose_sq += 0.5 * jnp.sum(wl * jnp.sum(r_l * r_l, -1))
    return Linearization(
        e=e, A=A, B=B, w=w, e_p=e_p, J_p=J_p, e_m=e_m, J_a=J_a, J_b=J_b, H_pose=H_pose,
        H_motion=H_motion, W=W, H_point=H_point, g_pose=g_pose, g_point=g_point,
        cost=cost_proj + pose_sq, lin_err=0.5 * jnp.sum(w * sq) + pose_sq, r_point=r_l, w_point=wl)


def linearized_error(graph: FactorGraph, lin: Linearization, dp, dl):
    """GTSAM's linearised error ``½ Σ w |e + J δ|²`` of a step (dp (N, 6), dl (M, 3))."""
    f = graph.projection
    # einsum, not the unrolled mv: XLA:CPU fuses an unrolled product into the reduction badly
    r = lin.e + jnp.einsum("kri,ki->kr", lin.A, dp[f.pose_idx]) + jnp.einsum("kri,ki->kr", lin.B, dl[f.point_idx])
    rp = lin.e_p + mv(lin.J_p, dp[graph.prior.pose_idx])
    rm = lin.e_m + mv(lin.J_a, dp[graph.motion.idx_a]) + mv(lin.J_b, dp[graph.motion.idx_b])
    out = 0.5 * (jnp.sum(lin.w * jnp.sum(r * r, -1)) + jnp.sum(graph.prior.weight * jnp.sum(rp * rp, -1))
                 + jnp.sum(graph.motion.weight * jnp.sum(rm * rm, -1)))
    if graph.point_prior is not None:
        pp = graph.point_prior
        S = pp.sqrt_info.astype(dl.dtype)
        rl = lin.r_point + mv(S, dl)
        out += 0.5 * jnp.sum(lin.w_point * jnp.sum(rl * rl, -1))
    return out

def gradient(graph: FactorGraph, x: Variables, st: Structure):
    """The objective's gradient in the tangent space at ``x``: (g_pose (N, 6), g_point (M, 3)),
    from the analytic Jacobians and IRLS weights (``ρ'(x)/x``, so the exact robust gradient)."""
    f = graph.projection
    N, M = x.poses.shape[0], x.points.shape[0]
    e, A, B, _ = projection_linearize(graph, x)
    sq = jnp.sum(e * e, -1)
    w = jnp.where(st.obs_active, f.weight, 0.0) * huber_weight(sq, jnp.asarray(graph.huber_k, e.dtype))
    act = st.pose_active
    A = jnp.where(act[f.pose_idx][:, None, None], A, 0.0)
    e_p, J_p, e_m, J_a, J_b = pose_factor_jacobians(graph, x.poses)
    wp = jnp.where(act[graph.prior.pose_idx], graph.prior.weight, 0.0)
    wa = jnp.where(act[graph.motion.idx_a], graph.motion.weight, 0.0)
    wb = jnp.where(act[graph.motion.idx_b], graph.motion.weight, 0.0)
    we = w[:, None] * e
    g_pose = jax.ops.segment_sum(mtv(A, we), f.pose_idx, N)
    g_pose += jax.ops.segment_sum(wp[:, None] * mtv(J_p, e_p), graph.prior.pose_idx, N)
    g_pose += jax.ops.segment_sum(wa[:, None] * mtv(J_a, e_m), graph.motion.idx_a, N)
    g_pose += jax.ops.segment_sum(wb[:, None] * mtv(J_b, e_m), graph.motion.idx_b, N)
    g_point = jax.ops.segment_sum(mtv(B, we), f.point_idx, M)
    if graph.point_prior is not None:
        pp = graph.point_prior
        g_point += pp.weight[:, None] * mtv(pp.sqrt_info.astype(e.dtype), point_prior_residual(graph, x.points))
    return g_pose, jnp.where(st.point_active[:, None], g_point, 0.0)


def retract(x: Variables, dp, dl) -> Variables:
    """``T ← T exp(δ)``, ``L ← L + δ``."""
    return Variables(poses=x.poses @ se3.exp(dp), points=x.points + dl)
