"""Robust (keypoint) cue: candidate regions confirmed by keypoints that move against the scene.

Matches are lifted to 3D with both frames' 3x3-median depth and the refined relative pose; their
displacement, divided by depth (the prior's scale is unknown, its depth noise relative), is scored
against the static reference's robust statistics along and across the viewing ray.
"""

from __future__ import annotations

import jax.numpy as jnp

from cm3d.motion.frames import FramePrior, MotionConfig
from cm3d.ops import camera, components, robust, se3
from cm3d.ops.robust import masked_median_low


def _sample_median3(depth, uv):
    """3x3 median of the positive depths around the nearest pixels of (N, 2) ``(u, v)`` (0 when
    none is positive; the lower middle value for an even count), and in-bounds flags."""
    H, W = depth.shape
    u = jnp.round(uv[:, 0]).astype(jnp.int32)
    v = jnp.round(uv[:, 1]).astype(jnp.int32)
    inb = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    off = jnp.arange(-1, 2)
    vv = jnp.clip(v[:, None, None] + off[None, :, None], 0, H - 1)
    uu = jnp.clip(u[:, None, None] + off[None, None, :], 0, W - 1)
    patch = depth[vv, uu].reshape(-1, 9)
    ok = patch > camera.MIN_DEPTH
    cnt = jnp.sum(ok, -1)
    srt = jnp.sort(jnp.where(ok, patch, jnp.inf), axis=-1)
    med = jnp.take_along_axis(srt, jnp.clip((cnt - 1) // 2, 0, 8)[:, None], -1)[:, 0]
    return jnp.where(cnt > 0, med, 0.0), inb


def _sample(img, uv):
    """Nearest-pixel values of img (H, W[, C]) at (N, 2) ``(u, v)``; and in-bounds flags."""
    H, W = img.shape[:2]
    u = jnp.round(uv[:, 0]).astype(jnp.int32)
    v = jnp.round(uv[:, 1]).astype(jnp.int32)
    inb = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    return img[jnp.clip(v, 0, H - 1), jnp.clip(u, 0, W - 1)], inb


def candidate_regions(flow_mask, geo_mask, valid, cfg: MotionConfig = MotionConfig()):
    """Cleaned candidate mask and its component labels: the chosen combination of the flow and
    geometry masks, opened by ``open_radius`` and without components under ``min_region_frac``."""
    if cfg.candidate_source == "geo":
        cand = geo_mask
    elif cfg.candidate_source == "union":
        cand = geo_mask | (flow_mask & valid)
    else:
        cand = geo_mask & flow_mask
    cand = components.opening(cand, cfg.open_radius)
    H, W = cand.shape
    labels = components.label_components(cand)
    keep = components.region_area(labels) >= max(1, int(round(cfg.min_region_frac * H * W)))
    labels = jnp.where(keep, labels, -1)
    return labels >= 0, labels


def keypoint_displacements(prior_t: FramePrior, prior_t2: FramePrior, matches, rel,
                           cfg: MotionConfig = MotionConfig()):
    """Relative 3D displacement (N, 3) of matched keypoints in camera-t axes, their unit viewing rays
    (N, 3) and validity (N,).

    Both ends are lifted with their frame's 3x3-median depth (invalid on a depth edge), the t2 end
    brought into camera t by ``inv(rel)``; frame t2's depth is rescaled by the median predicted /
    observed ratio and the displacement divided by the depth in frame t, so it is free of the
    prior's unknown scale.
    """
    uv0, uv1 = matches.uv0.astype(prior_t.depth.dtype), matches.uv1.astype(prior_t.depth.dtype)
    z0, in0 = _sample_median3(prior_t.depth, uv0)
    z1, in1 = _sample_median3(prior_t2.depth, uv1)
    s0, _ = _sample(camera.depth_smooth(prior_t.depth, cfg.kp_max_depth_ratio), uv0)
    s1, _ = _sample(camera.depth_smooth(prior_t2.depth, cfg.kp_max_depth_ratio), uv1)
    ok = jnp.asarray(matches.valid, bool) & in0 & in1 & s0 & s1 & (z0 > camera.MIN_DEPTH) & (z1 > camera.MIN_DEPTH)

    X0 = camera.backproject(uv0, z0, prior_t.intrinsic)
    z_pred = se3.transform_points(rel, X0)[:, 2]
    ratio = z_pred / jnp.where(ok, z1, 1.0)
    scale = masked_median_low(ratio, ok & (ratio > 0))
    scale = jnp.where(scale > 0, scale, 1.0)
    X1 = se3.transform_points(se3.inverse(rel), camera.backproject(uv1, z1 * scale, prior_t2.intrinsic))
    disp = (X1 - X0) / jnp.where(ok, z0, 1.0)[:, None]
    ray = X0 / jnp.maximum(jnp.linalg.norm(X0, axis=-1, keepdims=True), 1e-12)
    return jnp.where(ok[:, None], disp, 0.0), ray, ok


def static_reference(labels, matches, kp_ok, cfg: MotionConfig = MotionConfig()):
    """Valid keypoints (N,) outside every candidate region: the presumed-static reference."""
    lab, inb = _sample(labels, matches.uv0.astype(jnp.float32))
    return kp_ok & inb & (lab < 0)


def dynamic_keypoints(disp, ray, ok, cfg: MotionConfig = MotionConfig(), reference=None):
    """Keypoints (N,) whose relative displacement deviates from the robust mean one.

    Statistics come from the ``reference`` keypoints (default: all valid; :func:`motion_cues` passes
    those outside the candidate regions); with fewer than ``kp_min_reference`` the reference is zero
    displacement with sigmas ``kp_sigma_along`` / ``kp_sigma_across``. The deviation from the median
    is split along the viewing ray (depth noise) and across it, each scaled by its robust sigma. A
    keypoint is dynamic when the score exceeds ``kp_sigma_k`` and the deviation ``kp_min_rel_disp``
    (magnitude), or when both ``|d_i|`` and ``|m|`` exceed ``kp_min_rel_disp`` at an angle above
    ``kp_direction_deg`` (direction).
    """
    ref = ok if reference is None else jnp.asarray(reference, bool) & ok
    enough = jnp.sum(ref) >= cfg.kp_min_reference
    m = jnp.stack([masked_median_low(disp[:, k], ref) for k in range(3)]) * enough
    dev = disp - m
    along = jnp.sum(dev * ray, -1)
    across = jnp.linalg.norm(dev - along[:, None] * ray, axis=-1)
    floor = cfg.kp_min_rel_disp / max(cfg.kp_sigma_k, 1e-6) / 4.0
    med_along = masked_median_low(along, ref) * enough
    s_along = jnp.where(enough, robust.MAD_TO_SIGMA * masked_median_low(jnp.abs(along - med_along), ref),
                        cfg.kp_sigma_along)
    s_across = jnp.where(enough, masked_median_low(across, ref) / 1.1774, cfg.kp_sigma_across)
    s_along, s_across = jnp.maximum(s_along, floor), jnp.maximum(s_across, floor)
    score = jnp.sqrt(((along - med_along) / s_along) ** 2 + (across / s_across) ** 2)
    mag = (score > cfg.kp_sigma_k) & (jnp.linalg.norm(dev, axis=-1) > cfg.kp_min_rel_disp)
    nd, nm = jnp.linalg.norm(disp, axis=-1), jnp.linalg.norm(m)
    cosang = jnp.sum(disp * m, -1) / jnp.maximum(nd * nm, 1e-12)
    big = (nd > cfg.kp_min_rel_disp) & (nm > cfg.kp_min_rel_disp)
    direction = big & (cosang < jnp.cos(jnp.deg2rad(cfg.kp_direction_deg)))
    return (mag | direction) & ok


def robust_motion_cue(labels, matches, kp_dynamic, kp_ok, cfg: MotionConfig = MotionConfig()):
    """Candidate regions (labels from :func:`candidate_regions`) confirmed by dynamic keypoints.

    A region is kept with at least ``kp_min_dynamic`` dynamic keypoints, also ``kp_min_fraction`` of
    its valid ones; one without keypoints iff ``keep_unverified``. Returns (mask (H, W), flags (N,)).
    """
    H, W = labels.shape
    n = H * W
    lab, inb = _sample(labels, matches.uv0.astype(jnp.float32))
    inside = kp_ok & inb & (lab >= 0)
    idx = jnp.where(inside, lab, n)
    dyn = kp_dynamic & inside
    n_dyn = jnp.zeros(n + 1, jnp.int32).at[idx].add(dyn.astype(jnp.int32))[:n]
    n_all = jnp.zeros(n + 1, jnp.int32).at[idx].add(inside.astype(jnp.int32))[:n]
    confirmed = (n_dyn >= cfg.kp_min_dynamic) & (n_dyn >= cfg.kp_min_fraction * n_all)
    if cfg.keep_unverified:
        confirmed = confirmed | (n_all == 0)
    region = jnp.where(labels >= 0, confirmed[jnp.maximum(labels, 0)], False)
    return region, dyn
