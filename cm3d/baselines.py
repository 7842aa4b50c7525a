"""Host-side baselines and reference solvers (numpy, OpenCV, GTSAM): never inside ``jit``.

* :func:`pnp_ransac_poses`: per-frame PnP + RANSAC (OpenCV ``solvePnPRansac``, 2 px, 1000
  iterations), the paper's Table 4 baseline, on the same landmarks and tracks cm3d refines.
* :func:`prior_poses`: the foundation-model prior itself.
* :func:`gtsam_graph` / :func:`gtsam_solve`: the same factor graph in GTSAM (projection factors
  with a Huber robust model, ``PriorFactorPose3``, ``BetweenFactorPose3``) and its
  ``LevenbergMarquardtOptimizer``: the reference the LM solver is tested and benchmarked against.
* :func:`monst3r_masks`: the MonST3R-style fixed-threshold dynamic mask of a sequence.

Poses are cam_to_world 4x4 (see :mod:`cm3d.ops.se3`). GTSAM's tangent order is (rotation,
translation), jaxlie's (translation, rotation): sigmas are permuted here, nowhere else.
"""

from __future__ import annotations

import dataclasses
import functools
import time

import numpy as np


# ----------------------------------------------------------------------------------------------
# Prior and PnP + RANSAC


def prior_poses(seq) -> np.ndarray:
    """The prior's own poses (S, 4, 4): the 'no refinement' baseline."""
    return np.asarray(seq.cam_to_world, np.float64)


def pnp_ransac_poses(points, pose_idx, point_idx, uv, valid, intrinsics, fallback,
                     reproj_px: float = 2.0, iterations: int = 1000, min_points: int = 6,
                     confidence: float = 0.999, seed: int = 0):
    """Per-frame PnP + RANSAC poses (S, 4, 4) cam_to_world, and which frames succeeded (S,) bool.

    points: (M, 3) world landmarks (from prior depth); pose_idx, point_idx, uv, valid: padded
    observations (K,), (K,), (K, 2), (K,); intrinsics: (S, 3, 3); fallback: (S, 4, 4) poses used
    where PnP has fewer than ``min_points`` correspondences or fails (the prior). OpenCV's
    ``solvePnPRansac`` (EPnP hypotheses, iterative refinement on the inliers), ``reproj_px``
    threshold, ``iterations`` RANSAC iterations, seeded.
    """
    import cv2

    points = np.asarray(points, np.float64)
    pose_idx, point_idx = np.asarray(pose_idx), np.asarray(point_idx)
    uv, valid = np.asarray(uv, np.float64), np.asarray(valid, bool)
    intrinsics, fallback = np.asarray(intrinsics, np.float64), np.asarray(fallback, np.float64)
    S = len(fallback)
    out, ok = fallback.copy(), np.zeros(S, bool)
    for s in range(S):
        sel = valid & (pose_idx == s)
        if sel.sum() < min_points:
            continue
        obj = np.ascontiguousarray(points[point_idx[sel]])
        img = np.ascontiguousarray(uv[sel])
        cv2.setRNGSeed(seed + s)
        found, rvec, tvec, inliers = cv2.solvePnPRansac(
            obj, img, intrinsics[s], None, iterationsCount=iterations, reprojectionError=reproj_px,
            confidence=confidence, flags=cv2.SOLVEPNP_EPNP)
        if not found or inliers is None or len(inliers) < min_points:
            continue
        inl = inliers[:, 0]
        rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], intrinsics[s], None, rvec, tvec)
        R, _ = cv2.Rodrigues(rvec)
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(tvec))):
            continue
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R.T, -R.T @ tvec[:, 0]
        out[s], ok[s] = T, True
    return out, ok


# ----------------------------------------------------------------------------------------------
# GTSAM reference


def _perm(sigma):
    """jaxlie tangent order (v, w) -> GTSAM's (w, v)."""
    sigma = np.asarray(sigma, np.float64)
    return np.concatenate([sigma[3:], sigma[:3]])


