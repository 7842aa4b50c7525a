"""Static landmarks: seeded on the most confident static pixel of each cell, lifted with the prior
depth, followed by the flow one frame at a time (:mod:`cm3d.trajectory`'s rules inside the step)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from cm3d import trajectory
from cm3d.ops import camera
from cm3d.pipeline.config import PipelineConfig
from cm3d.pipeline.state import Landmarks


def nearest_pixel(uv, h: int, w: int):
    """Nearest pixel (row, column) of uv (L, 2), clipped to the image."""
    r = jnp.clip(jnp.round(uv[:, 1]).astype(jnp.int32), 0, h - 1)
    c = jnp.clip(jnp.round(uv[:, 0]).astype(jnp.int32), 0, w - 1)
    return r, c


def advance_landmarks(lm_: Landmarks, flow, static, slot, cfg: PipelineConfig, image=None) -> Landmarks:
    """Follow live landmarks from the previous frame into slot ``slot`` with the previous flow
    (chained bilinear flow, as :func:`cm3d.trajectory.chain_tracks`), re-aligned to each landmark's
    seed patch (:func:`cm3d.trajectory.align_to_seed`) in this frame's image (h, w, 3) when given;
    record the observation. A landmark stops at the border or on a dynamic pixel."""
    h, w = static.shape
    T = cfg.track.track_length
    b = cfg.track.border * 0.5
    fl = trajectory.bilinear(flow[None], jnp.zeros(lm_.uv.shape[0], jnp.int32), lm_.uv)
    nxt = lm_.uv + fl
    if image is not None:
        nxt = trajectory.align_to_seed(lm_.patches, trajectory.gray(image), nxt, cfg.track)
    inside = (nxt[:, 0] >= b) & (nxt[:, 0] <= w - 1 - b) & (nxt[:, 1] >= b) & (nxt[:, 1] <= h - 1 - b)
    r, c = nearest_pixel(nxt, h, w)
    j = slot - lm_.seed
    good = lm_.alive & inside & static[r, c] & (j >= 1) & (j < T)
    put = (jnp.arange(T)[None, :] == j[:, None]) & good[:, None]
    return lm_.replace(uv=jnp.where(good[:, None], nxt, lm_.uv), alive=good,
                       obs_uv=jnp.where(put[..., None], nxt[:, None, :], lm_.obs_uv),
                       obs_valid=lm_.obs_valid | put)


def seed_landmarks(lm_: Landmarks, slot, image, depth, conf, static, K, pose, cfg: PipelineConfig) -> Landmarks:
    """Seed the block of slot ``slot``: the most confident static pixel of each cell, lifted to
    the world with the prior depth and the slot's initial pose (4, 4), with its patch of the
    frame's image (h, w, 3) for the re-alignment (:func:`cm3d.trajectory.seed_patches`)."""
    uv, ok = trajectory.select_landmark_pixels(depth, conf, static, cfg.track)
    C = uv.shape[0]
    r, c = nearest_pixel(uv, *depth.shape)
    d = depth[r, c]
    pw = camera.backproject(uv, d, K, pose)
    ok = ok & (d > 0)
    start = (slot // cfg.track.keyframe_every) * C
    T = cfg.track.track_length
    first = jnp.zeros((C, T, 2), uv.dtype).at[:, 0].set(uv)
    fvalid = jnp.zeros((C, T), bool).at[:, 0].set(ok)
    upd = lambda a, v: jax.lax.dynamic_update_slice_in_dim(a, v.astype(a.dtype), start, 0)  # noqa: E731
    patches = trajectory.seed_patches(trajectory.gray(image), uv, cfg.track)
    return lm_.replace(uv=upd(lm_.uv, uv), alive=upd(lm_.alive, ok), obs_uv=upd(lm_.obs_uv, first),
                       obs_valid=upd(lm_.obs_valid, fvalid), points=upd(lm_.points, pw),
                       patches=jax.tree.map(upd, lm_.patches, patches))


def landmark_observations(lm_: Landmarks, cfg: PipelineConfig) -> trajectory.Observations:
    """The window's projection observations (K = L x T), tracks shorter than ``min_track`` dropped."""
    valid = lm_.obs_valid & (jnp.sum(lm_.obs_valid, -1) >= cfg.track.min_track)[:, None]
    tracks = trajectory.Tracks(uv=lm_.obs_uv, valid=valid, frame=lm_.seed)
    return trajectory.track_observations(tracks)


