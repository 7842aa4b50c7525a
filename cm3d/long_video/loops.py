"""Loop closures measured in the images of a stitched video, and the frame-level pose graph they close.

A chunked video's overlaps carry each chunk's end orientation into the next, so the chunks' small
errors add up along the video. Where the camera returns to a place it saw many frames earlier, the
two frames' images measure their relative pose directly (host side, OpenCV; entry point
:func:`close_loops`):

* :func:`loop_candidates`: frame pairs at least ``min_gap`` frames apart whose current poses look at
  the same place (centres within ``max_distance`` x the median depth, optical axes within
  ``max_angle_deg``), at most one per later frame, spread over the video;
* :func:`measure_loops`: SIFT matches of each pair, both ways: each frame's keypoints lifted with its
  depth and posed in the other's image by PnP + RANSAC (``cv2.solvePnPRansac``, then LM on the
  inliers); a loop is accepted when both pass an a-contrario test (:func:`pnp_log_nfa`: the inliers
  against the count the same pose gets with the matches' image ends shuffled), and is their midpoint;
* :func:`solve_loops`: one SE(3) pose per frame, the stitched trajectory's consecutive motions
  (noise from the chunks' disagreement on their shared frames, :func:`motion_noise`) and the loops as
  between factors, solved by :func:`cm3d.solvers.lm.solve`; the loops' noise estimated, inconsistent
  loops dropped (a χ² test).

:func:`close_loops` keeps the result only when loops held out of the solve agree with it better than
with the stitched trajectory (evidence the solution did not see) and the motions are bent within their
noise.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np
from scipy.special import gammainc

from cm3d.data.sequence import Sequence
from cm3d.ops import keypoints, robust
from cm3d.solvers import factors, lm

PNP_SAMPLE = 4  # points a PnP hypothesis is fitted to (inliers by construction, not evidence)
SHUFFLES = 8  # cyclic shifts of the image ends (as the memory's chance test)


@dataclasses.dataclass(frozen=True)
class LoopConfig:
    """Options of :func:`close_loops`.

    enabled: look for loops at all; max_frames: longer videos are left alone (the graph is solved dense,
    its cost grows with the cube of the frames); min_gap: frames between a loop's two frames (nearer
    frames are tied by the chunks themselves); max_distance: camera centres within this many times the
    median depth; max_angle_deg: optical axes within; max_pairs: candidates measured (spread over the
    video); keypoints: detection and ratio test; reproj_px: PnP inlier threshold at the images'
    resolution; ransac_iterations: PnP RANSAC hypotheses; max_log_nfa: accept a loop when log10 of its
    expected false alarms is below; min_inliers: PnP inliers at least; outlier_quantile: drop loops whose
    whitened residual exceeds ``χ²_6(q)``; holdout: every ``holdout``-th accepted loop is held out of the
    check solve; vce_iterations: rounds of the loops' noise estimate at most; iterations: LM steps.
    """

    enabled: bool = True
    max_frames: int = 1000
    min_gap: int = 60
    max_distance: float = 0.5
    max_angle_deg: float = 30.0
    max_pairs: int = 200
    keypoints: keypoints.KeypointConfig = keypoints.KeypointConfig(max_matches=1000, contrast_threshold=0.01)
    reproj_px: float = 2.0
    ransac_iterations: int = 1000
    max_log_nfa: float = -2.0
    min_inliers: int = 12
    outlier_quantile: float = 0.999
    holdout: int = 4
    vce_iterations: int = 10
    iterations: int = 30

    def __post_init__(self):
        if (self.min_gap < 2 or self.max_frames < 2 or self.max_pairs < 1 or self.ransac_iterations < 1
                or self.min_inliers < PNP_SAMPLE):
            raise ValueError(f"LoopConfig: min_gap >= 2, max_frames >= 2, max_pairs >= 1, ransac_iterations >= 1 "
                             f"and min_inliers >= {PNP_SAMPLE} required, got {self}")
        if not (self.max_distance > 0 and 0 < self.max_angle_deg <= 180 and self.reproj_px > 0
                and 0 < self.outlier_quantile < 1 and self.holdout >= 2 and self.iterations >= 1
                and self.vce_iterations >= 0):
            raise ValueError("LoopConfig: max_distance, reproj_px > 0, max_angle_deg in (0, 180], outlier_quantile "
                             f"in (0, 1), holdout >= 2, iterations >= 1, vce_iterations >= 0 required, got {self}")


def loop_candidates(poses, median_depth: float, cfg: LoopConfig = LoopConfig()) -> np.ndarray:
    """Frame pairs ``(i, j)`` (E, 2), ``j - i >= cfg.min_gap``, whose ``poses`` (S, 4, 4) cam_to_world look at
    the same place: for each later frame j the nearest earlier frame i (centre distance over
    ``max_distance`` x ``median_depth`` plus axis angle over ``max_angle_deg``, both at most 1), then at most
    ``max_pairs`` of these, evenly spread over j."""
    P = np.asarray(poses, np.float64)
    S = P.shape[0]
    C, Z = P[:, :3, 3], P[:, :3, 2]
    dist = np.linalg.norm(C[:, None] - C[None], axis=-1) / (cfg.max_distance * median_depth)
    ang = np.degrees(np.arccos(np.clip(Z @ Z.T, -1.0, 1.0))) / cfg.max_angle_deg
    i, j = np.meshgrid(np.arange(S), np.arange(S), indexing="ij")
    ok = (j - i >= cfg.min_gap) & (dist <= 1.0) & (ang <= 1.0)
    score = np.where(ok, dist + ang, np.inf)
    best = np.argmin(score, axis=0)  # per later frame j
    js = np.flatnonzero(np.isfinite(score[best, np.arange(S)]))
    if len(js) > cfg.max_pairs:
        js = js[np.round(np.linspace(0, len(js) - 1, cfg.max_pairs)).astype(np.int64)]
    return np.stack([best[js], js], 1).astype(np.int64) if len(js) else np.zeros((0, 2), np.int64)


def pnp_log_nfa(X, uv, K, T, reproj_px: float, tests: int) -> tuple[int, float, float]:
    """The a-contrario test of a PnP pose ``T`` (4, 4; camera of ``X`` -> camera of ``uv``) on the matches
    ``X`` (N, 3) <-> ``uv`` (N, 2): (inliers k within ``reproj_px``, chance inliers λ, log10 NFA).

    λ: the same pose's inliers with the image ends cyclically shifted (``SHUFFLES`` shifts, their mean,
    plus half an inlier so that a clean background is not taken for an impossible one): what chance
    gives at this match count and keypoint layout. ``NFA = tests · P(Poisson(λ) >= k - 4)`` (4: PnP's
    sample, inliers of any hypothesis). NFA < 1: fewer than one pose this good expected by chance."""
    X, uv = np.asarray(X, np.float64), np.asarray(uv, np.float64)
    n = len(X)
    Y = X @ T[:3, :3].T + T[:3, 3]
    front = Y[:, 2] > 1e-9
    proj = (Y @ np.asarray(K, np.float64).T)[:, :2] / np.where(front, Y[:, 2], 1.0)[:, None]
    hit = lambda q: front & (np.sum((proj - q) ** 2, 1) < reproj_px ** 2)  # noqa: E731
    k = int(np.sum(hit(uv)))
    if n < 2:
        return k, 0.5, float(np.log10(tests))
    shifts = [1 + (s * (n - 1)) // SHUFFLES for s in range(SHUFFLES)]
    lam = (sum(int(np.sum(hit(np.roll(uv, o, 0)))) for o in shifts) + 0.5) / SHUFFLES
    excess = k - PNP_SAMPLE
    tail = float(gammainc(excess, lam)) if excess > 0 else 1.0  # P(Poisson(λ) >= excess)
    return k, lam, float(np.log10(tests) + np.log10(max(tail, 1e-300)))


def _lift(uv, depth, K):
    """Pixels ``uv`` (N, 2) lifted with ``depth`` (H, W) at their nearest pixel: (X (N, 3), ok (N,))."""
    H, W = depth.shape
    ui = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, W - 1)
    vi = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, H - 1)
    z = np.asarray(depth, np.float64)[vi, ui]
    ok = np.isfinite(z) & (z > 0)
    z = np.where(ok, z, 0.0)
    K = np.asarray(K, np.float64)
    return np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0] * z, (uv[:, 1] - K[1, 2]) / K[1, 1] * z, z], 1), ok


def _pnp(X, uv, K, cfg: LoopConfig, tests: int):
    """PnP + RANSAC of 3D points ``X`` (camera a) onto pixels ``uv`` (camera b), LM on the inliers:
    (T (4, 4) camera a -> camera b or None, inliers, chance inliers, log10 NFA)."""
    import cv2

    if len(X) < cfg.min_inliers:
        return None, 0, 0.0, float(np.log10(tests))
    found, rv, tv, inl = cv2.solvePnPRansac(X, uv, K, None, reprojectionError=cfg.reproj_px,
                                            iterationsCount=cfg.ransac_iterations, flags=cv2.SOLVEPNP_EPNP)
    if not found or inl is None or len(inl) < PNP_SAMPLE:
        return None, 0, 0.0, float(np.log10(tests))
    rv, tv = cv2.solvePnPRefineLM(X[inl[:, 0]], uv[inl[:, 0]], K, None, rv, tv)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = cv2.Rodrigues(rv)[0], tv.ravel()
    if not np.all(np.isfinite(T)):
        return None, 0, 0.0, float(np.log10(tests))
    return (T, *pnp_log_nfa(X, uv, K, T, cfg.reproj_px, tests))


def measure_loops(seq: Sequence, pairs, static=None, cfg: LoopConfig = LoopConfig()):
    """Relative poses of frame pairs ``(i, j)`` measured in their images (host, OpenCV), both ways: j's
    matched keypoints lifted with j's depth and posed in i's image by PnP, and i's lifted and posed in
    j's. A pair is accepted when both poses pass the chance test (:func:`pnp_log_nfa`, at least
    ``cfg.min_inliers`` inliers); its relative pose is their midpoint on SE(3) (each direction's error is
    its own depth's and keypoints').

    Returns (accepted (E,) bool, T (E, 4, 4) ``T_i^{-1} T_j`` in the sequence's units (its depth), facts
    per pair: dict of arrays ``inliers``, ``matches``, ``chance``, ``log_nfa`` (the weaker direction's),
    ``disagreement_deg`` (the two directions' rotation difference))."""
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    E = len(pairs)
    det = {}
    tests = max(E, 1) * cfg.ransac_iterations * 2
    out_T = np.tile(np.eye(4), (E, 1, 1))
    acc = np.zeros(E, bool)
    facts = {k: np.zeros(E) for k in ("inliers", "matches", "chance", "log_nfa", "disagreement_deg")}
    facts["log_nfa"][:] = np.log10(tests)
    facts["disagreement_deg"][:] = np.nan
    for e, (i, j) in enumerate(pairs):
        for f in (i, j):
            if f not in det:
                m = None if static is None else np.asarray(static[f], bool)
                det[f] = keypoints.detect(seq.images[f], cfg.keypoints, m)
        mt = keypoints.match_detections(det[i], det[j], cfg.keypoints)
        uv_i, uv_j = mt.uv0[mt.valid].astype(np.float64), mt.uv1[mt.valid].astype(np.float64)
        Xj, ok_j = _lift(uv_j, seq.depth[j], seq.intrinsic[j])
        Xi, ok_i = _lift(uv_i, seq.depth[i], seq.intrinsic[i])
        fwd = _pnp(Xj[ok_j], uv_i[ok_j], np.asarray(seq.intrinsic[i], np.float64), cfg, tests)  # cam j -> cam i
        bwd = _pnp(Xi[ok_i], uv_j[ok_i], np.asarray(seq.intrinsic[j], np.float64), cfg, tests)  # cam i -> cam j
        facts["matches"][e] = min(ok_i.sum(), ok_j.sum())
        weak = max((fwd, bwd), key=lambda r: r[3])
        facts["inliers"][e], facts["chance"][e], facts["log_nfa"][e] = weak[1], weak[2], weak[3]
        if fwd[0] is None or bwd[0] is None:
            continue
        d = se3_log(np.linalg.inv(fwd[0]) @ np.linalg.inv(bwd[0]))
        facts["disagreement_deg"][e] = float(np.degrees(np.linalg.norm(d[3:])))
        out_T[e] = fwd[0] @ _se3_exp(0.5 * d)
        acc[e] = weak[1] >= cfg.min_inliers and weak[3] < cfg.max_log_nfa
    return acc, out_T, facts


def motion_noise(chunk_poses, ranges) -> np.ndarray:
    """(6,) per-axis noise (translation first) of one consecutive relative motion of a stitched video, from
    the chunks' disagreement on their shared frames: two chunks' relative motions of the same consecutive
    pair differ by sqrt(2) x it (a robust RMS: 1.4826 x the median absolute difference). chunk_poses: each
    chunk's placed poses (S_k, 4, 4); ranges: their global [start, stop)."""
    d = []
    for k in range(1, len(ranges)):
        a0, b0 = ranges[k - 1]
        a1, _ = ranges[k]
        for f in range(a1, b0 - 1):
            Pa, Pb = chunk_poses[k - 1], chunk_poses[k]
            ra = np.linalg.inv(Pa[f - a0]) @ Pa[f + 1 - a0]
            rb = np.linalg.inv(Pb[f - a1]) @ Pb[f + 1 - a1]
            d.append(np.linalg.inv(ra) @ rb)
    if not d:
        return np.full(6, np.nan)
    d = se3_log(np.stack(d))
    return robust.MAD_TO_SIGMA * np.median(np.abs(d), 0) / np.sqrt(2.0)


def _graph(P, ia, ib, meas, sig, w):
    """:func:`solve_loops`' graph (host arrays in, float32 leaves; built from NumPy so that no eager JAX
    operation compiles per size): between factors only, the first frame fixed (the gauge)."""
    N = P.shape[0]
    f = lambda a: jnp.asarray(np.asarray(a, np.float32))  # noqa: E731
    i32 = lambda a: jnp.asarray(np.asarray(a, np.int32))  # noqa: E731
    fixed = np.zeros(N, bool)
    fixed[0] = True
    return factors.FactorGraph(
        intrinsics=f(np.broadcast_to(np.eye(3), (N, 3, 3))),
        projection=factors.ProjectionFactors(pose_idx=i32([0]), point_idx=i32([0]), z=f(np.zeros((1, 2))),
                                             sigma=f([1.0]), weight=f([0.0]), memory=jnp.asarray(np.zeros(1, bool))),
        prior=factors.PriorFactors(pose_idx=i32([0]), target=f(P[:1]), sigma=f(np.ones((1, 6))), weight=f([0.0])),
        motion=factors.MotionFactors(idx_a=i32(ia), idx_b=i32(ib), measured=f(meas), sigma=f(sig), weight=f(w)),
        huber_k=f(np.inf), memory_alpha=f(0.5), pose_fixed=jnp.asarray(fixed))


@functools.partial(jax.jit, static_argnames="iterations")
def _solve(graph, poses, iterations: int):
    x0 = factors.Variables(poses, jnp.zeros((1, 3), poses.dtype))
    res = lm.solve(graph, x0, lm.LMOptions(backward="none", max_iterations=iterations, linear_solver="dense"))
    return res.params.poses


def se3_log(T) -> np.ndarray:
    """SE(3) logarithm on the host (NumPy float64), (..., 4, 4) -> (..., 6), translation first: the same map as
    :func:`cm3d.ops.se3.log` (jaxlie's order), without compiling a JAX program per shape."""
    from scipy.spatial.transform import Rotation

    T = np.asarray(T, np.float64)
    shape = T.shape[:-2]
    T = T.reshape(-1, 4, 4)
    w = Rotation.from_matrix(T[:, :3, :3]).as_rotvec()
    t = T[:, :3, 3]
    th2 = np.sum(w * w, -1, keepdims=True)
    th = np.sqrt(th2)
    small = th2 < 1e-4
    with np.errstate(divide="ignore", invalid="ignore"):
        closed = (1.0 - th * np.sin(th) / (2.0 * (1.0 - np.cos(th)))) / th2
    c = np.where(small, 1.0 / 12.0 + th2 / 720.0 + th2 * th2 / 30240.0, closed)
    wt = np.cross(w, t)
    return np.concatenate([t - 0.5 * wt + c * np.cross(w, wt), w], -1).reshape(shape + (6,))


def _se3_exp(xi) -> np.ndarray:
    """SE(3) exponential on the host (NumPy float64), (6,) translation first -> (4, 4): the inverse of
    :func:`se3_log`."""
    from scipy.spatial.transform import Rotation

    v, w = np.asarray(xi[:3], np.float64), np.asarray(xi[3:], np.float64)
    th2 = float(w @ w)
    th = np.sqrt(th2)
    if th2 < 1e-4:
        b, c = 0.5 - th2 / 24.0 + th2 * th2 / 720.0, 1.0 / 6.0 - th2 / 120.0 + th2 * th2 / 5040.0
    else:
        b, c = (1.0 - np.cos(th)) / th2, (th - np.sin(th)) / (th2 * th)
    wv = np.cross(w, v)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rotation.from_rotvec(w).as_matrix(), v + b * wv + c * np.cross(w, wv)
    return T


def _loop_residuals(P, pairs, T):
    """Whitening-free residuals (L, 6) of loops ``T`` (``T_i^{-1} T_j``) at poses ``P``: log(T^{-1} P_i^{-1} P_j)."""
    if len(pairs) == 0:
        return np.zeros((0, 6))
    rel = np.linalg.inv(P[pairs[:, 0]]) @ P[pairs[:, 1]]
    return se3_log(np.linalg.inv(T) @ rel)


def solve_loops(P, loops, T_loops, sigma_motion, sigma_loop, weight=None, iterations: int = 30,
                pad_to: int | None = None) -> np.ndarray:
    """One SE(3) pose per frame from the trajectory ``P`` (S, 4, 4)'s consecutive motions (noise
    ``sigma_motion`` (6,), translation first) and the loops ``(i, j)`` (L, 2) measuring ``T_i^{-1} T_j`` as
    ``T_loops`` (L, 4, 4), with noise ``sigma_loop`` (6,) (``weight`` (L,): 0 leaves a loop out); the first
    frame fixed (the gauge); ``iterations`` LM steps (:func:`cm3d.solvers.lm.solve`, dense).
    Factors are padded to ``pad_to`` slots, at least to a multiple of 64 (one compiled program for nearby
    sizes). Returns poses (S, 4, 4) float64."""
    P = np.asarray(P, np.float64)
    S = P.shape[0]
    loops = np.asarray(loops, np.int64).reshape(-1, 2)
    L = len(loops)
    Q = (S - 1) + L
    Qp = max(Q, pad_to or 0, -(-Q // 64) * 64)
    ia, ib = np.zeros(Qp, np.int64), np.zeros(Qp, np.int64)
    meas, sig, wt = np.tile(np.eye(4), (Qp, 1, 1)), np.ones((Qp, 6)), np.zeros(Qp)
    ia[:S - 1], ib[:S - 1], meas[:S - 1] = np.arange(S - 1), np.arange(1, S), np.linalg.inv(P[:-1]) @ P[1:]
    ia[S - 1:Q], ib[S - 1:Q], meas[S - 1:Q] = loops[:, 0], loops[:, 1], T_loops
    sig[:S - 1], sig[S - 1:Q] = sigma_motion, sigma_loop
    wt[:S - 1], wt[S - 1:Q] = 1.0, (np.ones(L) if weight is None else weight)
    graph = _graph(P, ia, ib, meas, sig, wt)
    return np.asarray(_solve(graph, jnp.asarray(P, jnp.float32), iterations=iterations), np.float64)


@jax.jit
def _jacobians(graph, poses):
    _, _, e, J_a, J_b = factors.pose_factor_jacobians(graph, poses)
    return e, J_a, J_b


def _loop_leverage(P, loops, T, sigma_motion, sigma_loop, weight):
    """Leverage ``h`` (L, 6) of each loop residual component in :func:`solve_loops`' graph linearised at
    ``P``: ``diag(J N^{-1} Jᵀ)`` of the whitened, weighted Jacobian (first frame fixed), host float64.
    ``1 - h`` is the share of a loop's noise left in its residual (its redundancy)."""
    from scipy.linalg import cho_factor, cho_solve

    S, L = P.shape[0], len(loops)
    ia = np.r_[np.arange(S - 1), loops[:, 0]]
    ib = np.r_[np.arange(1, S), loops[:, 1]]
    meas = np.concatenate([np.linalg.inv(P[:-1]) @ P[1:], T])
    sig = np.concatenate([np.broadcast_to(sigma_motion, (S - 1, 6)), np.broadcast_to(sigma_loop, (L, 6))])
    w = np.r_[np.ones(S - 1), weight]
    _, J_a, J_b = (np.asarray(x, np.float64) for x in _jacobians(_graph(P, ia, ib, meas, sig, w), jnp.asarray(P)))
    sw = np.sqrt(w)[:, None, None]
    J_a, J_b = J_a * sw, J_b * sw
    N = np.zeros((S, 6, S, 6))  # Σ Jᵀ J block by block: a factor touches its two frames only
    for (x, Jx), (y, Jy) in itertools.product(((ia, J_a), (ib, J_b)), repeat=2):
        np.add.at(N, (x, slice(None), y), np.einsum("kri,krj->kij", Jx, Jy))
    N = N.reshape(S * 6, S * 6)[6:, 6:] + 1e-9 * np.eye((S - 1) * 6)  # frame 0 fixed
    Jl = np.zeros((L, 6, S, 6))  # the loops' rows of J
    Jl[np.arange(L), :, ia[S - 1:]] += J_a[S - 1:]
    Jl[np.arange(L), :, ib[S - 1:]] += J_b[S - 1:]
    Jl = Jl.reshape(L * 6, S * 6)[:, 6:]
    h = np.sum(Jl * cho_solve(cho_factor(N), Jl.T).T, 1).reshape(L, 6)
    return np.clip(h, 0.0, 1.0)


def _vce_solve(P, loops, T, sigma_motion, weight, cfg: LoopConfig):
    """:func:`solve_loops` with the loops' noise estimated (robust variance components, per translation and
    rotation: the median of ``r² / (1 - h)`` (``h`` the leverage, :func:`_loop_leverage`) against χ²_1's
    median; started at the loops' misfit to ``P``) and loops beyond ``χ²_6(cfg.outlier_quantile)`` dropped,
    at most ``cfg.vce_iterations`` rounds (until the noise changes by < 5 % and no loop is dropped or let back).
    Returns (poses, weights (L,), sigma_loop (6,))."""
    w = np.asarray(weight, np.float64).copy()
    used = w > 0
    r0 = _loop_residuals(P, loops[used], T[used])
    sl = np.maximum(np.sqrt(np.mean(r0 ** 2, 0)), sigma_motion)
    limit = float(robust.chi2_quantile(cfg.outlier_quantile, 6))
    for it in range(cfg.vce_iterations + 1):
        sol = solve_loops(P, loops, T, sigma_motion, sl, w, cfg.iterations)
        if it == cfg.vce_iterations:
            break
        r = _loop_residuals(sol, loops, T)
        h = _loop_leverage(sol, loops, T, sigma_motion, sl, w)
        sl_old = sl
        sl = robust.variance_components(r / sl, h, w > 0, sl)
        w_old, w = w, np.where(np.sum((r / sl_old) ** 2, 1) > limit, 0.0, np.asarray(weight, np.float64))
        if np.all(np.abs(np.log(sl / sl_old)) < 0.05) and np.array_equal(w, w_old):
            break  # converged: the solve above is the estimate's
    return sol, w, sl


def close_loops(seq: Sequence, sigma_motion, static=None, cfg: LoopConfig = LoopConfig()):
    """Loop closures of a stitched ``seq`` (its poses, images, depth, intrinsics): candidates
    (:func:`loop_candidates`), measured (:func:`measure_loops`), solved (:func:`solve_loops`).

    The motions' noise is ``sigma_motion`` (6,), translation first; the loops' is estimated (robust variance
    components, :func:`_vce_solve`), loops beyond ``χ²_6(cfg.outlier_quantile)`` dropped. Two checks on
    evidence the solution did not see or cannot fake: every ``cfg.holdout``-th loop is held out of a first
    solve, and those loops must agree with it better than with the stitched poses (median whitened squared
    residual); and the final solution may bend the median motion by at most ``χ²_6(q)`` of its noise (loops
    that contradict the chunks and one another bend them all).
    Returns (poses (S, 4, 4): the solution when kept, else the input; facts dict)."""
    import time

    t0 = time.perf_counter()
    P = np.asarray(seq.cam_to_world, np.float64)
    facts = {"kept": False, "candidates": 0, "accepted": 0}
    if not cfg.enabled:
        return P, {**facts, "reason": "disabled"}
    if P.shape[0] > cfg.max_frames:
        return P, {**facts, "reason": f"{P.shape[0]} frames > max_frames ({cfg.max_frames}): the dense solve"}
    d = np.asarray(seq.depth, np.float64)
    med = float(np.median(d[d > 0])) if np.any(d > 0) else 1.0
    pairs = loop_candidates(P, med, cfg)
    facts["candidates"] = len(pairs)
    if len(pairs) == 0:
        return P, {**facts, "reason": "no candidate pairs", "seconds": time.perf_counter() - t0}
    acc, T, mf = measure_loops(seq, pairs, static, cfg)
    facts.update(accepted=int(acc.sum()), inliers_median=float(np.median(mf["inliers"][acc])) if acc.any() else 0.0,
                 measure_s=time.perf_counter() - t0)
    P, fit = fit_loops(P, pairs[acc], T[acc], sigma_motion, med, cfg)
    return P, {**facts, **fit, "seconds": time.perf_counter() - t0}


def fit_loops(P, loops, T, sigma_motion, scale: float, cfg: LoopConfig = LoopConfig()):
    """:func:`close_loops`' solve of measured ``loops`` (L, 2) / ``T`` (L, 4, 4) on the trajectory ``P``
    (S, 4, 4); ``scale``: the scene's median depth (the motions' noise floor is 1e-4 of it and 1e-4 rad).
    Returns (poses, the solution when kept, else ``P``; facts dict with ``kept``)."""
    P = np.asarray(P, np.float64)
    med = float(scale)
    facts = {"kept": False}
    L = len(loops)
    if L < 2 * cfg.holdout:
        return P, {**facts, "reason": f"{L} accepted loops (< {2 * cfg.holdout})"}
    sigma_motion = np.asarray(sigma_motion, np.float64)
    if sigma_motion.shape != (6,) or not np.all(np.isfinite(sigma_motion)):
        return P, {**facts, "reason": f"no motion noise (chunks sharing fewer than 2 frames): {sigma_motion}"}
    # a floor (1e-4 of the median depth, 1e-4 rad): chunks that agree exactly would weight a motion infinitely
    sigma_motion = np.maximum(sigma_motion, [1e-4 * med] * 3 + [1e-4] * 3)
    held = np.arange(L) % cfg.holdout == cfg.holdout - 1
    part, _, sl = _vce_solve(P, loops, T, sigma_motion, (~held).astype(float), cfg)
    white = lambda X: float(np.median(np.sum((_loop_residuals(X, loops[held], T[held]) / sl) ** 2, 1)))  # noqa: E731
    before, after = white(P), white(part)
    facts.update(holdout_before=before, holdout_after=after)
    if not after < before:
        return P, {**facts, "reason": "held-out loops agree better with the stitch"}
    sol, w, sl = _vce_solve(P, loops, T, sigma_motion, np.ones(L), cfg)
    # the loops may bend the chunks' motions only within their noise: most motions beyond χ²_6(q) means the
    # loops contradict the chunks (and one another), not that they correct a drift
    rel = np.linalg.inv(P[:-1]) @ P[1:]
    rm = _loop_residuals(sol, np.stack([np.arange(len(P) - 1), np.arange(1, len(P))], 1), rel)
    misfit = float(np.median(np.sum((rm / sigma_motion) ** 2, 1)))
    limit = float(robust.chi2_quantile(cfg.outlier_quantile, 6))
    facts.update(motion_misfit=misfit, motion_misfit_limit=limit)
    if not misfit <= limit:
        return P, {**facts, "reason": "the loops bend the chunks' motions beyond their noise"}
    ok = bool(np.all(np.isfinite(sol)))
    facts.update(kept=ok, loops_used=int(np.sum(w > 0)), loops_dropped=loops[w == 0].tolist(),
                 sigma_loop_trans=float(np.linalg.norm(sl[:3])),
                 sigma_loop_rot_deg=float(np.degrees(np.linalg.norm(sl[3:]))),
                 sigma_motion_trans=float(np.linalg.norm(sigma_motion[:3])),
                 sigma_motion_rot_deg=float(np.degrees(np.linalg.norm(sigma_motion[3:]))))
    return (sol if ok else P), facts
