"""Geometry cue: the residual between the observed flow and the ego flow of the static scene.

The prior poses are noisy (tens of pixels of ego-flow error), so the relative pose is first
re-aligned to the flow (:func:`refine_relative_pose`); ``|flow − ego_flow|`` is thresholded by Otsu
on log residual above a noise floor. The MonST3R-style baseline uses a fixed 1 px.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from cm3d.motion.frames import FramePrior, MotionConfig
from cm3d.motion.occlusion import depth_range_residual, forward_backward_consistent, visible_in_partner
from cm3d.ops import camera, robust, se3
from cm3d.ops.components import dilate, line_opening
from cm3d.ops.otsu import threshold_otsu
from cm3d.ops.robust import masked_median_low
from cm3d.solvers.camera_motion import fit_camera_motion


def relative_pose(prior_t: FramePrior, prior_t2: FramePrior):
    """Camera-t to camera-t2 transform ``inv(T_t2) @ T_t`` (4, 4) of the priors."""
    return se3.inverse(prior_t2.cam_to_world) @ prior_t.cam_to_world


def ego_flow_rel(depth, K0, K1, rel):
    """Static-scene flow (H, W, 2) and validity for camera-0 depth and relative pose ``rel``."""
    eye = jnp.eye(4, dtype=depth.dtype)
    return camera.ego_flow(depth, K0, eye, K1, se3.inverse(rel))


def _lands_inside(flow, margin):
    """(H, W) bool: the flow sends the pixel at least ``margin`` px inside the image."""
    H, W = flow.shape[:2]
    tgt = camera.pixel_grid(H, W, flow.dtype) + flow
    u, v = tgt[..., 0], tgt[..., 1]
    return (u >= margin) & (u <= W - 1 - margin) & (v >= margin) & (v <= H - 1 - margin)


def refine_relative_pose(depth, K0, K1, flow, rel_init, weight, cfg: MotionConfig = MotionConfig()):
    """Camera-0 to camera-1 pose (4, 4) that best explains ``flow`` on static pixels.

    Minimises ``sum_i w_i rho(|pi(K1 T X_i) - (p_i + F(p_i))|)`` over a ``pose_stride`` grid, ``X_i``
    lifted with ``depth``/``K0``, Geman-McClure at a robust scale (movers are the outliers), by
    ``pose_iters`` Gauss-Newton steps from ``rel_init`` (:func:`cm3d.solvers.camera_motion.fit_camera_motion`).
    ``weight`` (H, W) >= 0. Without valid pixels returns ``rel_init``.
    """
    s = cfg.pose_stride
    H, W = depth.shape
    grid = camera.pixel_grid(H, W, depth.dtype)[::s, ::s].reshape(-1, 2)
    d = depth[::s, ::s].reshape(-1)
    target = grid + flow[::s, ::s].reshape(-1, 2)
    w0 = weight[::s, ::s].reshape(-1) * (d > camera.MIN_DEPTH)

    def scale(rn, ok):
        return jnp.maximum(cfg.pose_min_scale_px,
                           cfg.pose_scale_k * robust.MAD_TO_SIGMA * masked_median_low(rn, ok))

    T = fit_camera_motion(camera.backproject(grid, d, K0), target, K1, w0, rel_init.astype(depth.dtype)[None],
                          scale, cfg.pose_iters)
    return T[0]


@struct.dataclass
class GeometryCue:
    """The residual-flow cue of one frame pair: mask, residual (H, W) px, valid (H, W), the Otsu
    threshold (px), the flow-refined relative pose (4, 4) camera t -> camera t2 and the occluded
    pixels (H, W) (forward-backward inconsistent or hidden in t2; never judged), the ego flow (H, W, 2)
    of the pixel's own depth under that pose."""

    mask: jax.Array
    residual: jax.Array
    valid: jax.Array
    threshold: jax.Array
    rel_pose: jax.Array
    occluded: jax.Array
    ego: jax.Array


