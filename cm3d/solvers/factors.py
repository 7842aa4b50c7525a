"""CogniMap3D's factor graph: batched residual functions over padded index arrays (jaxls style).

The objective (paper, "factor graph"), GTSAM's convention (Huber ``ρ`` on the whitened norm)::

    C(T, L) = ½|f_prior|² + Σ_k w_k ρ(|f_proj,k|) + ½ Σ_i |f_motion,i|²
    f_prior  = (T_0 ⊖ T_0^init) / σ_prior                              (6,)  gauge fixing
    f_proj   = (π(T_i, L_j) − z_ij) / σ_ij,  σ_ij² ← α σ_ij² for memory landmarks   (2,)
    f_motion = ((T_a^{-1} T_b) ⊖ (T_a^{0 -1} T_b^0)) / σ_motion  (6,)

Poses cam_to_world 4x4, landmarks world (3,), ``π`` the pinhole of :mod:`cm3d.ops.camera`,
``a ⊖ b = log(b^{-1} a)`` in jaxlie's order (translation first). Factor families are pytrees with
a leading slot axis, padded with ``weight = 0``. Jacobians are w.r.t. the right perturbation
``T exp(ξ)``. Entry points: :func:`build_graph`, :func:`total_cost`, :func:`reject_outliers`.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from flax import struct

from cm3d.ops import robust, se3

MIN_DEPTH = 1e-6  # camera z below which a projection is a cheirality failure


# Data


@struct.dataclass
class Variables:
    """Optimisation variables: poses (N, 4, 4) cam_to_world, points (M, 3) world landmarks."""

    poses: jnp.ndarray
    points: jnp.ndarray


@struct.dataclass
class ProjectionFactors:
    """Reprojection factors ``w ρ(|(π(T_pose, L_point) − z) / σ|)``, K slots.

    pose_idx, point_idx: (K,) int32; z: (K, 2) observed pixel ``(u, v)``; sigma: (K,) isotropic
    pixel std; weight: (K,) >= 0 multiplier of the robust cost (0 = padding / rejected);
    memory: (K,) bool, landmark recalled from memory (its σ² is scaled by the graph's α).
    depth: optional (K,) measured camera depth of the observation (RGB-D style; 0 = none): a third
    residual row ``(log z − log depth) / depth_sigma``, in the same robust kernel; depth_sigma: (K,)
    std of log depth (relative depth noise), also scaled by α for memory landmarks.
    """

    pose_idx: jnp.ndarray
    point_idx: jnp.ndarray
    z: jnp.ndarray
    sigma: jnp.ndarray
    weight: jnp.ndarray
    memory: jnp.ndarray
    depth: jnp.ndarray | None = None
    depth_sigma: jnp.ndarray | None = None


@struct.dataclass
class PriorFactors:
    """Pose priors ``½ w |(T_pose ⊖ target) / σ|²``, P slots.

    pose_idx: (P,) int32; target: (P, 4, 4); sigma: (P, 6) tangent std (translation first);
    weight: (P,) >= 0 (0 = padding).
    """

    pose_idx: jnp.ndarray
    target: jnp.ndarray
    sigma: jnp.ndarray
    weight: jnp.ndarray


@struct.dataclass
class MotionFactors:
    """Relative-motion (between) factors ``½ w |((T_a^{-1} T_b) ⊖ measured) / σ|²``, Q slots.

    idx_a, idx_b: (Q,) int32; measured: (Q, 4, 4) ``T_a^{0 -1} T_b^0``; sigma: (Q, 6); weight: (Q,).
    """

    idx_a: jnp.ndarray
    idx_b: jnp.ndarray
    measured: jnp.ndarray
    sigma: jnp.ndarray
    weight: jnp.ndarray


@struct.dataclass
class PointPriorFactors:
    """Priors on landmarks ``½ w |S (L − target)|²`` (M slots): target (M, 3); sqrt_info (M, 3, 3) the
    whitening ``S`` (``I / σ`` isotropic, ``[nᵀ / σ; 0; 0]`` point-to-plane); weight (M,) (0 = none)."""

    target: jnp.ndarray
    sqrt_info: jnp.ndarray
    weight: jnp.ndarray


@struct.dataclass
class FactorGraph:
    """The whole problem: intrinsics (N, 3, 3), the factor families, the Huber threshold ``huber_k``
    (whitened; ``inf`` = least squares) and the memory covariance scale ``memory_alpha`` (α < 1 trusts
    memory landmarks more). All leaves are arrays, so gradients flow to every float. ``pose_fixed``
    (N,) holds poses (structure-only solves); ``point_prior``: optional :class:`PointPriorFactors`."""

    intrinsics: jnp.ndarray
    projection: ProjectionFactors
    prior: PriorFactors
    motion: MotionFactors
    huber_k: jnp.ndarray
    memory_alpha: jnp.ndarray
    pose_fixed: jnp.ndarray
    point_prior: PointPriorFactors | None = None

    @property
    def num_poses(self) -> int:
        return int(self.intrinsics.shape[-3])


# Robust kernel


def _safe_sqrt(s):
    pos = s > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, s, 1.0)), 0.0)


def huber_loss(sq_norm, k):
    """GTSAM's Huber ``ρ(x)`` of the whitened norm ``x = sqrt(sq_norm)``: ``x²/2`` or ``k x − k²/2``."""
    x = _safe_sqrt(sq_norm)
    outer = x > k
    k_safe = jnp.where(jnp.isfinite(k), k, 0.0)
    return jnp.where(outer, k_safe * x - 0.5 * k_safe * k_safe, 0.5 * sq_norm)


def huber_weight(sq_norm, k):
    """IRLS weight ``ρ'(x)/x``: 1 inside the threshold, ``k/x`` outside (GTSAM's reweighting)."""
    x = _safe_sqrt(sq_norm)
    outer = x > k
    return jnp.where(outer, k / jnp.where(outer, x, 1.0), 1.0)


# Projection factor


def mm(a, b):
    """Small batched matmul ``a (..., i, c) @ b (..., c, j)`` unrolled over ``c`` (XLA:CPU runs batched
    dots of 2x3 / 6x3 blocks far slower than fused elementwise code)."""
    return sum(a[..., :, c, None] * b[..., None, c, :] for c in range(a.shape[-1]))


def mtm(a, b):
    """``a^T b`` for small batched blocks ``a (..., r, i)``, ``b (..., r, j)`` (unrolled over r)."""
    return sum(a[..., r, :, None] * b[..., r, None, :] for r in range(a.shape[-2]))


def mv(a, v):
    """``a (..., i, c) @ v (..., c)`` unrolled over c."""
    return sum(a[..., :, c] * v[..., c, None] for c in range(a.shape[-1]))


def mtv(a, v):
    """``a^T v`` for ``a (..., r, i)``, ``v (..., r)`` unrolled over r."""
    return sum(a[..., r, :] * v[..., r, None] for r in range(a.shape[-2]))


def _skew(v):
    z = jnp.zeros_like(v[..., 0])
    return jnp.stack([
        jnp.stack([z, -v[..., 2], v[..., 1]], -1),
        jnp.stack([v[..., 2], z, -v[..., 0]], -1),
        jnp.stack([-v[..., 1], v[..., 0], z], -1),
    ], -2)


def effective_sigma(graph: FactorGraph):
    """(K,) pixel std of each projection factor after the memory scaling ``σ² ← α σ²``."""
    f = graph.projection
    alpha = jnp.asarray(graph.memory_alpha, f.sigma.dtype)
    return f.sigma * jnp.where(f.memory, jnp.sqrt(alpha), 1.0)


def project(poses, points, K):
    """Pixels (..., 2) and camera z (...) of world points (..., 3) in cameras poses (..., 4, 4)."""
    R, t = poses[..., :3, :3], poses[..., :3, 3]
    pc = mtv(R, points - t)
    z = pc[..., 2]
    zs = jnp.where(z > MIN_DEPTH, z, 1.0)
    uvw = mv(K, pc)
    return uvw[..., :2] / zs[..., None], z


def _depth_rows(graph: FactorGraph, z, front):
    """The depth factors' whitened log-depth residual (K,), its scale ``1 / (z σ_d)`` for the
    Jacobian (K,) (0 where there is no measured depth or the point is behind the camera)."""
    f = graph.projection
    alpha = jnp.asarray(graph.memory_alpha, z.dtype)
    sd = f.depth_sigma * jnp.where(f.memory, jnp.sqrt(alpha), 1.0)
    has = front & (f.depth > MIN_DEPTH)
    zs = jnp.where(has, z, 1.0)
    r = jnp.where(has, (jnp.log(zs) - jnp.log(jnp.where(has, f.depth, 1.0))) / sd, 0.0)
    return r, jnp.where(has, 1.0 / (zs * sd), 0.0)


def projection_residual(graph: FactorGraph, x: Variables):
    """Whitened reprojection residuals (K, 2) and cheirality validity (K,); behind the camera the
    residual is the constant ``2 f_x / σ`` with zero derivative (GTSAM's convention). With measured
    depths (:class:`ProjectionFactors`) the residual is (K, 3): the log-depth row last."""
    f = graph.projection
    T = x.poses[f.pose_idx]
    K = graph.intrinsics[f.pose_idx]
    uv, z = project(T, x.points[f.point_idx], K)
    sig = effective_sigma(graph)
    front = z > MIN_DEPTH
    r = jnp.where(front[:, None], uv - f.z, 2.0 * K[:, 0, 0][:, None]) / sig[:, None]
    if f.depth is not None:
        r = jnp.concatenate([r, _depth_rows(graph, z, front)[0][:, None]], -1)
    return r, front


def projection_linearize(graph: FactorGraph, x: Variables):
    """Whitened residuals e (K, 2) and analytic Jacobians A = de/dξ_pose (K, 2, 6), B = de/dL (K, 2, 3)
    (three rows each with measured depths).

    With ``p_c = R^T (L − t)``: ``dp_c/dξ = [−I, [p_c]×]`` (right perturbation ``T exp(ξ)``,
    translation first), ``dp_c/dL = R^T``, ``duv/dp_c = (K_{:2} − uv e_3^T) / z``.
    """
    f = graph.projection
    T = x.poses[f.pose_idx]
    K = graph.intrinsics[f.pose_idx]
    R, t = T[:, :3, :3], T[:, :3, 3]
    pc = mtv(R, x.points[f.point_idx] - t)
    z = pc[:, 2]
    front = z > MIN_DEPTH
    zs = jnp.where(front, z, 1.0)
    uvw = mv(K, pc)
    uv = uvw[:, :2] / zs[:, None]
    sig = effective_sigma(graph)
    inv_s = 1.0 / sig
    e = jnp.where(front[:, None], uv - f.z, 2.0 * K[:, 0, 0][:, None]) * inv_s[:, None]
    e3 = jnp.array([0.0, 0.0, 1.0], pc.dtype)
    P = (K[:, :2, :] - uv[:, :, None] * e3) / zs[:, None, None]  # (K, 2, 3)
    P = P * (jnp.where(front, inv_s, 0.0))[:, None, None]
    if f.depth is not None:  # d log z / d p_c = e_3ᵀ / z
        rd, sc = _depth_rows(graph, z, front)
        e = jnp.concatenate([e, rd[:, None]], -1)
        P = jnp.concatenate([P, (sc[:, None] * e3)[:, None, :]], 1)
    A = jnp.concatenate([-P, mm(P, _skew(pc))], -1)
    B = mm(P, jnp.swapaxes(R, -1, -2))
    return e, A, B, front


# Pose factors (prior, motion)


def _log(T):
    return jaxlie.SE3.from_matrix(T).log()


def _pose_errors(graph: FactorGraph, poses):
    """Error transforms (P + Q, 4, 4): ``target^{-1} T`` of the priors, then
    ``measured^{-1} T_a^{-1} T_b`` of the motion factors, and ``X = T_a^{-1} T_b`` (Q, 4, 4)."""
    pf, mf = graph.prior, graph.motion
    Ep = se3.inverse(pf.target) @ poses[pf.pose_idx]
    X = se3.inverse(poses[mf.idx_a]) @ poses[mf.idx_b]
    Em = se3.inverse(mf.measured) @ X
    return jnp.concatenate([Ep, Em], 0), X


def pose_residuals(graph: FactorGraph, poses):
    """Whitened prior (P, 6) and motion (Q, 6) residuals: ``(T ⊖ target)/σ``,
    ``((T_a^{-1} T_b) ⊖ measured)/σ`` (one batched jaxlie log)."""
    P = graph.prior.pose_idx.shape[0]
    E, _ = _pose_errors(graph, poses)
    xi = _log(E)
    return xi[:P] / graph.prior.sigma, xi[P:] / graph.motion.sigma


def adjoint(T):
    """SE(3) adjoint (..., 6, 6) of poses (..., 4, 4) in jaxlie's order: ``[[R, [t]× R], [0, R]]``."""
    R, t = T[..., :3, :3], T[..., :3, 3]
    top = jnp.concatenate([R, mm(_skew(t), R)], -1)
    bottom = jnp.concatenate([jnp.zeros_like(R), R], -1)
    return jnp.concatenate([top, bottom], -2)


def ad(xi):
    """SE(3) ``ad`` (..., 6, 6) of tangents (..., 6) in jaxlie's order: ``[[ω^, v^], [0, ω^]]``."""
    v, w = _skew(xi[..., :3]), _skew(xi[..., 3:])
    return jnp.concatenate([jnp.concatenate([w, v], -1),
                            jnp.concatenate([jnp.zeros_like(w), w], -1)], -2)


def jlog(E: jaxlie.SE3):
    """``d log(E exp ξ)/dξ`` at 0, i.e. ``J_r^{-1}(log E)`` (..., 6, 6), differentiable everywhere.
    jaxlie's ``jlog`` has a NaN derivative at the identity, so below 0.01 rad the series
    ``I + ad/2 + ad²/12 − ad⁴/720`` is used (double ``where``, no NaN branch)."""
    xi = E.log()
    small = jnp.sum(xi[..., 3:] ** 2, -1) < 1e-4
    A = ad(xi)
    A2 = mm(A, A)
    eye = jnp.eye(6, dtype=xi.dtype)
    taylor = eye + 0.5 * A + A2 / 12.0 - mm(A2, A2) / 720.0
    away = jaxlie.SE3.exp(jnp.array([0.0, 0.0, 0.0, 0.3, 0.0, 0.0], xi.dtype)).wxyz_xyz
    safe = jaxlie.SE3(jnp.where(small[..., None], away, E.wxyz_xyz))
    return jnp.where(small[..., None, None], taylor, safe.jlog().astype(xi.dtype))


def pose_factor_jacobians(graph: FactorGraph, poses, method: str = "analytic"):
    """Whitened residuals and Jacobians of the pose factors w.r.t. right perturbations ``T exp(ξ)``.

    Returns (e_prior (P, 6), J_prior (P, 6, 6), e_motion (Q, 6), J_a (Q, 6, 6), J_b (Q, 6, 6)).
    ``"analytic"``: ``d log(E exp ξ)/dξ = J_r^{-1}(log E)`` (:func:`jlog`), and ``T_a`` enters through
    ``−J_r^{-1} Ad((T_a^{-1} T_b)^{-1})``; ``"autodiff"``: ``jax.jacfwd`` through ``exp`` (reference).
    """
    if method == "autodiff":
        return _pose_factor_jacobians_autodiff(graph, poses)
    if method != "analytic":
        raise ValueError(f"pose_factor_jacobians: unknown method {method!r} (analytic, autodiff)")
    pf, mf = graph.prior, graph.motion
    P = pf.pose_idx.shape[0]
    E, X = _pose_errors(graph, poses)
    Eg = jaxlie.SE3.from_matrix(E)
    sig = jnp.concatenate([pf.sigma, mf.sigma], 0)
    e = Eg.log() / sig
    J = jlog(Eg) / sig[:, :, None]
    J_a = -mm(J[P:], adjoint(se3.inverse(X)))
    return e[:P], J[:P], e[P:], J_a, J[P:]


def _pose_factor_jacobians_autodiff(graph: FactorGraph, poses):
    pf, mf = graph.prior, graph.motion
    zero6 = jnp.zeros(6, poses.dtype)

    def prior_one(T, target, sigma, d):
        return _log(se3.inverse(target) @ T @ se3.exp(d)) / sigma

    def motion_one(Ta, Tb, meas, sigma, da, db):
        rel = se3.inverse(Ta @ se3.exp(da)) @ (Tb @ se3.exp(db))
        return _log(se3.inverse(meas) @ rel) / sigma

    Tp = poses[pf.pose_idx]
    e_p = jax.vmap(prior_one, (0, 0, 0, None))(Tp, pf.target, pf.sigma, zero6)
    J_p = jax.vmap(jax.jacfwd(prior_one, 3), (0, 0, 0, None))(Tp, pf.target, pf.sigma, zero6)
    Ta, Tb = poses[mf.idx_a], poses[mf.idx_b]
    args = (Ta, Tb, mf.measured, mf.sigma, zero6, zero6)
    axes = (0, 0, 0, 0, None, None)
    e_m = jax.vmap(motion_one, axes)(*args)
    J_a, J_b = jax.vmap(jax.jacfwd(motion_one, (4, 5)), axes)(*args)
    return e_p, J_p, e_m, J_a, J_b


# Cost


def total_cost(graph: FactorGraph, x: Variables, obs_mask=None):
    """GTSAM-convention objective ``½|f_prior|² + Σ w ρ(|f_proj|) + ½Σ|f_motion|²`` (scalar).

    obs_mask: optional (K,) bool restricting the projection factors (the solver passes the factors
    of landmarks it can estimate). Written with plain ops, so it is twice differentiable almost
    everywhere (the implicit gradient uses its exact Hessian).
    """
    f = graph.projection
    e, _ = projection_residual(graph, x)
    w = f.weight if obs_mask is None else jnp.where(obs_mask, f.weight, 0.0)
    k = jnp.asarray(graph.huber_k, e.dtype)
    proj = jnp.sum(w * huber_loss(jnp.sum(e * e, -1), k))
    ep, em = pose_residuals(graph, x.poses)
    prior = 0.5 * jnp.sum(graph.prior.weight * jnp.sum(ep * ep, -1))
    motion = 0.5 * jnp.sum(graph.motion.weight * jnp.sum(em * em, -1))
    return proj + prior + motion + point_prior_cost(graph, x.points)


def point_prior_residual(graph: FactorGraph, points):
    """Whitened landmark-prior residuals ``S (L − target)`` (M, 3) (zeros without point priors);
    the Jacobian with respect to ``L`` is ``S``."""
    pp = graph.point_prior
    if pp is None:
        return jnp.zeros_like(points)
    return jnp.einsum("mij,mj->mi", pp.sqrt_info.astype(points.dtype), points - pp.target.astype(points.dtype))


def point_prior_cost(graph: FactorGraph, points):
    """``½ Σ w |S (L − target)|²`` (0 without point priors)."""
    if graph.point_prior is None:
        return jnp.zeros((), points.dtype)
    r = point_prior_residual(graph, points)
    return 0.5 * jnp.sum(graph.point_prior.weight * jnp.sum(r * r, -1))


def with_point_prior(graph: FactorGraph, target, sqrt_info, weight) -> FactorGraph:
    """``graph`` with landmark priors (see :class:`PointPriorFactors`); target (M, 3), sqrt_info
    (M, 3, 3), weight (M,) (bool or >= 0)."""
    dt = graph.intrinsics.dtype
    weight = jnp.asarray(weight)
    weight = weight.astype(dt) if weight.dtype == bool else jnp.asarray(weight, dt)
    return graph.replace(point_prior=PointPriorFactors(jnp.asarray(target, dt), jnp.asarray(sqrt_info, dt), weight))


# The paper's graph


@dataclasses.dataclass(frozen=True)
class GraphConfig:
    """Noise model of the paper's graph. Units: pixels, radians, and the poses' length unit.

    sigma_proj: reprojection std (px); huber_k: Huber threshold in std units; memory_alpha: covariance
    scale of memory-landmark projections (0 < α < 1); prior_sigma_*: the gauge prior on the first pose;
    motion_sigma_*: std of the relative-motion factors from the initial poses; motion_pairs (static):
    ``"consecutive"`` the paper's chain ``T_{i−1}^{-1} T_i``, ``"anchor"`` ``T_0^{-1} T_i`` (the prior's
    errors are per frame, not a random walk; docs/factor_graph.md), ``"both"``.
    """

    sigma_proj: float = 1.0
    huber_k: float = 2.0
    memory_alpha: float = 0.5
    prior_sigma_rot: float = 1e-4
    prior_sigma_trans: float = 1e-4
    motion_sigma_rot: float = 0.05
    motion_sigma_trans: float = 0.05
    motion_pairs: str = "consecutive"

    def __post_init__(self):
        if self.motion_pairs not in MOTION_PAIRS:
            raise ValueError(f"GraphConfig.motion_pairs: unknown {self.motion_pairs!r} ({', '.join(MOTION_PAIRS)})")
        for name in ("sigma_proj", "huber_k", "prior_sigma_rot", "prior_sigma_trans",
                     "motion_sigma_rot", "motion_sigma_trans"):
            if not getattr(self, name) > 0:
                raise ValueError(f"GraphConfig.{name}: must be > 0, got {getattr(self, name)}")
        if not 0 < self.memory_alpha:
            raise ValueError(f"GraphConfig.memory_alpha: must be > 0, got {self.memory_alpha}")


MOTION_PAIRS = ("anchor", "consecutive", "both")


def motion_pairs(num_poses: int, kind: str = "consecutive"):
    """Index pairs (idx_a, idx_b) (Q,) int32 of the motion factors over ``num_poses`` poses
    (:attr:`GraphConfig.motion_pairs`): ``anchor`` 0 -> i, ``consecutive`` i − 1 -> i for
    i = 1..N−1, ``both`` the anchor pairs then the consecutive ones."""
    ib = jnp.arange(1, num_poses, dtype=jnp.int32)
    if kind == "anchor":
        return jnp.zeros_like(ib), ib
    if kind == "consecutive":
        return ib - 1, ib
    if kind == "both":
        return jnp.concatenate([jnp.zeros_like(ib), ib - 1]), jnp.concatenate([ib, ib])
    raise ValueError(f"motion_pairs: unknown kind {kind!r} ({', '.join(MOTION_PAIRS)})")


def _tangent_sigma(rot, trans, n, dtype):
    return jnp.broadcast_to(jnp.array([trans] * 3 + [rot] * 3, dtype), (n, 6))


def build_graph(init_poses, intrinsics, pose_idx, point_idx, uv, valid, memory=None,
                pose_valid=None, cfg: GraphConfig = GraphConfig(), depth=None, depth_sigma=None) -> FactorGraph:
    """The paper's graph from initial poses and padded observations.

    init_poses: (N, 4, 4) T^0 (prior poses); intrinsics: (N, 3, 3); pose_idx, point_idx: (K,);
    uv: (K, 2) observed pixels; valid: (K,) bool or weights; memory: (K,) bool (landmark recalled
    from memory: ``Σ_proj ← α Σ_proj``); pose_valid: (N,) bool, padded pose slots get no motion
    factors. One prior on pose 0 (``T_0 ⊖ T_0^init``), motion factors between the valid pose pairs
    of ``cfg.motion_pairs`` (default: consecutive poses) from ``T_a^{0 -1} T_b^0``. depth: optional
    (K,) measured depth per observation (0 = none) with depth_sigma (scalar or (K,)) its log std.
    Jittable; gradients flow to every float input.
    """
    init_poses = jnp.asarray(init_poses)
    dt = init_poses.dtype
    N = init_poses.shape[0]
    Kn = pose_idx.shape[0]
    valid = jnp.asarray(valid)
    weight = valid.astype(dt) if valid.dtype == bool else jnp.asarray(valid, dt)
    memory = jnp.zeros(Kn, bool) if memory is None else jnp.asarray(memory, bool)
    pv = jnp.ones(N, bool) if pose_valid is None else jnp.asarray(pose_valid, bool)
    proj = ProjectionFactors(
        pose_idx=jnp.asarray(pose_idx, jnp.int32), point_idx=jnp.asarray(point_idx, jnp.int32),
        z=jnp.asarray(uv, dt), sigma=jnp.full(Kn, cfg.sigma_proj, dt), weight=weight, memory=memory)
    if depth is not None:
        if depth_sigma is None:
            raise ValueError("build_graph: depth needs depth_sigma (the log-depth std)")
        proj = proj.replace(depth=jnp.asarray(depth, dt), depth_sigma=jnp.broadcast_to(jnp.asarray(depth_sigma, dt), (Kn,)))
    prior = PriorFactors(
        pose_idx=jnp.zeros(1, jnp.int32), target=init_poses[:1],
        sigma=_tangent_sigma(cfg.prior_sigma_rot, cfg.prior_sigma_trans, 1, dt),
        weight=pv[:1].astype(dt))
    ia, ib = motion_pairs(N, cfg.motion_pairs)
    motion = MotionFactors(
        idx_a=ia, idx_b=ib, measured=se3.inverse(init_poses[ia]) @ init_poses[ib],
        sigma=_tangent_sigma(cfg.motion_sigma_rot, cfg.motion_sigma_trans, ia.shape[0], dt),
        weight=(pv[ia] & pv[ib]).astype(dt))
    return FactorGraph(intrinsics=jnp.asarray(intrinsics, dt), projection=proj, prior=prior,
                       motion=motion, huber_k=jnp.asarray(cfg.huber_k, dt),
                       memory_alpha=jnp.asarray(cfg.memory_alpha, dt), pose_fixed=jnp.zeros(N, bool))


# After solving: re-orthonormalisation and adaptive outlier rejection


def orthonormalize_poses(poses):
    """Poses (..., 4, 4) with rotations re-orthonormalised by SVD (paper: after solving). The derivative
    passes straight through (SVD derivatives are singular at repeated singular values)."""
    fixed = se3.orthonormalize_pose(jax.lax.stop_gradient(poses))
    return poses + jax.lax.stop_gradient(fixed - poses)


@dataclasses.dataclass(frozen=True)
class OutlierConfig:
    """Adaptive reprojection threshold ``τ = max(τ_min, median + n_mad · 1.4826 · MAD)`` in px."""

    tau_min_px: float = 2.0
    n_mad: float = 3.0


def reprojection_errors(graph: FactorGraph, x: Variables):
    """Pixel reprojection error norms (K,) (cheirality failures: inf)."""
    f = graph.projection
    uv, z = project(x.poses[f.pose_idx], x.points[f.point_idx], graph.intrinsics[f.pose_idx])
    err = jnp.linalg.norm(uv - f.z, axis=-1)
    return jnp.where(z > MIN_DEPTH, err, jnp.inf)


def adaptive_threshold(errors, valid, cfg: OutlierConfig = OutlierConfig()):
    """``τ = max(τ_min, median + n_mad · 1.4826 · MAD)`` of the valid errors (px)."""
    finite = valid & jnp.isfinite(errors)
    e = jnp.where(finite, errors, 0.0)
    return jnp.maximum(cfg.tau_min_px, robust.masked_median(e, finite) + cfg.n_mad * robust.mad_sigma(e, finite))


def reject_outliers(graph: FactorGraph, x: Variables, cfg: OutlierConfig = OutlierConfig()):
    """Zero the weight of projection factors whose error exceeds the adaptive threshold.

    Returns (graph with rejected factors' weight 0, inlier mask (K,), threshold τ in px).
    """
    f = graph.projection
    err = reprojection_errors(graph, x)
    valid = f.weight > 0
    tau = adaptive_threshold(err, valid, cfg)
    inlier = valid & (err <= tau)
    proj = f.replace(weight=jnp.where(inlier, f.weight, 0.0))
    return graph.replace(projection=proj), inlier, tau


def calibrate_depth(graph: FactorGraph, x: Variables, inlier, floor: float) -> FactorGraph:
    """The depth factors re-fitted to the solution ``x`` from its ``inlier`` (K,) observations.

    * **Per-frame scale.** Each frame's depths are rescaled by its median ratio ``z / depth``
      relative to the median frame's. A per-frame depth scale is common in predicted depth (VGGT's),
      and independent per-observation factors cannot absorb it: they would move the camera along
      its axis instead. The frames' common scale stays the depths'.
    * **Noise.** The log-depth residuals are not independent within a frame: the per-frame scales
      ``s_i`` scatter by ``σ_s`` (robust, over the frames), far more than ``n_i`` independent
      observations of noise ``σ_w`` (the rescaled residuals' robust std) would let their median
      scatter. What the rescaling removes is one of a frame's correlated errors (a tilt or a smooth
      bias remains, of the same order), so a frame's ``n_i`` depth factors are weighted to carry
      one measurement of std ``σ_s`` together: ``depth_sigma = max(σ_w, σ_s √n_i, floor)``.

    Frames with fewer than 8 such observations keep their depths; with fewer than 8 such
    observations in all, or fewer than 3 frames with 8, the sigmas stay as they were."""
    f = graph.projection
    N = graph.intrinsics.shape[0]
    _, z = project(x.poses[f.pose_idx], x.points[f.point_idx], graph.intrinsics[f.pose_idx])
    ok = inlier & (f.depth > MIN_DEPTH) & (z > MIN_DEPTH)
    r = jnp.where(ok, jnp.log(jnp.where(ok, z, 1.0)) - jnp.log(jnp.where(ok, f.depth, 1.0)), 0.0)
    n = jax.ops.segment_sum(ok.astype(jnp.int32), f.pose_idx, N)
    s = robust.segment_median(r, f.pose_idx, ok, N)
    has = n >= 8
    s = jnp.where(has, s - robust.masked_median(s, has), 0.0)
    depth = f.depth * jnp.exp(s)[f.pose_idx]
    white = robust.mad_sigma(r - s[f.pose_idx], ok)
    frame = robust.mad_sigma(s, has) * jnp.sqrt(n.astype(r.dtype))
    sig = jnp.maximum(jnp.maximum(white, frame[f.pose_idx]), floor)
    sig = jnp.where((jnp.sum(ok) >= 8) & (jnp.sum(has) >= 3), sig, f.depth_sigma)
    return graph.replace(projection=f.replace(depth=depth.astype(f.depth.dtype), depth_sigma=sig.astype(f.depth_sigma.dtype)))


# A seeded bundle-adjustment problem (tests, benchmarks)


def random_problem(seed: int, num_poses: int, num_points: int, obs_per_point: int = 12,
                   pixel_noise: float = 1.0, outlier_frac: float = 0.02, pose_noise: float = 0.02,
                   point_noise: float = 0.05, cfg: GraphConfig = GraphConfig(),
                   obs_capacity: int | None = None, width: int = 640, height: int = 480):
    """A video-like bundle-adjustment problem with the paper's factors (host, numpy; tests, benchmarks).

    Cameras on a gentle arc, landmarks 3–6 units ahead seen by ``obs_per_point`` consecutive cameras,
    Gaussian pixel noise plus ``outlier_frac`` gross outliers (10–40 px); initial poses and landmarks
    are the truth perturbed by ``pose_noise`` / ``point_noise``. Returns (graph, init, truth Variables).
    """
    rng = np.random.default_rng(seed)
    N, M = num_poses, num_points
    n_obs = min(obs_per_point, N)
    f = 0.8 * width
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    s = np.linspace(0, 1, N)
    poses = np.tile(np.eye(4), (N, 1, 1))
    for i in range(N):
        yaw = 0.6 * s[i] + 0.02 * np.sin(7 * s[i])
        c, sn = np.cos(yaw), np.sin(yaw)
        R = np.array([[c, 0, sn], [0, 1, 0], [-sn, 0, c]])
        poses[i, :3, :3] = R
        poses[i, :3, 3] = [3.0 * s[i], 0.1 * np.sin(5 * s[i]), 0.5 * s[i]]
    first = rng.integers(0, N - n_obs + 1, M)
    pts = np.zeros((M, 3))
    for j in range(M):
        mid = poses[first[j] + n_obs // 2]
        d = rng.uniform(3.0, 6.0)
        u, v = rng.uniform(0.1 * width, 0.9 * width), rng.uniform(0.1 * height, 0.9 * height)
        ray = np.linalg.solve(K, [u, v, 1.0])
        pts[j] = mid[:3, :3] @ (ray * d) + mid[:3, 3]
    pose_idx = (first[:, None] + np.arange(n_obs)[None]).ravel()
    point_idx = np.repeat(np.arange(M), n_obs)
    Tinv = np.linalg.inv(poses[pose_idx])
    pc = np.einsum("kij,kj->ki", Tinv[:, :3, :3], pts[point_idx]) + Tinv[:, :3, 3]
    uv = (pc @ K.T)[:, :2] / pc[:, 2:3]
    uv += rng.normal(0, pixel_noise, uv.shape)
    out = rng.random(len(uv)) < outlier_frac
    ang = rng.uniform(0, 2 * np.pi, len(uv))
    mag = rng.uniform(10, 40, len(uv))
    uv[out] += np.stack([np.cos(ang), np.sin(ang)], -1)[out] * mag[out, None]
    from scipy.spatial.transform import Rotation

    xi = rng.normal(size=(N, 6)) * pose_noise
    xi[0] = 0
    noise = np.tile(np.eye(4), (N, 1, 1))
    noise[:, :3, :3] = Rotation.from_rotvec(xi[:, 3:]).as_matrix()
    noise[:, :3, 3] = xi[:, :3]
    init_poses = poses @ noise
    init_pts = pts + rng.normal(0, point_noise, pts.shape)
    Kcap = obs_capacity or len(uv)
    pad = Kcap - len(uv)
    if pad < 0:
        raise ValueError(f"obs_capacity {Kcap} < {len(uv)} observations")
    valid = np.concatenate([np.ones(len(uv), bool), np.zeros(pad, bool)])
    pose_idx = np.concatenate([pose_idx, np.zeros(pad, int)])
    point_idx = np.concatenate([point_idx, np.zeros(pad, int)])
    uv = np.concatenate([uv, np.zeros((pad, 2))])
    graph = build_graph(init_poses, np.broadcast_to(K, (N, 3, 3)), pose_idx, point_idx, uv, valid,
                        cfg=cfg)
    return graph, Variables(jnp.asarray(init_poses), jnp.asarray(init_pts)), \
        Variables(jnp.asarray(poses), jnp.asarray(pts))
