"""Whole-trajectory refinement: one pose graph over every frame of a stitched video.

A prior per frame at its stitched pose and a motion factor per consecutive pair measured from the
images (:func:`measure_frame_pairs`: flow + depth -> robust Sim(3)). Noise levels come from robust
variance component estimation; the chain is block-tridiagonal
(:func:`cm3d.solvers.chain_pose_graph.solve_chain`). Entry point: :func:`refine_frames`.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from cm3d.data.sequence import Sequence
from cm3d.eval.metrics import ate
from cm3d.long_video.fuse import place_poses
from cm3d.long_video.layout import StitchError
from cm3d.ops import camera, robust, se3, sim3
from cm3d.ops import flow as oflow
from cm3d.solvers import factors
from cm3d.solvers.chain_pose_graph import solve_chain
from cm3d.solvers.sim3_irls import robust_sim3



@dataclasses.dataclass(frozen=True)
class FrameGraphConfig:
    """Options of :func:`refine_frames` (all static).

    grid_step: pixel stride of correspondence candidates; robust_iterations, robust_k: IRLS rounds and
    Cauchy scale of each pair's Sim(3) fit; min_inlier_fraction, min_points, max_residual: a pair's fit
    is dropped below these inliers / points or above ``max_residual`` x the median point distance;
    vce_iterations: variance-estimation rounds; outlier_quantile: drop motion factors above
    ``χ²_6(q)``; max_deviation: refuse a result that moves the trajectory more than this many times the
    centre noise; iterations: LM steps; pad_frames: pad the graph to a multiple (one compiled program).
    """

    grid_step: int = 2
    robust_iterations: int = 8
    robust_k: float = 2.0
    min_inlier_fraction: float = 0.5
    min_points: int = 50
    max_residual: float = 0.05
    vce_iterations: int = 3
    outlier_quantile: float = 0.999
    max_deviation: float = 2.0
    iterations: int = 10
    pad_frames: int = 64
    flow: oflow.FlowConfig = oflow.FlowConfig()

    def __post_init__(self):
        if (self.grid_step < 1 or self.robust_iterations < 0 or self.vce_iterations < 0 or self.min_points < 3
                or self.iterations < 1 or self.pad_frames < 1):
            raise ValueError("FrameGraphConfig: grid_step >= 1, robust_iterations >= 0, vce_iterations >= 0, "
                             f"min_points >= 3 and iterations >= 1 required, got {self}")
        if not (0 <= self.min_inlier_fraction <= 1 and 0 < self.outlier_quantile < 1 and self.max_deviation > 0
                and self.robust_k > 0 and self.max_residual > 0):
            raise ValueError("FrameGraphConfig: min_inlier_fraction in [0, 1], outlier_quantile in (0, 1), "
                             f"max_deviation, max_residual and robust_k > 0 required, got {self}")


class PairMeasurements(NamedTuple):
    """:func:`measure_frame_pairs`' result: M (E, 4, 4) Sim(3) cam j -> cam i; inlier_fraction (E,);
    points (E,) valid correspondences; residual (E,) robust residual sigma over the median depth."""

    M: np.ndarray
    inlier_fraction: np.ndarray
    points: np.ndarray
    residual: np.ndarray


def _pad(a, n: int, mode: str):
    """Pad the leading axis of ``a`` to ``n``: with zeros, or by repeating the last entry."""
    extra = n - a.shape[0]
    if extra <= 0:
        return a
    fill = np.zeros((extra,) + a.shape[1:], a.dtype) if mode == "zeros" else np.repeat(a[-1:], extra, 0)
    return np.concatenate([a, fill])


def frame_pair_points(seq: Sequence, i: int, j: int, flow, step: int = 2, static=None):
    """3D-3D correspondences between frames i and j (host, NumPy float64): every ``step``-th pixel of i
    lifted into camera i (dst) and its flow target lifted with j's depth into camera j (src).
    Returns (src (P, 3), dst (P, 3), ok (P,)); ``dst ≈ T src`` with ``T`` the Sim(3) cam j -> cam i."""
    H, W = seq.image_size
    v, u = np.mgrid[step // 2:H:step, step // 2:W:step]
    u, v = u.ravel(), v.ravel()
    u2, v2 = u + flow[v, u, 0].astype(np.float64), v + flow[v, u, 1].astype(np.float64)
    ui, vi = np.rint(u2).astype(np.int64), np.rint(v2).astype(np.int64)
    inside = (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
    ui, vi = np.clip(ui, 0, W - 1), np.clip(vi, 0, H - 1)
    di = np.asarray(seq.depth[i], np.float64)[v, u]
    dj = np.asarray(seq.depth[j], np.float64)[vi, ui]
    ok = inside & np.isfinite(di) & np.isfinite(dj) & (di > 0) & (dj > 0)
    if static is not None:
        ok &= np.asarray(static[i], bool)[v, u] & np.asarray(static[j], bool)[vi, ui]
    K = lambda f: np.asarray(seq.intrinsic[f], np.float64)  # noqa: E731
    dst = camera.backproject(np.stack([u, v], -1).astype(np.float64), np.where(ok, di, 0.0), K(i))
    src = camera.backproject(np.stack([u2, v2], -1), np.where(ok, dj, 0.0), K(j))
    return src, dst, ok


@functools.partial(jax.jit, static_argnames=("iterations", "k"))
def _fit_pairs(src, dst, ok, iterations: int, k: float):
    return jax.vmap(functools.partial(robust_sim3, iterations=iterations, k=k))(src, dst, ok)


def measure_frame_pairs(seq: Sequence, pairs, static=None, cfg: FrameGraphConfig = FrameGraphConfig(),
                        pad_to: int | None = None) -> PairMeasurements:
    """Relative Sim(3)s of frame pairs ``(i, j)`` (E, 2) from host optical flow and the depth maps: the
    measured ``T_i^{-1} T_j`` (scale: the depth ratio), by one jitted, vmapped
    :func:`cm3d.solvers.sim3_irls.robust_sim3` over pairs padded to ``pad_to``."""
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    if pairs.shape[0] == 0:
        return PairMeasurements(np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0, np.int64), np.zeros(0))
    src, dst, ok = [], [], []
    for i, j in pairs:
        F = oflow.compute_flow(seq.images[i], seq.images[j], cfg.flow)
        s, d, o = frame_pair_points(seq, int(i), int(j), F, cfg.grid_step, static)
        src.append(s), dst.append(d), ok.append(o)
    E = len(src)
    pad = lambda a: jnp.asarray(_pad(np.stack(a), max(E, pad_to or 0), "zeros"))  # noqa: E731
    fit = _fit_pairs(pad(src), pad(dst), pad(ok), iterations=cfg.robust_iterations, k=cfg.robust_k)
    return PairMeasurements(np.asarray(fit.transform, np.float64)[:E], np.asarray(fit.inlier_fraction, np.float64)[:E],
                            np.asarray(fit.num_valid, np.int64)[:E], np.asarray(fit.rel_sigma, np.float64)[:E])


def frame_graph(poses, idx_a, idx_b, measured, sigma_motion, sigma_prior, weight=None) -> factors.FactorGraph:
    """The whole-trajectory pose graph as a :class:`~cm3d.solvers.factors.FactorGraph`: a prior per frame
    at ``poses`` (N, 4, 4), a motion factor per measured consecutive pair (Q, 4, 4); sigmas (., 6) or
    (6,), translation first; weight (Q,) (0 = dropped); no landmarks. Arrays take ``poses``' dtype."""
    poses = jnp.asarray(poses)
    f = lambda a: jnp.asarray(a, poses.dtype)  # noqa: E731
    N, Q = poses.shape[0], int(np.shape(idx_a)[0])
    wt = np.ones(Q) if weight is None else np.asarray(weight)
    if np.any((np.asarray(idx_b) != np.asarray(idx_a) + 1) & (wt > 0)):
        raise StitchError("frame_graph: motion factors must join consecutive frames (idx_b = idx_a + 1)")
    return factors.FactorGraph(
        intrinsics=jnp.tile(jnp.eye(3, dtype=poses.dtype), (N, 1, 1)),
        projection=factors.ProjectionFactors(pose_idx=jnp.zeros(1, jnp.int32), point_idx=jnp.zeros(1, jnp.int32),
                                             z=jnp.zeros((1, 2), poses.dtype), sigma=jnp.ones(1, poses.dtype),
                                             weight=jnp.zeros(1, poses.dtype), memory=jnp.zeros(1, bool)),
        prior=factors.PriorFactors(pose_idx=jnp.arange(N, dtype=jnp.int32), target=poses,
                                   sigma=jnp.broadcast_to(f(sigma_prior), (N, 6)), weight=jnp.ones(N, poses.dtype)),
        motion=factors.MotionFactors(idx_a=jnp.asarray(idx_a, jnp.int32), idx_b=jnp.asarray(idx_b, jnp.int32),
                                     measured=f(measured), sigma=jnp.broadcast_to(f(sigma_motion), (Q, 6)),
                                     weight=f(wt)),
        huber_k=jnp.asarray(np.inf, poses.dtype), memory_alpha=jnp.asarray(0.5, poses.dtype),
        pose_fixed=jnp.zeros(N, bool))


