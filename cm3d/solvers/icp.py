"""ICP in JAX: point-to-point (SE(3) or Sim(3)) and point-to-plane (Gauss-Newton on SE(3) or Sim(3),
optional robust kernel) against a cached :class:`~cm3d.ops.neighbors.TargetIndex` (:func:`icp`), or
trimmed point-to-point Sim(3) ICP with a fixed number of iterations against a cloud in the sorted
grid layout (:func:`icp_grid`, the memory's verification: no index to build per map).

Correspondences come from the warm-started graph walk (:func:`cm3d.ops.neighbors.walk`): each
source point is seeded once from the coarse grid, walked to a local minimum, then moved by one
walk step per iteration (~16 candidates instead of a grid or tree search). The walk can stop at a
local minimum of the k-NN graph, so once this *walk phase* has settled (``walk_tolerance`` x the
thresholds) an *exact phase* iterates with exact correspondences: matches the k-NN graph certifies
are kept, the others are searched on the fine / coarse grid
(:func:`cm3d.ops.neighbors.exact_nearest`, whose cache keeps the answers of points that barely
moved). It stops where exact ICP (Open3D's) stops, and the reported fitness, inlier count and
inlier RMSE are exact (what ``registration_icp`` reports). Before the full cloud, coarse stages run
the same ICP on every 16th and every 4th source point (``subsample``, ``levels``), so most
iterations cost a fraction of a full one.

One iteration (as Open3D's ``RegistrationICP``): estimate the update from the current
correspondences, apply it, re-match, and stop when fitness and inlier RMSE change by less than
``relative_fitness`` / ``relative_rmse`` (or after ``max_iterations``). Everything is jittable and
vmappable (a batch of pairs is ``jax.vmap`` of :func:`icp`, see :func:`icp_batch`); empty or tiny
clouds return the initial transform with fitness 0, never NaN.

Tangent order is jaxlie's ``(v, w)``; the update is applied on the left, ``T <- exp(xi) T``.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import jax
import jax.numpy as jnp
import jaxlie
from flax import struct
from jax import lax

from cm3d.ops.neighbors import (
    TargetIndex,
    build_target_index,
    exact_nearest,
    seed,
    walk,
    walk_to_convergence,
)
from cm3d.ops import sim3
from cm3d.ops.grid import grid_nearest
from cm3d.ops.voxel import valid_points
from cm3d.solvers.umeyama import umeyama_transform

__all__ = ["ICPOptions", "ICPResult", "TargetIndex", "build_target_index", "icp", "icp_batch",
           "icp_coarse_to_fine", "icp_grid", "point_to_plane_update", "stack_indices"]

_METHODS = ("point_to_point", "point_to_plane")
_KERNELS = ("none", "huber", "cauchy", "tukey")
_MIN_SUBSAMPLE = 256  # fewest points of a subsampled coarse stage


@dataclasses.dataclass(frozen=True)
class ICPOptions:
    """Static ICP options (hashable: one compilation per distinct value).

    method: "point_to_plane" (needs target normals, from the index) or "point_to_point".
    max_correspondence_distance: metres, <= the index radius. with_scale: Sim(3) (point-to-point:
    Umeyama; point-to-plane: a 7-parameter Gauss-Newton step, scale about the inlier centroid).
    kernel / kernel_scale: robust IRLS weight of point-to-plane residuals (metres).
    relative_fitness / relative_rmse: convergence thresholds (Open3D's ICPConvergenceCriteria).
    seed_steps: walk steps allowed to settle the seeds; walk_steps: walk steps per iteration;
    exact_iterations: at most this many final iterations with exact correspondences once the walk
    phase has converged to ``walk_tolerance`` x the relative thresholds (0: walk only, to the
    thresholds themselves; the reported statistics are exact either way). None (default): 0 for
    point-to-plane (its walk-only fixed point is Open3D's to ~2e-5 m: Gauss-Newton on the planes
    does not care which nearby point of the same plane is matched), 100 for point-to-point (whose
    exact fixed point differs from Open3D's stopping point, see docs/point_clouds.md).
    subsample / levels: coarse-to-fine over the source: up to ``levels - 1`` coarse stages on every
    ``subsample**l``-th source point (coarsest first, only while that leaves >= 256 points), each
    to ``walk_tolerance`` x the thresholds, before the full cloud (1 / levels=1: full cloud only).
    ``max_iterations`` bounds all stages and phases together (``iterations`` counts them all).
    """

    method: str = "point_to_plane"
    max_correspondence_distance: float = 0.1
    max_iterations: int = 30
    with_scale: bool = False
    kernel: str = "none"
    kernel_scale: float = 0.05
    relative_fitness: float = 1e-6
    relative_rmse: float = 1e-6
    seed_steps: int = 16
    walk_steps: int = 1
    exact_iterations: int | None = None
    walk_tolerance: float = 10.0
    subsample: int = 4
    levels: int = 3

    def __post_init__(self):
        if self.method not in _METHODS:
            raise ValueError(f"method must be one of {_METHODS}, got {self.method!r}")
        if self.kernel not in _KERNELS:
            raise ValueError(f"kernel must be one of {_KERNELS}, got {self.kernel!r}")
        if not self.max_correspondence_distance > 0:
            raise ValueError("max_correspondence_distance must be > 0")


@struct.dataclass
class ICPResult:
    """transform (4, 4) source -> target (``[s R, t]`` with scale); scale (); fitness () inliers /
    valid source points; inlier_count (); inlier_rmse () metres (0 without inliers); iterations ();
    converged () bool; exact_searches () grid searches of source points in the exact phase (all its
    iterations together; matches certified by the graph or the cache need none); :func:`icp_grid`
    also returns ``matches`` (N,) the nearest target point of each source point and ``inliers`` (N,)
    at the final transform (None from :func:`icp`)."""

    transform: jnp.ndarray
    scale: jnp.ndarray
    fitness: jnp.ndarray
    inlier_count: jnp.ndarray
    inlier_rmse: jnp.ndarray
    iterations: jnp.ndarray
    converged: jnp.ndarray
    exact_searches: jnp.ndarray
    matches: jnp.ndarray | None = None
    inliers: jnp.ndarray | None = None


def _apply(T, p):
    """T (4, 4) applied to points p (N, 3), as broadcast multiply-adds (XLA CPU runs an (N, 3) x
    (3, 3) matmul ~10x slower)."""
    return p[:, 0:1] * T[:3, 0] + p[:, 1:2] * T[:3, 1] + p[:, 2:3] * T[:3, 2] + T[:3, 3]


def _stats(d2, inl, nvalid):
    cnt = jnp.sum(inl)
    fit = cnt / jnp.maximum(nvalid, 1)
    rmse = jnp.sqrt(jnp.sum(jnp.where(inl, d2, 0.0)) / jnp.maximum(cnt, 1))
    return fit.astype(d2.dtype), rmse, cnt


def _kernel_weight(r, o: ICPOptions):
    k = jnp.asarray(o.kernel_scale, r.dtype)
    a = jnp.abs(r)
    if o.kernel == "huber":
        return jnp.where(a <= k, 1.0, k / jnp.maximum(a, 1e-30))
    if o.kernel == "cauchy":
        return 1.0 / (1.0 + (r / k) ** 2)
    if o.kernel == "tukey":
        return jnp.where(a < k, (1.0 - (r / k) ** 2) ** 2, 0.0)
    return jnp.ones_like(r)


def point_to_plane_update(q, p, n, inl, o: ICPOptions):
    """Gauss-Newton step (4, 4) minimising sum w (n . (exp(xi) q - p))^2 over the correspondences
    q (N, 3) -> p (N, 3) with target normals n (N, 3) where ``inl`` (N,) (``o``: kernel, with_scale).

    With scale (Sim(3)): ``q' = e^sigma R (q - c) + c + t`` about the inlier centroid ``c`` (which
    decouples scale from translation), Jacobian columns ``(n, (q - c) x n, n . (q - c))``.
    """
    r = jnp.sum(n * (q - p), -1)
    w = jnp.where(inl, _kernel_weight(r, o), 0.0)
    if o.with_scale:
        c = jnp.sum(q * w[:, None], 0) / jnp.maximum(jnp.sum(w), 1e-12)
        qc = q - c
        J = jnp.concatenate([n, jnp.cross(qc, n), jnp.sum(n * qc, -1, keepdims=True)], axis=-1)
    else:
        J = jnp.concatenate([n, jnp.cross(q, n)], axis=-1)  # d r / d(v, w)
    d = J.shape[1]
    H = (J * w[:, None]).T @ J
    g = (J * w[:, None]).T @ r
    lam = 1e-9 * (jnp.trace(H) + 1e-12)
    xi = -jnp.linalg.solve(H + lam * jnp.eye(d, dtype=H.dtype), g)
    ok = (jnp.sum(inl) >= d) & jnp.all(jnp.isfinite(xi))
    xi = jnp.where(ok, xi, 0.0)
    U = jaxlie.SE3.exp(xi[:6]).as_matrix().astype(q.dtype)
    if o.with_scale:
        A = jnp.exp(xi[6]) * U[:3, :3]
        U = U.at[:3, :3].set(A).at[:3, 3].set(U[:3, 3] + c - A @ c)
    return U


def _update_point_to_point(q, p, inl, o: ICPOptions):
    """Umeyama update (4, 4) of the current correspondences (Open3D's point-to-point estimate)."""
    U = umeyama_transform(q, p, inl, o.with_scale)
    ok = (jnp.sum(inl) >= 3) & jnp.all(jnp.isfinite(U))
    return jnp.where(ok, U, jnp.eye(4, dtype=q.dtype))


def icp(source, index: TargetIndex, init=None, valid=None, options: ICPOptions = ICPOptions()) -> ICPResult:
    """Register source points (N, 3) (valid: optional (N,) mask) to the indexed target.

    init: (4, 4) initial source -> target transform (default identity). Returns :class:`ICPResult`.
    Deterministic; jit with ``options`` static (``jax.jit(icp, static_argnames="options")``).
    """
    o = options
    if o.exact_iterations is None:
        o = dataclasses.replace(o, exact_iterations=0 if o.method == "point_to_plane" else 100)
    if o.max_correspondence_distance > index.radius * (1 + 1e-6):
        raise ValueError(f"max_correspondence_distance {o.max_correspondence_distance} exceeds the index radius "
                         f"{index.radius}; build the index with radius >= it")
    src = jnp.asarray(source, index.points.dtype)
    dtype = src.dtype
    T0 = jnp.eye(4, dtype=dtype) if init is None else jnp.asarray(init, dtype)
    sv = valid_points(src, valid)
    nvalid = jnp.sum(sv)
    src = jnp.where(sv[:, None], src, 0.0)
    r = jnp.asarray(o.max_correspondence_distance, dtype)
    r2 = r * r
    if src.shape[0] == 0 or index.points.shape[0] == 0:
        z = jnp.zeros((), dtype)
        return ICPResult(transform=T0, scale=jnp.ones((), dtype), fitness=z, inlier_count=jnp.int32(0),
                         inlier_rmse=z, iterations=jnp.int32(0), converged=jnp.bool_(True),
                         exact_searches=jnp.int32(0))

    def update(T, q, m, inl):
        """The next transform from the correspondences of q = T src (N, 3) to the matches m."""
        mc = jnp.clip(m, 0)
        p = index.points[mc]
        if o.method == "point_to_plane":
            return point_to_plane_update(q, p, index.normals[mc], inl, o)
        return _update_point_to_point(q, p, inl, o)

    def walk_phase(src, sv, T0, tol, max_it):
        """Seed, walk to a local minimum, then iterate (update, walk) until fitness and RMSE change
        by less than ``tol`` x the thresholds (or ``max_it`` iterations)."""
        nv = jnp.sum(sv)
        q = _apply(T0, src)
        m, d2, moved = walk_to_convergence(index, q, seed(index, q, sv), o.seed_steps, return_moved=True)
        fit, rmse, _ = _stats(d2, sv & (m >= 0) & (d2 <= r2), nv)

        def cond(c):
            return (c[7] < max_it) & ~c[8]

        def body(c):
            T, q, m, d2, moved, fit, rmse, it, _ = c
            T = update(T, q, m, sv & (m >= 0) & (d2 <= r2)) @ T
            q = _apply(T, src)
            for _ in range(o.walk_steps):
                m, d2, moved = walk(index, q, m)
            fit2, rmse2, _ = _stats(d2, sv & (m >= 0) & (d2 <= r2), nv)
            done = (jnp.abs(fit2 - fit) < o.relative_fitness * tol) & (jnp.abs(rmse2 - rmse) < o.relative_rmse * tol)
            return T, q, m, d2, moved, fit2, rmse2, it + 1, done

        return lax.while_loop(cond, body, (T0, q, m, d2, moved, fit, rmse, jnp.int32(0), jnp.bool_(False)))

    # Coarse stages: the same ICP on every s^l-th source point, coarsest first, each to
    # walk_tolerance x the thresholds with at most half the iterations left, brings T close at a
    # fraction of the cost.
    it0 = jnp.int32(0)
    strides = []
    if o.subsample > 1:
        while src.shape[0] // (o.subsample ** (len(strides) + 1)) >= _MIN_SUBSAMPLE and len(strides) < o.levels - 1:
            strides.append(o.subsample ** (len(strides) + 1))
    for st in reversed(strides):
        T0, *_, it_l, _ = walk_phase(src[::st], sv[::st], T0, o.walk_tolerance, (o.max_iterations - it0) // 2)
        it0 = it0 + it_l
    tol = o.walk_tolerance if o.exact_iterations else 1.0
    T, q, m, d2, moved, fit, rmse, it, done = walk_phase(src, sv, T0, tol, o.max_iterations - it0)
    it = it + it0

    # Exact phase: the walk may stop at a local minimum of the k-NN graph, so the last iterations
    # use exact correspondences (certified walk matches, grid search for the rest) to reach the
    # fixed point of exact ICP (Open3D's).
    def exact_match(q, m, d2, moved, cache):
        # certificates need m's own list scanned: matches the last walk step moved are searched
        pos, dd2, searched, cache = exact_nearest(index, q, m, d2, sv, r, cache, settled=~moved)
        return jnp.where(pos >= 0, pos, m), jnp.where(pos >= 0, dd2, d2), pos, dd2, searched, cache

    # the walk phase's last step ran at T: its matches and their moved flags are current
    m, d2, pos, dd2, searched, cache = exact_match(q, m, d2, moved, None)
    if o.exact_iterations == 0:  # walk only: the exact statistics at the final transform
        inl = sv & (pos >= 0)
        fit, rmse, cnt = _stats(jnp.where(inl, dd2, 0.0), inl, nvalid)
        return ICPResult(transform=T, scale=sim3.scale(T), fitness=fit,
                         inlier_count=cnt.astype(jnp.int32), inlier_rmse=rmse, iterations=it, converged=done,
                         exact_searches=searched)
    inl = sv & (pos >= 0)
    fit, rmse, _ = _stats(jnp.where(inl, dd2, 0.0), inl, nvalid)

    def cond_x(c):
        return (c[-3] < o.exact_iterations) & ~c[-2] & (c[-1] < o.max_iterations)

    def body_x(c):
        T, q, m, d2, pos, dd2, fit, rmse, searched, cache, k, _, it = c
        T = update(T, q, pos, sv & (pos >= 0)) @ T
        q = _apply(T, src)
        m, d2, moved = walk(index, q, m)
        m, d2, pos, dd2, s2, cache = exact_match(q, m, d2, moved, cache)
        inl = sv & (pos >= 0)
        fit2, rmse2, _ = _stats(jnp.where(inl, dd2, 0.0), inl, nvalid)
        done = (jnp.abs(fit2 - fit) < o.relative_fitness) & (jnp.abs(rmse2 - rmse) < o.relative_rmse)
        return T, q, m, d2, pos, dd2, fit2, rmse2, searched + s2, cache, k + 1, done, it + 1

    init_x = (T, q, m, d2, pos, dd2, fit, rmse, searched, cache, jnp.int32(0), jnp.bool_(False), it)
    T, q, m, d2, pos, dd2, fit, rmse, searched, _, k, done_x, it = lax.while_loop(cond_x, body_x, init_x)
    inl = sv & (pos >= 0)
    fit, rmse, cnt = _stats(jnp.where(inl, dd2, 0.0), inl, nvalid)
    scale = sim3.scale(T)
    return ICPResult(transform=T, scale=scale, fitness=fit, inlier_count=cnt.astype(jnp.int32), inlier_rmse=rmse,
                     iterations=it, converged=done & ((o.exact_iterations == 0) | done_x), exact_searches=searched)


def stack_indices(indices: Sequence[TargetIndex]) -> TargetIndex:
    """Stack indices of equal capacity (and equal radius / k) into one batched pytree for vmap."""
    return jax.tree.map(lambda *x: jnp.stack(x), *indices)


def icp_batch(sources, indices: TargetIndex, inits=None, valid=None, options: ICPOptions = ICPOptions()):
    """:func:`icp` vmapped over a batch of pairs: sources (B, N, 3), stacked indices
    (:func:`stack_indices`), inits (B, 4, 4) or None, valid (B, N) or None -> batched ICPResult."""
    B = sources.shape[0]
    inits = jnp.broadcast_to(jnp.eye(4, dtype=sources.dtype), (B, 4, 4)) if inits is None else inits
    valid = jnp.ones(sources.shape[:2], bool) if valid is None else valid
    return jax.vmap(lambda s, i, t, v: icp(s, i, t, v, options))(sources, indices, inits, valid)


def icp_coarse_to_fine(levels, index: TargetIndex, init=None, options: Sequence[ICPOptions] = (),
                       icp_fn=icp) -> ICPResult:
    """ICP over a source pyramid, coarsest first: ``levels`` is a sequence of (points, valid)
    (e.g. from :func:`cm3d.ops.voxel.voxel_pyramid`, reversed), one :class:`ICPOptions` per level
    (typically a shrinking max_correspondence_distance). Each level starts from the previous result;
    returns the last level's result. icp_fn: the per-level solver with :func:`icp`'s signature (e.g.
    ``jax.jit(icp, static_argnames="options")`` to reuse its compilations)."""
    if len(levels) != len(options):
        raise ValueError("one ICPOptions per pyramid level")
    T = init
    res = None
    for (pts, val), o in zip(levels, options):
        res = icp_fn(pts, index, T, val, options=o)
        T = res.transform
    return res


def icp_grid(source, valid, target, target_valid, init, *, distance, iterations: int, cell, per_cell: int = 2,
             reach: int = 1, with_scale: bool = True) -> ICPResult:
    """Trimmed point-to-point ICP of ``source`` (n, 3) (``valid`` (n,)) to ``target`` (P, 3) in the
    layout of :func:`cm3d.ops.grid.sort_by_cell` at ``cell``: ``iterations`` steps, each matching every
    source point to its :func:`~cm3d.ops.grid.grid_nearest` target point and refitting the whole
    transform by Umeyama (Sim(3) with ``with_scale``) on the pairs closer than ``distance``; a step with
    fewer than 3 pairs or a non-finite fit keeps the transform. Returns :class:`ICPResult` at the final
    transform, with ``matches`` and ``inliers``.
    """
    src, dst = jnp.asarray(source, jnp.float32), jnp.asarray(target, jnp.float32)
    sv, dv = jnp.asarray(valid, bool), jnp.asarray(target_valid, bool)

    def nearest(T):
        j, d2 = grid_nearest(src @ T[:3, :3].T + T[:3, 3], dst, dv, cell, reach, per_cell)
        return j, d2, sv & (d2 < distance**2)

    def step(T, _):
        j, _, inl = nearest(T)
        T2 = umeyama_transform(src, dst[j], inl, with_scale=with_scale)
        return jnp.where((jnp.sum(inl) >= 3) & jnp.all(jnp.isfinite(T2)), T2, T), None

    T, _ = lax.scan(step, jnp.asarray(init, jnp.float32), None, length=iterations)
    j, d2, inl = nearest(T)
    fit, rmse, count = _stats(d2, inl, jnp.sum(sv))
    return ICPResult(transform=T, scale=sim3.scale(T), fitness=fit, inlier_count=count.astype(jnp.int32),
                     inlier_rmse=rmse, iterations=jnp.int32(iterations), converged=jnp.bool_(True),
                     exact_searches=jnp.int32(0), matches=j, inliers=inl)
