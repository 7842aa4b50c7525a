"""The window's factor graph without memory: tracks checked against the prior geometry, LM with
outlier rejection (:func:`cm3d.trajectory.refine_trajectory`), the significance gate and the
depth-scale gauge."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from cm3d import trajectory
from cm3d.motion import moving_tracks
from cm3d.ops import camera, robust
from cm3d.pipeline.config import PipelineConfig
from cm3d.pipeline.landmarks import landmark_observations, nearest_pixel
from cm3d.pipeline.state import Landmarks, Window
from cm3d.solvers import factors


def _frame_motion_residuals(r, uv, group, ok, num_groups: int, K, min_scale, rounds: int = 5):
    """Transfer residuals (K, 2) with each group's common image motion (what a prior pose error
    causes) removed: per group (one frame, one seeding frame) an affine field ``r ≈ a + B (uv − c) / f``
    fitted by IRLS with Cauchy weights at a robust scale (at least ``min_scale`` px); groups with
    fewer than 8 observations stay. r, uv (K, 2); group (K,) in [0, num_groups); ok (K,); K (K, 3, 3)."""
    f = K[:, 0, 0]
    phi = jnp.stack([jnp.ones_like(f), (uv[:, 0] - K[:, 0, 2]) / f, (uv[:, 1] - K[:, 1, 2]) / f], -1)  # (K, 3)
    r0 = jnp.where(ok[:, None], r, 0.0)
    count = jax.ops.segment_sum(ok.astype(jnp.int32), group, num_groups)
    w = ok.astype(r.dtype)
    eye = jnp.eye(3, dtype=r.dtype)
    res = r0
    for _ in range(rounds):
        A = jax.ops.segment_sum(w[:, None, None] * phi[:, :, None] * phi[:, None, :], group, num_groups)
        b = jax.ops.segment_sum(w[:, None, None] * phi[:, :, None] * r0[:, None, :], group, num_groups)
        tr = jnp.trace(A, axis1=-2, axis2=-1)
        coef = jnp.linalg.solve(A + 1e-6 * jnp.maximum(tr, 1e-12)[:, None, None] * eye, b)
        coef = jnp.where((count >= 8)[:, None, None] & jnp.all(jnp.isfinite(coef), (1, 2), keepdims=True), coef, 0.0)
        res = r0 - jnp.einsum("ki,kij->kj", phi, coef[group])
        e2 = jnp.sum(res * res, -1)
        scale = jnp.maximum(min_scale, robust.MAD_TO_SIGMA * jnp.sqrt(robust.masked_median(e2, ok)))
        w = ok / (1.0 + e2 / scale ** 2)
    return res


def prior_consistent_tracks(win: Window, lm_: Landmarks, obs: trajectory.Observations, cfg: PipelineConfig):
    """(L,) which tracks agree with the prior geometry (:class:`~cm3d.pipeline.TrackCheckConfig`): the
    RMS over a track's observations after the seed of the reprojection error at the initial
    variables, with the image motion of the prior's pose error removed (:func:`_frame_motion_residuals`)."""
    L, T = lm_.obs_valid.shape
    ov = obs.valid.reshape(L, T)
    has = ov[:, 0]
    P = win.poses[obs.pose_idx]
    Kk = win.intrinsic[obs.pose_idx]
    pred, z = factors.project(P, lm_.points[obs.point_idx], Kk)
    r = pred - obs.uv
    j = jnp.tile(jnp.arange(T), L)
    ok = obs.valid & (z > factors.MIN_DEPTH) & jnp.all(jnp.isfinite(r), -1) & (j > 0)
    W = win.poses.shape[0]
    block = jnp.repeat(lm_.seed // cfg.track.keyframe_every, T)
    group = block * W + obs.pose_idx
    res = _frame_motion_residuals(r, obs.uv, group, ok, cfg.seed_blocks * W, Kk, cfg.track_check.min_px)
    err = jnp.where(ok, jnp.linalg.norm(res, axis=-1), jnp.where(obs.valid & (j > 0), 1e6, 0.0)).reshape(L, T)
    n = jnp.sum(ov, -1)
    sq = jnp.sum(jnp.where(ov, err ** 2, 0.0), -1)
    rms = jnp.sqrt(sq / jnp.maximum(n - 1, 1))
    med = robust.masked_median(rms, has)
    tau = jnp.maximum(cfg.track_check.min_px, med + cfg.track_check.n_mad * robust.mad_sigma(rms, has))
    return has & (rms <= tau)


def structure_only_cost(graph: factors.FactorGraph, poses, points, iterations: int = 15, min_observations: int = 2):
    """The graph's objective with the poses held and every landmark re-estimated (the gate's null
    hypothesis): the landmarks decouple, so each takes damped, Huber-reweighted Gauss-Newton steps on
    its own 3x3 system, kept only when its cost falls. Landmarks with fewer than ``min_observations``
    observations are ignored, as in :func:`cm3d.solvers.lm.solve`. Returns (cost, points (M, 3))."""
    f = graph.projection
    M = points.shape[0]
    k = jnp.asarray(graph.huber_k, points.dtype)
    counts = jax.ops.segment_sum((f.weight > 0).astype(jnp.int32), f.point_idx, M)
    active = (f.weight > 0) & (counts >= min_observations)[f.point_idx]
    w0 = jnp.where(active, f.weight, 0.0)

    pp = graph.point_prior
    wl = jnp.zeros(M, points.dtype) if pp is None else jnp.where(counts >= min_observations, pp.weight, 0.0)

    def prior_terms(pts):  # landmark priors (memory): per-landmark cost, Gauss-Newton block and gradient
        if pp is None:
            return jnp.zeros(M, pts.dtype), 0.0, 0.0
        r = factors.point_prior_residual(graph, pts)
        S = pp.sqrt_info.astype(pts.dtype)
        return (0.5 * wl * jnp.sum(r * r, -1), wl[:, None, None] * jnp.einsum("mij,mil->mjl", S, S),
                wl[:, None] * jnp.einsum("mij,mi->mj", S, r))

    def per_point_cost(pts):
        e, _ = factors.projection_residual(graph, factors.Variables(poses, pts))
        return jax.ops.segment_sum(w0 * factors.huber_loss(jnp.sum(e * e, -1), k), f.point_idx, M) + prior_terms(pts)[0]

    def body(_, carry):
        pts, lam = carry
        e, _, B, _ = factors.projection_linearize(graph, factors.Variables(poses, pts))
        w = w0 * factors.huber_weight(jnp.sum(e * e, -1), k)
        H = jax.ops.segment_sum(w[:, None, None] * jnp.einsum("kij,kil->kjl", B, B), f.point_idx, M)
        g = jax.ops.segment_sum(w[:, None] * jnp.einsum("kij,ki->kj", B, e), f.point_idx, M)
        _, Hl, gl = prior_terms(pts)
        H, g = H + Hl, g + gl
        diag = jnp.diagonal(H, axis1=-2, axis2=-1)
        Hd = H + (lam[:, None] * jnp.maximum(diag, 1e-12))[:, :, None] * jnp.eye(3, dtype=H.dtype)
        step = -jnp.linalg.solve(Hd, g[..., None])[..., 0]
        step = jnp.where(jnp.isfinite(step), step, 0.0)
        new = pts + step
        better = per_point_cost(new) < per_point_cost(pts)
        return jnp.where(better[:, None], new, pts), jnp.where(better, lam * 0.1, lam * 10.0)

    pts, _ = jax.lax.fori_loop(0, iterations, body, (points, jnp.full(M, 1e-4, points.dtype)))
    cost = factors.total_cost(graph, factors.Variables(poses, pts), active)
    if pp is not None:  # total_cost counts every landmark prior; count those of estimable landmarks only
        cost = cost - factors.point_prior_cost(graph, pts) + jnp.sum(prior_terms(pts)[0])
    return cost, pts


def chi2_threshold(obs: trajectory.Observations, inlier, num_poses: int, quantile, dtype):
    """``χ²_q(6 (n − 1))``, ``n`` the poses with an inlier observation."""
    seen = jnp.zeros(num_poses, jnp.int32).at[obs.pose_idx].max(inlier.astype(jnp.int32))
    return robust.chi2_quantile(quantile, 6.0 * jnp.maximum(jnp.sum(seen) - 1, 1).astype(dtype))


def gate_refinement(win: Window, points0, obs: trajectory.Observations, ref: trajectory.Refinement,
                    cfg: PipelineConfig) -> trajectory.Refinement:
    """The significance gate on an ungated refinement: the likelihood-ratio test of "the prior poses
    are right" (poses held, landmarks re-estimated from their lifted positions ``points0`` on the
    inlier observations) against the refined poses, ``2 ΔC > χ²_q(6 (n − 1))``."""
    rc = cfg.refine
    if not rc.gate:
        return ref.replace(refined=jnp.ones((), bool))
    gp = ref.graph.projection if ref.graph is not None else None
    g = factors.build_graph(win.poses, win.intrinsic, obs.pose_idx, obs.point_idx, obs.uv, ref.inlier,
                            gp.memory if gp is not None else obs.memory, win.valid, rc.graph,
                            None if gp is None else gp.depth, None if gp is None else gp.depth_sigma)
    if ref.graph is not None and ref.graph.point_prior is not None:  # both hypotheses see the remembered surface
        g = g.replace(point_prior=ref.graph.point_prior)
    cost0, points_fixed = structure_only_cost(g, win.poses, points0, min_observations=rc.solver.min_observations)
    dt = win.poses.dtype
    stat = (2.0 * (cost0 - ref.result.cost)).astype(dt)
    thr = chi2_threshold(obs, ref.inlier, win.poses.shape[0], rc.gate_quantile, dt)
    use = stat > thr
    return ref.replace(poses=jnp.where(use, ref.refined_poses, win.poses),
                       points=jnp.where(use, ref.result.params.points, points_fixed),
                       refined=use, gate_stat=stat, gate_threshold=thr)


def rescale_window(poses, points, init_poses, init_points, seed, valid):
    """The graph's solution at the prior depth's scale (the gauge the factors leave nearly free):
    camera centres and landmarks rescaled about the anchor by ``1 / r``, ``r`` the median ratio of
    each landmark's distance to its seeding camera, refined over initial. poses, init_poses
    (W, 4, 4); points, init_points (L, 3); seed (L,) slot; valid (L,). Returns (poses, points)."""
    d_ref = jnp.linalg.norm(points - poses[seed, :3, 3], axis=-1)
    d_init = jnp.linalg.norm(init_points - init_poses[seed, :3, 3], axis=-1)
    ok = valid & (d_init > 0) & jnp.isfinite(d_ref)
    r = robust.masked_median(d_ref / jnp.where(ok, d_init, 1.0), ok)
    r = jnp.where((jnp.sum(ok) >= 3) & jnp.isfinite(r) & (r > 0), jnp.clip(r, 0.2, 5.0), 1.0)
    c0 = poses[0, :3, 3]
    return poses.at[:, :3, 3].set(c0 + (poses[:, :3, 3] - c0) / r), c0 + (points - c0) / r


def observed_depth(win: Window, obs: trajectory.Observations, max_ratio: float):
    """The prior depth (K,) at every observation's nearest pixel of its slot, 0 where the depth is
    not a measurement of the tracked point: confidence 0 (e.g. a filled sensor hole), a depth edge
    (the 3x3 neighbourhood's max / min above ``max_ratio``: a pixel off there lands on the other
    surface) or an invalid observation."""
    h, w = win.depth.shape[1:]
    r, c = nearest_pixel(obs.uv, h, w)
    i = obs.pose_idx
    d = win.depth[i, r, c]
    ok = obs.valid & (win.conf[i, r, c] > 0) & camera.depth_smooth(win.depth, max_ratio)[i, r, c]
    return jnp.where(ok, d, 0.0)


def factor_graph(win: Window, lm_: Landmarks, cfg: PipelineConfig):
    """The window's factor graph without memory: prior check (:func:`prior_consistent_tracks`), track cue
    (:func:`cm3d.motion.moving_tracks`), LM with outlier rejection, the gate, the depth-scale gauge.
    Returns (Refinement, poses, observations, dropped tracks)."""
    obs = landmark_observations(lm_, cfg)
    T = cfg.track.track_length
    obs_all_first = obs.valid.reshape(lm_.obs_valid.shape)[:, 0]
    first = prior_consistent_tracks(win, lm_, obs, cfg)
    first = first & ~moving_tracks(lm_.points, win.poses, win.intrinsic, obs.pose_idx, obs.uv, obs.valid,
                                   lm_.seed // cfg.track.keyframe_every, cfg.seed_blocks, cfg.motion)
    obs = obs.replace(valid=obs.valid & jnp.repeat(first, T))
    if cfg.refine.depth_factors:
        obs = obs.replace(depth=observed_depth(win, obs, cfg.refine.depth_edge_ratio))
    ungated = dataclasses.replace(cfg.refine, gate=False)
    ref = trajectory.refine_trajectory(win.poses, win.intrinsic, lm_.points, obs, ungated, pose_valid=win.valid,
                                       memory=None, assoc=cfg.assoc, realign=False)
    ref = gate_refinement(win, lm_.points, obs, ref, cfg)
    n_bad = jnp.sum(obs_all_first & ~first)
    # the scale fix belongs to refined poses only: when the gate keeps the prior, so does the scale
    fixed = rescale_window(ref.poses, ref.points, win.poses, lm_.points, lm_.seed, first)[0]
    poses = jnp.where(ref.refined, fixed, ref.poses)
    poses = jnp.where(win.valid[:, None, None], poses, win.poses)
    return ref, poses, obs, n_bad