def geometry_motion_cue(prior_t: FramePrior, prior_t2: FramePrior, flow, cfg: MotionConfig = MotionConfig(),
                        flow_back=None) -> GeometryCue:
    """Residual flow cue (:class:`GeometryCue`) of frame t against t2.

    ``residual`` = distance of the flow to the ego flows of the depths within ``edge_radius_px``
    (:func:`~cm3d.motion.occlusion.depth_range_residual`; the plain ``|flow - ego_flow|`` inside a
    surface) under the flow-refined relative pose. Judged (``valid``) where depth is positive and
    confident (``depth_conf >= min_depth_conf`` and > 0: a zero confidence is no measurement, e.g.
    a sensor hole that :func:`cm3d.data.quality.fill_depth_holes` filled), in front of both
    cameras, inside the image and not occluded: the z-buffer test
    against t2's depth (``cfg.occlusion``) and, with ``flow_back`` (H, W, 2), t2 -> t, the
    forward-backward check (it always keeps inconsistent pixels out of the pose fit, and out of
    the judgement with ``cfg.fb_occludes``: off by default, as DIS flow is also inconsistent on fast
    movers, whose pixels it would drop). Threshold: Otsu (on log residual when ``otsu_log``), at least
    ``max(residual_floor_px, residual_noise_k * median residual)``.
    """
    depth, K0, K1 = prior_t.depth, prior_t.intrinsic, prior_t2.intrinsic
    rel = relative_pose(prior_t, prior_t2)
    measured = (prior_t.depth_conf > 0) & (depth > camera.MIN_DEPTH)
    conf_ok = (prior_t.depth_conf >= cfg.min_depth_conf) & measured
    if cfg.edge_radius_px > 0 and cfg.hole_edges:
        # beside a sensor hole (filled, confidence 0) that spans the edge window, the depth range
        # within the edge radius is unknown: such holes open along depth edges (the sensor's shadow,
        # thin structures, a depth map registered off the image); isolated dropouts do not count
        conf_ok &= ~dilate(line_opening(~measured, cfg.edge_radius_px), cfg.edge_radius_px)
    consistent = jnp.ones_like(conf_ok)
    if cfg.occlusion and flow_back is not None:
        consistent = forward_backward_consistent(flow, flow_back, cfg.fb_alpha, cfg.fb_beta_px2)
    if cfg.refine_pose:
        rel = refine_relative_pose(depth, K0, K1, flow, rel, (conf_ok & consistent).astype(depth.dtype), cfg)
    if cfg.edge_radius_px > 0:
        residual, ego, ego_ok = depth_range_residual(flow, depth, conf_ok, K0, K1, rel, cfg.edge_radius_px)
    else:
        ego, ego_ok = ego_flow_rel(depth, K0, K1, rel)
        residual = jnp.linalg.norm(flow - ego, axis=-1)
    occluded = ~consistent if cfg.fb_occludes else jnp.zeros_like(consistent)
    if cfg.occlusion:
        occluded |= ~visible_in_partner(depth, K0, K1, rel, prior_t2.depth, cfg.zbuffer_rel_tol)
    valid = (ego_ok & conf_ok & _lands_inside(ego, cfg.border_px) & _lands_inside(flow, cfg.border_px)
             & ~occluded)
    residual = jnp.where(valid, residual, 0.0)
    sub = max(1, cfg.pose_stride)  # the median noise level from a grid subsample is plenty
    floor = jnp.maximum(cfg.residual_floor_px,
                        cfg.residual_noise_k * masked_median_low(residual[::sub, ::sub], valid[::sub, ::sub]))
    if cfg.otsu_log:
        t = jnp.exp(threshold_otsu(jnp.log(residual + 1e-3), cfg.otsu_bins, valid)) - 1e-3
    else:
        t = threshold_otsu(residual, cfg.otsu_bins, valid)
    thr = jnp.maximum(t, floor)
    return GeometryCue(mask=(residual > thr) & valid, residual=residual, valid=valid, threshold=thr, rel_pose=rel,
                       occluded=occluded, ego=ego)


def baseline_motion_cue(prior_t: FramePrior, prior_t2: FramePrior, flow, rel, cfg: MotionConfig = MotionConfig()):
    """MonST3R-style mask: ``|flow - ego_flow| > baseline_threshold_px`` with the ego flow under ``rel``."""
    ego, ok = ego_flow_rel(prior_t.depth, prior_t.intrinsic, prior_t2.intrinsic, rel)
    return ok & (jnp.linalg.norm(flow - ego, axis=-1) > cfg.baseline_threshold_px)