def gtsam_graph(graph, init, min_observations: int = 2):
    """The :class:`~cm3d.solvers.factors.FactorGraph` as a GTSAM graph and initial values.

    Only factors with weight > 0 are added (weights must be 0 or 1); landmarks with fewer than
    ``min_observations`` observations are left out with their observations (cm3d freezes them).
    Returns (graph, values, active_poses (N,) bool, active_points (M,) bool).
    """
    import gtsam
    from gtsam.symbol_shorthand import L, X

    f, pf, mf = graph.projection, graph.prior, graph.motion
    if np.any(np.asarray(graph.pose_fixed)):
        raise ValueError("gtsam_graph: fixed poses are not supported by the GTSAM reference")
    w = np.asarray(f.weight, np.float64)
    for name, ww in (("projection", w), ("prior", np.asarray(pf.weight)), ("motion", np.asarray(mf.weight))):
        if np.any((ww != 0) & (ww != 1)):
            raise ValueError(f"gtsam_graph: {name} weights must be 0 or 1 for the GTSAM reference")
    poses0 = np.asarray(init.poses, np.float64)
    points0 = np.asarray(init.points, np.float64)
    N, M = len(poses0), len(points0)
    pose_idx, point_idx = np.asarray(f.pose_idx), np.asarray(f.point_idx)
    z = np.asarray(f.z, np.float64)
    alpha = float(graph.memory_alpha)
    sig = np.asarray(f.sigma, np.float64) * np.where(np.asarray(f.memory), np.sqrt(alpha), 1.0)
    Ks = np.asarray(graph.intrinsics, np.float64)
    k = float(graph.huber_k)
    on = w > 0
    counts = np.bincount(point_idx[on], minlength=M)
    point_ok = counts >= min_observations
    on &= point_ok[point_idx]

    g = gtsam.NonlinearFactorGraph()
    noise_cache, cal_cache = {}, {}
    pose_used = np.zeros(N, bool)
    for kk in np.flatnonzero(on):
        s = float(sig[kk])
        if s not in noise_cache:
            base = gtsam.noiseModel.Isotropic.Sigma(2, s)
            noise_cache[s] = (gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(k), base)
                              if np.isfinite(k) else base)
        i = int(pose_idx[kk])
        if i not in cal_cache:
            Kc = Ks[i]
            cal_cache[i] = gtsam.Cal3_S2(Kc[0, 0], Kc[1, 1], Kc[0, 1], Kc[0, 2], Kc[1, 2])
        g.add(gtsam.GenericProjectionFactorCal3_S2(z[kk], noise_cache[s], X(i), L(int(point_idx[kk])),
                                                   cal_cache[i]))
        pose_used[i] = True
    for p in np.flatnonzero(np.asarray(pf.weight) > 0):
        i = int(pf.pose_idx[p])
        noise = gtsam.noiseModel.Diagonal.Sigmas(_perm(pf.sigma[p]))
        g.add(gtsam.PriorFactorPose3(X(i), gtsam.Pose3(np.asarray(pf.target[p], np.float64)), noise))
        pose_used[i] = True
    for q in np.flatnonzero(np.asarray(mf.weight) > 0):
        a, b = int(mf.idx_a[q]), int(mf.idx_b[q])
        noise = gtsam.noiseModel.Diagonal.Sigmas(_perm(mf.sigma[q]))
        g.add(gtsam.BetweenFactorPose3(X(a), X(b), gtsam.Pose3(np.asarray(mf.measured[q], np.float64)), noise))
        pose_used[a] = pose_used[b] = True
    values = gtsam.Values()
    for i in np.flatnonzero(pose_used):
        values.insert(X(int(i)), gtsam.Pose3(poses0[i]))
    for j in np.flatnonzero(point_ok):
        values.insert(L(int(j)), gtsam.Point3(*points0[j]))
    return g, values, pose_used, point_ok


def gtsam_params(max_iterations: int = 100, rel_tol: float = 1e-5, abs_tol: float = 1e-5):
    """GTSAM's default LM parameters (λ0 = 1e-5, factor 10, bounds [0, 1e5]) with these tolerances."""
    import gtsam

    p = gtsam.LevenbergMarquardtParams()
    p.setMaxIterations(max_iterations)
    p.setRelativeErrorTol(rel_tol)
    p.setAbsoluteErrorTol(abs_tol)
    return p


