"""Levenberg–Marquardt for bundle-adjustment-shaped factor graphs, in pure JAX.

Variables are poses on SE(3) (cam_to_world 4x4, retracted ``T ← T exp(δ)`` with jaxlie's tangent
order, translation first) and landmarks in R³ (``L ← L + δ``). The factors are those of
:mod:`cm3d.solvers.factors`: Huber-robust reprojection (analytic Jacobians, robustified by
reweighting as GTSAM does), pose priors and relative-motion factors (analytic ``J_r^{-1}``
Jacobians; ``jax.jacfwd`` ones are available for reference).

One LM *trial* solves the damped normal equations ``(H + λI) δ = −g`` (GTSAM's damping: λ on every
variable) by the **Schur complement**: the 3x3 landmark blocks ``C_j`` are eliminated, the reduced
camera system ``S = H_pp + λI − Σ_j E_j^T C_j^{-1} E_j`` is solved, the landmarks are
back-substituted. Two reduced solvers:

* ``"dense"``: ``S`` is assembled from the landmarks' observation pairs (``Σ_j n_j (n_j−1)/2``
  6x6 blocks in chunks, not an O(N² M) product) and factored by Jacobi-scaled dense Cholesky;
* ``"pcg"``: matrix-free ``S v`` products and block-Jacobi preconditioned conjugate gradients, for
  pose counts where the O(N³) factorisation dominates (inexact steps: see the docs' benchmark).

The λ schedule, step acceptance (model fidelity > 1e-3) and stopping rules are GTSAM's
``LevenbergMarquardtOptimizer`` defaults, so the same problem gives the same cost history. The
loop is one ``lax.while_loop`` whose body evaluates a candidate and proposes the next; every array
has a fixed capacity (padding has weight 0), so a sweep compiles once and the solver is
``vmap``-able over problems. Optional exact-Newton polish steps (``newton_steps``) follow the LM
phase: IRLS converges only linearly when Huber outliers are present.

Gradients (``LMOptions.backward``):

* ``"implicit"`` (default): implicit function theorem at the optimum, ``custom_vjp``; the adjoint
  system uses the **exact** Hessian (Hessian-vector products as the forward-mode derivative of
  the analytic gradient) solved by conjugate gradients preconditioned by the Gauss–Newton Schur
  solve (the forward pass's last factorisation). The Gauss–Newton Hessian alone gives wrong gradients
  (weak gauge/scale directions). Needs a tightly converged forward solve: use
  :data:`IMPLICIT_OPTIONS` (gradient-norm stop plus Newton polish).
* ``"unrolled"``: exactly ``unroll_steps`` LM trials in a ``lax.scan`` with ``jax.checkpoint``.
* ``"none"``: no gradient rule (a ``while_loop`` is not reverse-differentiable).

Variables that no factor can determine are frozen (δ = 0) instead of producing NaN: landmarks with
fewer than ``min_observations`` valid observations (their observations are then ignored: a landmark
seen once carries no information about the poses), poses with no factor at all, and poses marked
in ``graph.pose_fixed``.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.custom_batching import custom_vmap

from cm3d.ops import se3
from cm3d.solvers.factors import (
    FactorGraph,
    Variables,
    orthonormalize_poses,
    point_prior_residual,
    pose_factor_jacobians,
    projection_linearize,
    total_cost,
    huber_loss,
    huber_weight,
    mm,
    mtm,
    mtv,
    mv,
)

LINEAR_SOLVERS = ("auto", "dense", "pcg")
BATCHINGS = ("auto", "sequential", "native")
BACKWARDS = ("implicit", "unrolled", "none")
STOP_REASONS = ("running", "relative/absolute decrease", "gradient tolerance", "small cost change",
                "lambda upper bound", "max iterations", "non-finite initial point",
                "pair capacity too small: raise LMOptions.pair_capacity (schur_pair_count gives the need)")
PAIR_OVERFLOW = 7  # stop reason: the graph has more landmark observation pairs than the capacity


@dataclasses.dataclass(frozen=True)
class LMOptions:
    """Options (all static). Defaults are GTSAM's ``LevenbergMarquardtParams``.

    max_iterations: outer iterations (accepted steps); max_linear_solves: cap on trials (each a
    damped solve); rel_tol / abs_tol: GTSAM's relative/absolute error decrease tolerances;
    grad_tol: also stop when the Jacobi-scaled gradient ``max_i |g_i| / sqrt(H_ii)`` is at most
    ``grad_tol`` (0 disables); lambda_*: initial value,
    multiplicative factor and bounds of the damping; min_model_fidelity: accept a step when
    actual/predicted decrease exceeds it. linear_solver: "dense", "pcg" or "auto" (dense up to
    ``dense_max_poses`` pose slots); pcg_max_iterations / pcg_tol: inner CG of the "pcg" solver;
    pair_capacity: static number of landmark observation pairs of the dense Schur assembly
    (``None``: 8 per observation; :func:`schur_pair_count` gives the exact need);
    min_observations: landmarks with fewer valid observations are frozen. backward: "implicit",
    "unrolled" or "none"; unroll_steps: trials of the unrolled mode; implicit_cg_iterations /
    implicit_cg_tol: adjoint (and Newton) solves; implicit_damping: relative damping of their
    Gauss–Newton preconditioner; newton_steps: exact-Newton steps after LM (IRLS converges only
    linearly with Huber outliers; implicit gradients need a tight optimum). batching: how
    ``vmap`` runs the solver: "native" batches every operation (a ``while_loop`` over the whole
    batch), "sequential" maps the problems one after another inside the program (on CPU the
    batched gathers/scatters fall out of cache and run several times slower), "auto": sequential
    on the CPU backend, native elsewhere.
    """

    max_iterations: int = 100
    max_linear_solves: int = 300
    rel_tol: float = 1e-5
    abs_tol: float = 1e-5
    grad_tol: float = 0.0
    lambda_init: float = 1e-5
    lambda_factor: float = 10.0
    lambda_min: float = 0.0
    lambda_max: float = 1e5
    min_model_fidelity: float = 1e-3
    linear_solver: str = "auto"
    dense_max_poses: int = 512
    pcg_max_iterations: int = 300
    pcg_tol: float = 1e-10
    pair_capacity: int | None = None
    min_observations: int = 2
    backward: str = "implicit"
    unroll_steps: int = 10
    implicit_cg_iterations: int = 8
    implicit_cg_tol: float = 1e-8
    implicit_damping: float = 1e-9
    newton_steps: int = 0
    batching: str = "auto"

    def __post_init__(self):
        if self.linear_solver not in LINEAR_SOLVERS:
            raise ValueError(f"LMOptions.linear_solver: unknown {self.linear_solver!r} {LINEAR_SOLVERS}")
        if self.batching not in BATCHINGS:
            raise ValueError(f"LMOptions.batching: unknown {self.batching!r} {BATCHINGS}")
        if self.backward not in BACKWARDS:
            raise ValueError(f"LMOptions.backward: unknown {self.backward!r} {BACKWARDS}")
        if self.max_iterations < 1 or self.max_linear_solves < 1 or self.unroll_steps < 1:
            raise ValueError("LMOptions: max_iterations, max_linear_solves, unroll_steps must be >= 1")
        if not (self.lambda_init > 0 and self.lambda_factor > 1 and self.lambda_max > self.lambda_init):
            raise ValueError("LMOptions: need lambda_init > 0, lambda_factor > 1, lambda_max > lambda_init")
        if self.pair_capacity is not None and self.pair_capacity < 1:
            raise ValueError("LMOptions.pair_capacity: must be >= 1 (or None)")
        if self.newton_steps < 0:
            raise ValueError("LMOptions.newton_steps: must be >= 0")
        if self.min_observations < 1:
            raise ValueError("LMOptions.min_observations: must be >= 1")


#: Options for a forward solve whose implicit gradient is accurate: stop on the gradient norm.
IMPLICIT_OPTIONS = LMOptions(rel_tol=1e-10, abs_tol=0.0, grad_tol=1e-8, max_iterations=100,
                             max_linear_solves=200, newton_steps=3)


@struct.dataclass
class LMResult:
    """Solver output. params: optimum (poses re-orthonormalised by SVD); cost: final objective;
    initial_cost; iterations: accepted steps (GTSAM's outer iterations); linear_solves: damped
    solves tried; converged: a tolerance was met; stop_reason: index into :data:`STOP_REASONS`;
    grad_norm: Jacobi-scaled gradient ``max |g_i|/sqrt(H_ii)`` at the optimum; lambda_: final damping; cost_history:
    (max_iterations + 1,) cost after each accepted step (last value repeated)."""

    params: Variables
    cost: jnp.ndarray
    initial_cost: jnp.ndarray
    iterations: jnp.ndarray
    linear_solves: jnp.ndarray
    converged: jnp.ndarray
    stop_reason: jnp.ndarray
    grad_norm: jnp.ndarray
    lambda_: jnp.ndarray
    cost_history: jnp.ndarray


# ----------------------------------------------------------------------------------------------
# Structure: which variables are estimable, and the landmark observation pairs of the Schur step


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
    """Active masks and the landmark observation pairs (jittable, fixed capacity).

    When the graph has more pairs than the capacity (``pair_count > pair_k1.shape[0]``) the pairs
    are incomplete: :func:`solve` then takes no step and reports stop reason :data:`PAIR_OVERFLOW`
    (a result, not a host callback, so compiled programs stay cacheable and vmappable).
    """
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


# ----------------------------------------------------------------------------------------------
# Linearisation


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


# ----------------------------------------------------------------------------------------------
# Damped Schur solves


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


def _reduced_rhs(graph, g_pose, g_point, sys):
    """Right-hand side ``−g_p + E C^{-1} g_l`` of the reduced system for ``H δ = −g``."""
    f = graph.projection
    N = g_pose.shape[0]
    return -g_pose + jax.ops.segment_sum(mv(sys.F, g_point[f.point_idx]), f.pose_idx, N)


def _back_substitute(graph, g_point, sys, st, dp):
    """Landmark steps ``δ_l = C^{-1} (−g_l − E^T δ_p)``."""
    f = graph.projection
    M = g_point.shape[0]
    Et = jax.ops.segment_sum(mtv(sys.W, dp[f.pose_idx]), f.point_idx, M)
    dl = mv(sys.Cinv, -g_point - Et)
    return jnp.where(st.point_active[:, None], dl, 0.0)


def schur_solve(graph, st, sys, g_pose, g_point):
    """``(dp, dl)`` solving the factored (dense) damped system for gradient ``(g_pose, g_point)``."""
    dp = _apply_dense(sys, _reduced_rhs(graph, g_pose, g_point, sys))
    dp = jnp.where(st.pose_active[:, None], dp, 0.0)
    return dp, _back_substitute(graph, g_point, sys, st, dp)


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


def _apply_dense(sys: SchurSystem, rhs):
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


def _use_dense(num_poses: int, options: LMOptions) -> bool:
    if options.linear_solver == "auto":
        return num_poses <= options.dense_max_poses
    return options.linear_solver == "dense"


def damped_step(graph, lin, st, lam, options: LMOptions, differentiable: bool = False):
    """Solve ``(H + λI) δ = −g`` by the Schur complement -> (dp (N, 6), dl (M, 3))."""
    N = lin.H_pose.shape[0]
    if _use_dense(N, options):
        sys = factor_dense(graph, lin, st, lam, differentiable)
        return schur_solve(graph, st, sys, lin.g_pose, lin.g_point)
    else:
        sys = factor_pcg(graph, lin, st, lam)
        rhs = _reduced_rhs(graph, lin.g_pose, lin.g_point, sys)
        dp, _ = pcg(lambda v: reduced_matvec(graph, lin, sys, v),
                    lambda r: mv(sys.precond, r), rhs,
                    options.pcg_max_iterations, options.pcg_tol, differentiable)
    dp = jnp.where(st.pose_active[:, None], dp, 0.0)
    return dp, _back_substitute(graph, lin.g_point, sys, st, dp)


def retract(x: Variables, dp, dl) -> Variables:
    """``T ← T exp(δ)``, ``L ← L + δ``."""
    return Variables(poses=x.poses @ se3.exp(dp), points=x.points + dl)


# ----------------------------------------------------------------------------------------------
# Exact Newton systems (implicit gradients, Newton polish)


def _tangent_cost(graph, xstar, st, dp, dl):
    x = retract(xstar, dp, dl)
    return total_cost(graph, x, st.obs_active)


def _newton_damping(lin, options):
    mean_diag = jnp.mean(jnp.diagonal(lin.H_pose, axis1=-2, axis2=-1))
    return options.implicit_damping * jnp.maximum(mean_diag, 1.0)


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


def _exact_newton_solve(graph, st, x, sys: SchurSystem, v, options: LMOptions):
    """``H^{-1} v`` for the exact Hessian ``H`` of the objective in the tangent space at ``x``:
    conjugate gradients on Hessian-vector products, preconditioned by the (lightly damped)
    Gauss–Newton Schur factorisation ``sys``. Inactive variables stay 0.

    ``H v`` is the forward-mode derivative of the analytic gradient along ``v`` (its Gauss–Newton
    part, the residuals' second derivatives and the robust weights' derivative), cheaper than
    forward-over-reverse through the objective. It differs from the Hessian of ``δ ↦ C(x ⊕ δ)``
    by a term proportional to the gradient (the retraction's curvature), which vanishes at the
    optimum where it is used."""
    N, M = x.poses.shape[0], x.points.shape[0]
    dt = x.points.dtype
    pa = st.pose_active[:, None].astype(dt)
    la = st.point_active[:, None].astype(dt)
    zp, zl = jnp.zeros((N, 6), dt), jnp.zeros((M, 3), dt)

    def grad_at(dp, dl):
        return gradient(graph, retract(x, dp, dl), st)

    def hvp(u):
        _, (hp, hl) = jax.jvp(grad_at, (zp, zl), (u[0] * pa, u[1] * la))
        return (hp * pa, hl * la)

    def precond(r):
        return schur_solve(graph, st, sys, -r[0], -r[1])

    return _pcg_tree(hvp, precond, (v[0] * pa, v[1] * la), options.implicit_cg_iterations,
                     options.implicit_cg_tol)[0]


# ----------------------------------------------------------------------------------------------
# The LM loop
#
# One loop body evaluates the pending candidate (linearise, accept or reject, update λ) and then
# proposes the next one (damped Schur step, or an exact-Newton step in the polish phase), so the
# linearisation and the factorisation each appear once in the compiled program.


@struct.dataclass
class _State:
    x: Variables
    lin: Linearization
    cand: Variables
    pred: jnp.ndarray  # predicted (linearised) decrease of the candidate
    cand_newton: jnp.ndarray  # the candidate is a Newton-polish step
    first: jnp.ndarray  # the candidate is the initial point
    pending: jnp.ndarray
    lam: jnp.ndarray
    iterations: jnp.ndarray
    solves: jnp.ndarray
    newton: jnp.ndarray
    reason: jnp.ndarray
    initial_cost: jnp.ndarray
    history: jnp.ndarray
    sys: SchurSystem | None  # the last Newton factorisation (newton_steps > 0): reused by the adjoint


def _grad_scaled(lin: Linearization):
    """``max_i |g_i| / sqrt(H_ii)``: the Jacobi-scaled gradient (units of sqrt(cost), invariant to
    the variables' units); ``g_i² / 2 H_ii`` is the decrease a step along coordinate ``i`` offers."""
    hp = jnp.diagonal(lin.H_pose, axis1=-2, axis2=-1)
    hl = jnp.diagonal(lin.H_point, axis1=-2, axis2=-1)
    sp = jnp.abs(lin.g_pose) * jax.lax.rsqrt(jnp.maximum(hp, 1e-300))
    sl = jnp.abs(lin.g_point) * jax.lax.rsqrt(jnp.maximum(hl, 1e-300))
    sp = jnp.where(hp > 0, sp, 0.0)
    sl = jnp.where(hl > 0, sl, 0.0)
    return jnp.maximum(jnp.max(sp, initial=0.0), jnp.max(sl, initial=0.0))


def _evaluate(graph, st, options, s: _State, differentiable) -> _State:
    """Linearise at the candidate; GTSAM's acceptance test and λ update (or Newton's)."""
    lin, dt = s.lin, s.lam.dtype
    lin_c = linearize(graph, s.cand, st, differentiable)
    finite = jnp.isfinite(lin_c.cost) & jnp.all(jnp.isfinite(s.cand.poses)) & jnp.all(jnp.isfinite(s.cand.points))
    cost_change = lin.cost - lin_c.cost
    # Levenberg-Marquardt (GTSAM LevenbergMarquardtOptimizer::tryLambda)
    valid = finite & (s.pred >= 0)
    measurable = s.pred > jnp.finfo(dt).eps * lin.lin_err
    fidelity = cost_change / jnp.where(measurable, s.pred, 1.0)
    success = valid & measurable & (fidelity > options.min_model_fidelity)
    small = valid & (jnp.abs(cost_change) < options.rel_tol * lin.cost)
    rel = cost_change / jnp.where(lin.cost != 0, lin.cost, 1.0)
    conv = (rel < options.rel_tol) | (cost_change < options.abs_tol)
    grad_ok = _grad_scaled(lin_c) <= options.grad_tol
    lam_up = s.lam * options.lambda_factor
    it = s.iterations + success.astype(jnp.int32)
    reason = jnp.where(success & grad_ok, 2, jnp.where(success & conv, 1, 0))
    reason = jnp.where(~success & small, 3, reason)
    reason = jnp.where(~success & ~small & (lam_up >= options.lambda_max), 4, reason)
    lam = jnp.where(success, jnp.maximum(options.lambda_min, s.lam / options.lambda_factor),
                    jnp.where(small, s.lam, lam_up))
    # Newton polish: accept when the cost does not rise (beyond round-off) and the gradient shrinks
    tiny = 1e-12 * jnp.abs(lin.cost)
    better = finite & ((lin_c.cost < lin.cost)
                       | ((lin_c.cost <= lin.cost + tiny) & (_grad_scaled(lin_c) < _grad_scaled(lin))))
    accept = jnp.where(s.first, finite, jnp.where(s.cand_newton, better, success))
    first_reason = jnp.where(finite, jnp.where(_grad_scaled(lin_c) <= options.grad_tol, 2, 0), 6)
    reason = jnp.where(s.first, first_reason,
                       jnp.where(s.cand_newton, jnp.where(better & grad_ok, 2, s.reason), reason))
    lm_trial = ~s.first & ~s.cand_newton
    it = jnp.where(lm_trial, it, s.iterations)
    lam = jnp.where(lm_trial, lam, s.lam)
    hidx = jnp.minimum(it, s.history.shape[0] - 1)
    history = s.history.at[hidx].set(jnp.where(lm_trial & success, lin_c.cost, s.history[hidx]))
    history = jnp.where(s.first, jnp.full_like(history, lin_c.cost), history)
    pick = lambda a, b: jax.tree.map(lambda u, v: jnp.where(accept, u, v), a, b)  # noqa: E731
    return s.replace(x=pick(s.cand, s.x), lin=pick(lin_c, lin), lam=lam.astype(dt), iterations=it,
                     solves=s.solves + (~s.first).astype(jnp.int32),
                     newton=s.newton + s.cand_newton.astype(jnp.int32),
                     reason=reason.astype(jnp.int32),
                     initial_cost=jnp.where(s.first, lin_c.cost, s.initial_cost), history=history,
                     first=jnp.zeros_like(s.first))


def _propose(graph, st, options, s: _State, newton, differentiable):
    """The next candidate: a damped Schur step, or (``newton``) an exact-Newton step."""
    lin = s.lin
    N = lin.H_pose.shape[0]
    sys = None
    if options.newton_steps and not differentiable:
        sys = factor_dense(graph, lin, st, jnp.where(newton, _newton_damping(lin, options), s.lam))

        def lm_step():
            if _use_dense(N, options):
                return schur_solve(graph, st, sys, lin.g_pose, lin.g_point)
            return damped_step(graph, lin, st, s.lam, options)

        def newton_step():
            return _exact_newton_solve(graph, st, s.x, sys, (-lin.g_pose, -lin.g_point), options)

        dp, dl = jax.lax.cond(newton, newton_step, lm_step)
    else:
        dp, dl = damped_step(graph, lin, st, s.lam, options, differentiable)
    finite = jnp.all(jnp.isfinite(dp)) & jnp.all(jnp.isfinite(dl))
    dp, dl = jnp.where(finite, dp, 0.0), jnp.where(finite, dl, 0.0)
    pred = jnp.where(finite, lin.lin_err - linearized_error(graph, lin, dp, dl), -1.0)
    return retract(s.x, dp, dl), pred.astype(s.lam.dtype), sys


def _overflow(st: Structure):
    return st.pair_count > st.pair_k1.shape[0]


def _body(graph, st, options, s: _State, differentiable: bool) -> _State:
    s = _evaluate(graph, st, options, s, differentiable)
    ok = ~_overflow(st)  # incomplete Schur pairs: evaluate the initial point, take no step
    lm_running = ok & (s.reason == 0) & (s.solves < options.max_linear_solves) & (s.iterations < options.max_iterations)
    polish = ok & (~lm_running) & (s.newton < options.newton_steps) & (_grad_scaled(s.lin) > options.grad_tol)
    propose = lm_running | polish
    if differentiable:
        cand, pred, sys = _propose(graph, st, options, s, polish, differentiable)
    else:
        cand, pred, sys = jax.lax.cond(propose, lambda: _propose(graph, st, options, s, polish, False),
                                       lambda: (s.x, jnp.zeros_like(s.lam), s.sys))
    return s.replace(cand=cand, pred=pred, cand_newton=polish, pending=propose, sys=sys)


def _start(graph, init: Variables, st, options) -> _State:
    """A state whose pending candidate is the initial point (evaluated by the first body)."""
    dt = init.points.dtype
    N, M = init.poses.shape[0], init.points.shape[0]
    zeros = lambda tree: jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), tree)  # noqa: E731
    lin0 = zeros(jax.eval_shape(lambda: linearize(graph, init, st)))
    sys0 = None
    if options.newton_steps:
        sys0 = zeros(jax.eval_shape(lambda: factor_dense(graph, lin0, st, jnp.ones((), dt))))
    z = jnp.zeros((), jnp.int32)
    return _State(x=init, lin=lin0, cand=init, pred=jnp.zeros((), dt), cand_newton=jnp.zeros((), bool),
                  first=jnp.ones((), bool), pending=jnp.ones((), bool),
                  lam=jnp.asarray(options.lambda_init, dt), iterations=z, solves=z, newton=z, reason=z,
                  initial_cost=jnp.zeros((), dt), history=jnp.zeros((options.max_iterations + 1,), dt),
                  sys=sys0)


def _finish(s: _State, options, st: Structure) -> LMResult:
    idx = jnp.arange(s.history.shape[0])
    hist = jnp.where(idx <= s.iterations, s.history, s.lin.cost)
    reason = jnp.where(_grad_scaled(s.lin) <= options.grad_tol, 2, s.reason)
    reason = jnp.where(reason == 0, 5, reason)
    reason = jnp.where(_overflow(st), PAIR_OVERFLOW, reason)
    params = Variables(poses=orthonormalize_poses(s.x.poses), points=s.x.points)
    return LMResult(params=params, cost=s.lin.cost, initial_cost=s.initial_cost, iterations=s.iterations,
                    linear_solves=s.solves, converged=(reason >= 1) & (reason <= 3),
                    stop_reason=reason, grad_norm=_grad_scaled(s.lin), lambda_=s.lam, cost_history=hist)


def _prepare(graph, init, options, differentiable=False):
    M = init.points.shape[0]
    pairs = _use_dense(init.poses.shape[0], options) or (options.newton_steps > 0 and not differentiable)
    return structure(graph, M, options, with_pairs=pairs)


def _run(graph: FactorGraph, init: Variables, options: LMOptions):
    st = _prepare(graph, init, options)
    s = jax.lax.while_loop(lambda s: s.pending, lambda s: _body(graph, st, options, s, False),
                           _start(graph, init, st, options))
    return _finish(s, options, st), s, st


def _sequential_batching(options: LMOptions) -> bool:
    if options.batching == "auto":
        return jax.default_backend() == "cpu"
    return options.batching == "sequential"


@functools.lru_cache(maxsize=None)
def _batchable_run(options: LMOptions):
    """``_run`` (result, last factorisation, structure) with a ``vmap`` rule that maps the batch
    sequentially (``lax.map``) instead of batching every operation."""

    @custom_vmap
    def run(graph, init):
        res, s, st = _run(graph, init, options)
        return res, s.sys, st

    @run.def_vmap
    def _rule(axis_size, in_batched, graph, init):
        args = jax.tree.map(lambda a, b: a if b else jnp.broadcast_to(a, (axis_size,) + a.shape),
                            (graph, init), tuple(in_batched))
        out = jax.lax.map(lambda gi: run(*gi), args)
        return out, jax.tree.map(lambda _: True, out)

    return run


def _run_batchable(graph, init, options):
    if _sequential_batching(options):
        return _batchable_run(options)(graph, init)
    res, s, st = _run(graph, init, options)
    return res, s.sys, st


def _solve_loop(graph: FactorGraph, init: Variables, options: LMOptions) -> LMResult:
    return _run_batchable(graph, init, options)[0]


def _solve_unrolled(graph: FactorGraph, init: Variables, options: LMOptions) -> LMResult:
    st = _prepare(graph, init, options, differentiable=True)

    @jax.checkpoint
    def body(s, _):
        new = _body(graph, st, options, s, True)
        return jax.tree.map(lambda a, b: jnp.where(s.pending, a, b), new, s), None

    s, _ = jax.lax.scan(body, _start(graph, init, st, options), None, length=options.unroll_steps + 1)
    return _finish(s, options, st)


# ----------------------------------------------------------------------------------------------
# Implicit differentiation


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _solve_implicit(options, graph, init):
    return _solve_loop(graph, init, options)


def _implicit_fwd(options, graph, init):
    res, sys, st = _run_batchable(graph, init, options)
    return res, (graph, res.params, init, sys, st)


def _implicit_bwd(options, saved, ct: LMResult):
    """IFT at the optimum: ``θ̄ = −(∂g/∂θ)^T H^{-1} x̄`` with the exact Hessian ``H``, solved by CG
    preconditioned by the forward pass's last (Newton) Gauss–Newton factorisation."""
    graph, xstar, init, sys, st = saved
    N, M = xstar.poses.shape[0], xstar.points.shape[0]
    dt = xstar.points.dtype
    if sys is None or not st.pair_k1.shape[0] > 1:
        st = structure(graph, M, options, with_pairs=True)
        lin = linearize(graph, xstar, st)
        sys = factor_dense(graph, lin, st, _newton_damping(lin, options))
    zp, zl = jnp.zeros((N, 6), dt), jnp.zeros((M, 3), dt)

    # cotangent of the outputs -> cotangent in the tangent space at x*
    _, vjp_retract = jax.vjp(lambda dp, dl: retract(xstar, dp, dl), zp, zl)
    ct_params = jax.tree.map(lambda c, p: jnp.zeros_like(p) if c.dtype == jax.dtypes.float0 else c,
                             ct.params, xstar)
    gp, gl = vjp_retract(ct_params)

    u = _exact_newton_solve(graph, st, xstar, sys, (gp, gl), options)
    ct_cost = ct.cost if ct.cost.dtype != jax.dtypes.float0 else jnp.zeros((), dt)

    def scalar(g):
        _, d = jax.jvp(lambda dp, dl: _tangent_cost(g, xstar, st, dp, dl), (zp, zl), (u[0], u[1]))
        return -d + ct_cost * total_cost(g, xstar, st.obs_active)

    _, vjp_graph = jax.vjp(scalar, graph)
    (ct_graph,) = vjp_graph(jnp.ones((), dt))
    ct_init = jax.tree.map(jnp.zeros_like, init)
    return ct_graph, ct_init


def _pcg_tree(matvec, precond, b, max_iterations, tol):
    """:func:`pcg` on a tuple of arrays (flattened)."""
    shapes = [a.shape for a in b]
    sizes = [a.size for a in b]

    def flat(t):
        return jnp.concatenate([a.reshape(-1) for a in t])

    def unflat(v):
        out, o = [], 0
        for sh, n in zip(shapes, sizes):
            out.append(v[o:o + n].reshape(sh))
            o += n
        return tuple(out)

    x, it = pcg(lambda v: flat(matvec(unflat(v))), lambda r: flat(precond(unflat(r))), flat(b),
                max_iterations, tol)
    return unflat(x), it


_solve_implicit.defvjp(_implicit_fwd, _implicit_bwd)


# ----------------------------------------------------------------------------------------------
# Public entry point


def solve(graph: FactorGraph, init: Variables, options: LMOptions = LMOptions()) -> LMResult:
    """Minimise the factor graph's objective from ``init`` -> :class:`LMResult`.

    graph: :class:`~cm3d.solvers.factors.FactorGraph` (N poses, K projection slots, ...);
    init: :class:`~cm3d.solvers.factors.Variables` (poses (N, 4, 4), points (M, 3)). Pure and
    jittable (``options`` static), ``vmap``-able over problems of equal capacities. Gradients of
    ``result.params`` / ``result.cost`` w.r.t. the graph's float leaves follow ``options.backward``.
    """
    if options.backward == "implicit":
        return _solve_implicit(options, graph, init)
    if options.backward == "unrolled":
        return _solve_unrolled(graph, init, options)
    return _solve_loop(graph, init, options)


solve_jit = jax.jit(solve, static_argnames=("options",))
