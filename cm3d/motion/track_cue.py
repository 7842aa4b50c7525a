"""Track cue: landmark tracks that move against the rigidly explained static scene over several frames.

Why: a mover as slow as the prior's pose noise is lost in the two-frame residual flow, but its track
drifts off the scene every frame. Entry points: :func:`track_residuals`, :func:`moving_tracks`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from cm3d.motion.frames import MotionConfig
from cm3d.ops import robust, se3
from cm3d.ops.robust import masked_median_low, segment_median  # noqa: F401 (re-exported)
from cm3d.solvers.camera_motion import fit_camera_motion, reprojection


def track_residuals(points, poses, intrinsics, pose_idx, uv, valid, block, num_blocks: int,
                    cfg: MotionConfig = MotionConfig()):
    """Reprojection residuals of landmark tracks after each group's best rigid correction.

    points (L, 3) world landmarks from their seed pixel; poses (W, 4, 4) cam_to_world priors and
    intrinsics (W, 3, 3); pose_idx, uv, valid (L * T,) landmark-major observations (t = 0 the seed);
    block (L,) int in [0, num_blocks): the seeding block. Per group (block b, frame i) a rigid
    correction ``exp(delta) T`` is fitted by ``track_iters`` damped Gauss-Newton steps with
    Geman-McClure weights at the group's robust scale, so tracks on movers stay outliers (a rigid
    model, not an affine one: the parallax depends on depth, docs/motion.md). Returns (residual
    (L * T, 2) px, judged (L * T,) bool: t > 0, in front, in a group of >= ``track_min_obs``).
    """
    L = points.shape[0]
    Kn = pose_idx.shape[0]
    T = Kn // L
    W = poses.shape[0]
    G = num_blocks * W
    dt = poses.dtype
    pose_idx = jnp.asarray(pose_idx, jnp.int32)
    group = jnp.repeat(jnp.asarray(block, jnp.int32), T) * W + pose_idx
    point = jnp.repeat(jnp.arange(L), T)
    j = jnp.tile(jnp.arange(T), L)
    inv = se3.inverse(poses)[pose_idx]
    X = jnp.einsum("kij,kj->ki", inv[:, :3, :3], points[point].astype(dt)) + inv[:, :3, 3]
    Kk = intrinsics[pose_idx].astype(dt)
    uv = jnp.asarray(uv, dt)
    weight = (valid & (j > 0)).astype(dt)
    eye = jnp.broadcast_to(jnp.eye(4, dtype=dt), (G, 4, 4))
    _, _, _, ok0 = reprojection(eye, X, uv, Kk, weight, group)
    fit = jax.ops.segment_sum(ok0.astype(jnp.int32), group, G) >= cfg.track_min_obs

    def scale(rn, ok):
        return jnp.maximum(cfg.track_min_scale_px, robust.MAD_TO_SIGMA * segment_median(rn, group, ok, G))[group]

    corr = fit_camera_motion(X, uv, Kk, weight, eye, scale, cfg.track_iters, group, fit)
    r, _, _, ok = reprojection(corr, X, uv, Kk, weight, group)
    return jnp.where(ok[:, None], r, 0.0), ok & fit[group]


def moving_tracks(points, poses, intrinsics, pose_idx, uv, valid, block, num_blocks: int,
                  cfg: MotionConfig = MotionConfig()):
    """The track cue: (L,) bool, landmark tracks that move against the static scene.

    A track moves when its RMS residual (:func:`track_residuals`) exceeds
    ``max(track_min_px, median + track_n_mad 1.4826 MAD)`` over the judged tracks. Arguments as
    :func:`track_residuals`; all False when ``cfg.track_cue`` is off.
    """
    L = points.shape[0]
    if not cfg.track_cue:
        return jnp.zeros(L, bool)
    r, judged = track_residuals(points, poses, intrinsics, pose_idx, uv, valid, block, num_blocks, cfg)
    return moving_from_residuals(r, judged, L, cfg)


def moving_from_residuals(r, judged, num_tracks: int, cfg: MotionConfig = MotionConfig()):
    """The decision of :func:`moving_tracks` from :func:`track_residuals`' output: (L,) bool."""
    L = num_tracks
    T = judged.shape[0] // L
    jl = judged.reshape(L, T)
    n = jnp.sum(jl, -1)
    rms = jnp.sqrt(jnp.sum(jnp.where(jl, jnp.sum(r * r, -1).reshape(L, T), 0.0), -1) / jnp.maximum(n, 1))
    has = n > 0
    med = masked_median_low(rms, has)
    mad = masked_median_low(jnp.abs(rms - med), has)
    tau = jnp.maximum(cfg.track_min_px, med + cfg.track_n_mad * robust.MAD_TO_SIGMA * mad)
    return has & (rms > tau)