def _extract(values, init, pose_used, point_ok):
    from gtsam.symbol_shorthand import L, X

    poses = np.array(init.poses, np.float64)
    points = np.array(init.points, np.float64)
    for i in np.flatnonzero(pose_used):
        poses[i] = values.atPose3(X(int(i))).matrix()
    for j in np.flatnonzero(point_ok):
        points[j] = values.atPoint3(L(int(j)))
    return poses, points


@dataclasses.dataclass(frozen=True)
class GTSAMSolution:
    """GTSAM's optimum: poses (N, 4, 4), points (M, 3) float64; cost, initial_cost; iterations;
    time_s of ``optimize()`` alone; history (error after each outer iteration) or None."""

    poses: np.ndarray
    points: np.ndarray
    cost: float
    initial_cost: float
    iterations: int
    time_s: float
    history: np.ndarray | None = None


def gtsam_solve(graph, init, max_iterations: int = 100, rel_tol: float = 1e-5, abs_tol: float = 1e-5,
                history: bool = False, min_observations: int = 2) -> GTSAMSolution:
    """Solve with GTSAM's ``LevenbergMarquardtOptimizer`` -> :class:`GTSAMSolution` (graph building
    excluded from ``time_s``); with ``history`` a second run steps ``iterate()`` and records the
    error after each outer iteration."""
    import gtsam

    g, values, pose_used, point_ok = gtsam_graph(graph, init, min_observations)
    params = gtsam_params(max_iterations, rel_tol, abs_tol)
    opt = gtsam.LevenbergMarquardtOptimizer(g, values, params)
    t0 = time.perf_counter()
    result = opt.optimize()
    elapsed = time.perf_counter() - t0
    poses, points = _extract(result, init, pose_used, point_ok)
    out = GTSAMSolution(poses, points, float(g.error(result)), float(g.error(values)), int(opt.iterations()),
                        elapsed)
    if history:
        opt = gtsam.LevenbergMarquardtOptimizer(g, values, params)
        hist = [opt.error()]
        while opt.iterations() < max_iterations:
            before = opt.error()
            opt.iterate()
            after = opt.error()
            if after < before:
                hist.append(after)
            dec = before - after
            if (rel_tol and dec / before < rel_tol) or dec < abs_tol:
                break
        out = dataclasses.replace(out, history=np.array(hist))
    return out


# ----------------------------------------------------------------------------------------------
# MonST3R-style dynamic masks


def monst3r_masks(inputs, num_frames: int, shape, cfg) -> np.ndarray:
    """The MonST3R-style baseline's dynamic masks (S, H, W) bool of one sequence, at input resolution.

    ``|flow − ego flow| > cfg.motion.baseline_threshold_px`` (a fixed threshold, no occlusion or
    appearance reasoning, no keypoint verification) under the same flow-refined relative pose as
    cm3d's cue, on the pipeline's host :class:`~cm3d.pipeline.prepare.Inputs` (what
    ``pipeline.run(observe=...)`` hands over) at its ``1 / stride``, upsampled like cm3d's masks.
    """
    import jax

    from cm3d.pipeline.run import upsample_masks

    sub = jax.tree.map(lambda a: np.asarray(a)[:num_frames], inputs)
    m = np.asarray(_monst3r_program()(sub.frame, sub.partner, sub.flow, sub.flow_rev, cfg.motion), bool)
    return upsample_masks(m, cfg.stride, shape)


def _monst3r_one(prior_t, prior_t2, flow, flow_rev, mcfg):
    from cm3d.motion import baseline_motion_cue, geometry_motion_cue

    rel = geometry_motion_cue(prior_t, prior_t2, flow, mcfg, flow_rev).rel_pose
    return baseline_motion_cue(prior_t, prior_t2, flow, rel, mcfg)


@functools.cache
def _monst3r_program():
    import jax

    return jax.jit(jax.vmap(_monst3r_one, in_axes=(0, 0, 0, 0, None)), static_argnums=4)