def rotation_noise(chunks, overlaps, G) -> float:
    """Per-axis rotation noise (rad) of a frame's prior, from the shared frames: two chunks' placed
    rotations of a frame differ by sqrt(2) x the per-frame noise."""
    d = []
    for k in range(1, len(chunks)):
        o = overlaps[k - 1]
        pa = place_poses(G[k - 1], chunks[k - 1].cam_to_world[-o:])
        pb = place_poses(G[k], chunks[k].cam_to_world[:o])
        rel = np.swapaxes(pa[:, :3, :3], 1, 2) @ pb[:, :3, :3]
        d.extend(np.asarray(se3.rotation_angle(jnp.asarray(rel))).tolist())
    return float(np.sqrt(np.mean(np.square(d))) / np.sqrt(2.0) / np.sqrt(3.0)) if d else float("nan")


_ate = jax.jit(ate)


def refine_frames(seq: Sequence, static=None, cfg: FrameGraphConfig = FrameGraphConfig(), noise: float | None = None,
                  rot_noise: float | None = None):
    """Refine a whole (stitched) trajectory in one pose graph over every frame.

    static: optional (S, H, W) bool; noise / rot_noise: prior centre noise (sequence units) and
    rotation noise (rad), the variance estimation's start (None: 1 % of median depth, 1°). Returns
    (poses (S, 4, 4), refined if kept else the input; facts dict with ``kept``).
    """
    t0 = time.perf_counter()
    P = np.asarray(seq.cam_to_world, np.float64)
    S = P.shape[0]
    facts = {"frames": S, "kept": False}
    if S < 2:
        return P, {**facts, "reason": "fewer than 2 frames"}
    if static is not None:
        static = np.asarray(static, bool)
        if static.shape != seq.depth.shape:
            raise StitchError(f"static: expected shape {seq.depth.shape} (frames, H, W), got {static.shape}")
    pairs = np.stack([np.arange(S - 1), np.arange(1, S)], 1)
    # padded to a multiple of cfg.pad_frames frames (and the pairs of as many): one compiled program
    N = -(-S // cfg.pad_frames) * cfg.pad_frames
    E = N - 1
    meas = measure_frame_pairs(seq, pairs, static, cfg, pad_to=E)
    frac, npts, rel = meas.inlier_fraction, meas.points, meas.residual
    Mr = sim3.to_rigid(meas.M)
    usable = ((frac >= cfg.min_inlier_fraction) & (npts >= cfg.min_points) & (rel <= cfg.max_residual)
              & np.all(np.isfinite(Mr), (1, 2)))
    t_measure = time.perf_counter() - t0
    if noise is None or not np.isfinite(noise) or noise <= 0:
        d = np.asarray(seq.depth, np.float64)
        noise = 0.01 * float(np.median(d[d > 0])) if np.any(d > 0) else 0.01
    rot_noise = np.deg2rad(1.0) if rot_noise is None or not np.isfinite(rot_noise) or rot_noise <= 0 else rot_noise
    sp = np.array([noise / np.sqrt(3.0)] * 3 + [rot_noise] * 3)
    sm = sp / 3.0
    Q = len(pairs)
    ia, ib = _pad(pairs[:, 0], E, "zeros"), _pad(pairs[:, 1], E, "zeros")
    Mp, w = _pad(Mr, E, "last"), _pad(usable.astype(np.float64), E, "zeros")
    Pp = _pad(P, N, "last")  # padded frames: only their prior
    limit = float(robust.chi2_quantile(cfg.outlier_quantile, 6))
    rounds = cfg.vce_iterations
    for it in range(rounds + 1):
        sol = solve_chain(frame_graph(Pp, ia, ib, Mp, sm, sp, w), jnp.asarray(Pp), iterations=cfg.iterations)
        if it == rounds:
            break
        rp, hp, rm, hm = (np.asarray(x, np.float64) for x in (sol.e_prior, sol.h_prior, sol.e_motion, sol.h_motion))
        sm_old = sm.copy()
        sp = robust.variance_components(rp, hp, np.arange(N) < S, sp)
        sm = robust.variance_components(rm, hm, w > 0, sm)
        # drop implausible motion factors (residuals whitened by the updated sigmas)
        w = np.where(np.sum((rm * sm_old / sm) ** 2, 1) > limit, 0.0, w)
    refined = np.asarray(sol.poses, np.float64)[:S]
    dev = float(_ate(jnp.asarray(refined), jnp.asarray(P)))
    ok = bool(np.all(np.isfinite(refined)))
    dev_limit = cfg.max_deviation * noise
    keep = ok and dev <= dev_limit
    if not keep:
        facts["reason"] = ("non-finite result" if not ok else
                           f"moves the trajectory by {dev:.3g} > {dev_limit:.3g} (max_deviation x the prior noise)")
    facts.update({"kept": keep, "pairs": Q, "pairs_used": int(np.sum(w > 0)),
                  "pairs_poor_fit": int(np.sum(~usable)),
                  "inlier_fraction_median": float(np.median(frac)) if len(frac) else float("nan"),
                  "residual_median": float(np.median(rel)) if len(rel) else float("nan"),
                  "sigma_prior_trans": float(sp[0]), "sigma_prior_rot_deg": float(np.rad2deg(sp[3])),
                  "sigma_motion_trans": float(sm[0]), "sigma_motion_rot_deg": float(np.rad2deg(sm[3])),
                  "deviation": dev, "deviation_limit": dev_limit, "rounds": rounds,
                  "cost_initial": float(sol.cost_initial), "cost": float(sol.cost), "measure_s": t_measure,
                  "seconds": time.perf_counter() - t0})
    return (refined if keep else P), facts
