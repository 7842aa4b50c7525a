"""Landmarks, tracks and association for the factor graph; trajectory refinement (paper, Sec. 3.4).

Landmarks: one static, confident pixel per cell of each keyframe (:func:`select_landmark_pixels`),
tracked by chained flow or keypoint matches (:func:`chain_tracks`, :func:`chain_keypoint_tracks`),
lifted with the prior depth (:func:`lift_landmarks`). :func:`refine_trajectory` solves the paper's
graph, rejects outliers, solves again, re-orthonormalises and gates the result. Pure JAX with
fixed shapes (padded, masked). ``S`` frames of ``H x W``; poses cam_to_world.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from cm3d.ops import camera, robust, sim3
from cm3d.solvers import factors, lm


@dataclasses.dataclass(frozen=True)
class TrackConfig:
    """Landmark selection and tracking (shape-affecting fields are static).

    cell: one candidate per cell x cell pixels of a keyframe; keyframe_every: frames between
    keyframes; track_length: frames a track spans (keyframe included); conf_quantile: a pixel is
    high-confidence when its confidence reaches this quantile of the frame's static pixels;
    border: pixels kept clear of the image border; fb_max_px: forward-backward flow consistency
    (only with a backward flow); min_track: shortest track kept (frames); klt_radius: half-width of
    the patch with which a chained position is re-aligned to the track's first frame
    (:func:`align_to_seed`; 0: off), klt_iterations its Gauss-Newton steps, klt_max_px the most it may
    move the chained position, klt_rcond the relative conditioning below which a direction of the
    patch's structure tensor is left to the chain (the aperture problem of an edge).
    """

    cell: int = 16
    keyframe_every: int = 3
    track_length: int = 10
    conf_quantile: float = 0.5
    border: int = 4
    fb_max_px: float = 0.5
    min_track: int = 3
    klt_radius: int = 3
    klt_iterations: int = 4
    klt_max_px: float = 1.5
    klt_rcond: float = 0.1

    def __post_init__(self):
        if self.cell < 1 or self.keyframe_every < 1 or self.track_length < 2:
            raise ValueError("TrackConfig: cell, keyframe_every >= 1 and track_length >= 2 required")
        if not 0.0 <= self.conf_quantile < 1.0:
            raise ValueError("TrackConfig.conf_quantile: must be in [0, 1)")
        if self.klt_radius < 0 or self.klt_iterations < 0:
            raise ValueError("TrackConfig: klt_radius and klt_iterations must be >= 0")
        if not (self.klt_max_px > 0 and 0.0 <= self.klt_rcond <= 1.0):
            raise ValueError("TrackConfig: klt_max_px must be > 0 and klt_rcond in [0, 1]")


@dataclasses.dataclass(frozen=True)
class AssociationConfig:
    """Adaptive association threshold ``τ_dist = max(tau_min, d_scene · ratio)`` (scene units).

    With ``memory=`` in :func:`refine_trajectory`, a landmark lies on the remembered surface when its
    nearest map point is within ``max(τ_dist, radius_voxels · voxel)`` and its tangent-plane distance
    below ``τ_dist``; its point-to-plane prior has std ``plane_sigma_ratio · d_scene``.
    """

    tau_min: float = 0.01
    ratio: float = 0.01
    radius_voxels: float = 1.5
    plane_sigma_ratio: float = 0.005


@dataclasses.dataclass(frozen=True)
class RefineConfig:
    """Trajectory refinement: noise model, solver, outlier rejection (``rounds`` solves) and the gate.

    gate: keep the prior poses unless a likelihood-ratio test (poses held at the prior, landmarks
    re-estimated, against the refined poses) gives ``2 ΔC > χ²_q(6 (S − 1))``; gate_quantile: q.
    depth_factors: the pipeline's windows attach the prior depth at every observation
    (:attr:`Observations.depth`), which adds depth factors (RGB-D style): their log std
    starts at ``depth_sigma_init`` (loose); after each solve but the last, each frame's depth scale
    and the log std are re-fitted to the inliers (:func:`cm3d.solvers.factors.calibrate_depth`), the
    std at least ``depth_sigma_floor``; depth_edge_ratio: no depth is attached on a depth edge (the
    pixel's 3x3 neighbourhood spans a larger max / min ratio).
    """

    graph: factors.GraphConfig = factors.GraphConfig()
    solver: lm.LMOptions = lm.LMOptions(backward="none", max_iterations=50)
    outliers: factors.OutlierConfig = factors.OutlierConfig()
    rounds: int = 2
    gate: bool = True
    gate_quantile: float = 0.99
    depth_factors: bool = True
    depth_sigma_init: float = 0.05
    depth_sigma_floor: float = 0.002
    depth_edge_ratio: float = 1.15


@struct.dataclass
class Tracks:
    """Tracks of landmark candidates. uv: (L, T, 2) pixel positions; valid: (L, T) bool;
    frame: (L,) int32 keyframe index of the track's start (its t = 0); the track is at frame
    ``frame + t`` at step t."""

    uv: jnp.ndarray
    valid: jnp.ndarray
    frame: jnp.ndarray


@struct.dataclass
class Observations:
    """Padded projection observations: pose_idx, point_idx (K,) int32, uv (K, 2), valid (K,) bool,
    memory (K,) bool; depth: optional (K,) measured depth at the observation (0 = none)."""

    pose_idx: jnp.ndarray
    point_idx: jnp.ndarray
    uv: jnp.ndarray
    valid: jnp.ndarray
    memory: jnp.ndarray
    depth: jnp.ndarray | None = None


def keyframes(num_frames: int, cfg: TrackConfig) -> jnp.ndarray:
    """Keyframe indices (static count): 0, κ, 2κ, ... before the last frame."""
    return jnp.arange(0, max(num_frames - 1, 1), cfg.keyframe_every, dtype=jnp.int32)


def scene_scale(depth, valid) -> jnp.ndarray:
    """``d_scene``: median prior depth over valid pixels (scalar)."""
    d = depth.ravel()
    return robust.masked_median(d, valid.ravel() & (d > 0))


def eligible_pixels(depth, conf, static, cfg: TrackConfig = TrackConfig()):
    """(H, W) bool: static, valid depth, confidence > 0 (never a filled sensor hole) and >= the
    frame's ``conf_quantile`` over its static valid pixels, at least ``border`` px from the edge."""
    H, W = depth.shape
    ok = static & (depth > 0) & jnp.isfinite(depth) & jnp.isfinite(conf) & (conf > 0)
    thr = jnp.nanquantile(jnp.where(ok, conf, jnp.nan), cfg.conf_quantile)
    thr = jnp.where(jnp.isfinite(thr), thr, jnp.inf)
    v, u = jnp.meshgrid(jnp.arange(H), jnp.arange(W), indexing="ij")
    inside = (u >= cfg.border) & (u < W - cfg.border) & (v >= cfg.border) & (v < H - cfg.border)
    return ok & (conf >= thr) & inside


def select_landmark_pixels(depth, conf, static, cfg: TrackConfig = TrackConfig()):
    """Landmark candidates of one frame: the most confident eligible pixel (:func:`eligible_pixels`) of
    every cell. depth, conf, static: (H, W). Returns uv (C, 2), valid (C,), ``C = (H // cell) * (W // cell)``."""
    H, W = depth.shape
    c = cfg.cell
    h, w = H // c, W // c
    elig = eligible_pixels(depth, conf, static, cfg)
    score = jnp.where(elig, conf, -jnp.inf)[: h * c, : w * c]
    blocks = score.reshape(h, c, w, c).transpose(0, 2, 1, 3).reshape(h * w, c * c)
    best = jnp.argmax(blocks, -1)
    valid = jnp.take_along_axis(blocks, best[:, None], -1)[:, 0] > -jnp.inf
    by, bx = best // c, best % c
    cy, cx = jnp.divmod(jnp.arange(h * w), w)
    uv = jnp.stack([cx * c + bx, cy * c + by], -1).astype(depth.dtype)
    return uv, valid


def keypoint_seeds(uv, valid, depth, conf, static, cfg: TrackConfig = TrackConfig()):
    """Keypoints (N, 2) of a frame usable as landmark seeds: valid (N,) and on an eligible pixel
    (:func:`eligible_pixels`, rounded position)."""
    H, W = depth.shape
    elig = eligible_pixels(depth, conf, static, cfg)
    r = jnp.clip(jnp.round(uv[:, 1]).astype(jnp.int32), 0, H - 1)
    c = jnp.clip(jnp.round(uv[:, 0]).astype(jnp.int32), 0, W - 1)
    return valid & elig[r, c]


def bilinear(stack, idx, uv):
    """Bilinear samples of ``stack[idx]`` (stack (S, H, W, C), idx (L,)) at pixels uv (L, 2), clamped."""
    H, W = stack.shape[1:3]
    x = jnp.clip(uv[:, 0], 0.0, W - 1.0)
    y = jnp.clip(uv[:, 1], 0.0, H - 1.0)
    x0 = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, W - 2)
    y0 = jnp.clip(jnp.floor(y).astype(jnp.int32), 0, H - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    a, b = stack[idx, y0, x0], stack[idx, y0, x0 + 1]
    c, d = stack[idx, y0 + 1, x0], stack[idx, y0 + 1, x0 + 1]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def gray(images):
    """Luma in [0, 1] of uint8 RGB images (..., H, W, 3) -> (..., H, W, 1)."""
    w = jnp.asarray([0.299, 0.587, 0.114], jnp.float32) / 255.0
    return (images.astype(jnp.float32) @ w)[..., None]


@struct.dataclass
class SeedPatches:
    """What :func:`align_to_seed` needs of each track's first frame, taken once when it is seeded:
    the zero-mean patch (L, P) around the seed pixel, its image gradient (L, P, 2) and the inverse
    structure tensor (L, 2, 2) with the directions below ``klt_rcond`` of the largest eigenvalue
    zeroed (an edge's aperture problem); ``P = (2 klt_radius + 1)²``."""

    template: Any
    grad: Any
    hinv: Any

    @classmethod
    def empty(cls, L: int, cfg: "TrackConfig") -> "SeedPatches":
        P = (2 * cfg.klt_radius + 1) ** 2
        return cls(template=jnp.zeros((L, P), jnp.float32), grad=jnp.zeros((L, P, 2), jnp.float32),
                   hinv=jnp.zeros((L, 2, 2), jnp.float32))


def _patch_offsets(r: int, dtype):
    g = jnp.arange(-r, r + 1, dtype=dtype)
    return jnp.stack(jnp.meshgrid(g, g, indexing="xy"), -1).reshape(-1, 2)  # (P, 2)


def _zero_mean(x):
    return x - jnp.mean(x, -1, keepdims=True)


def seed_patches(image, seed_uv, cfg: TrackConfig = TrackConfig()) -> SeedPatches:
    """:class:`SeedPatches` of the seed pixels ``seed_uv`` (L, 2) in the gray image (H, W, 1) they were
    seeded in (central differences for the gradient)."""
    L = seed_uv.shape[0]
    offs = _patch_offsets(cfg.klt_radius, seed_uv.dtype)
    P = offs.shape[0]
    zero = jnp.zeros(L * P, jnp.int32)

    def at(d):
        return bilinear(image[None], zero, (seed_uv[:, None] + offs + d).reshape(-1, 2))[:, 0].reshape(L, P)

    one = jnp.eye(2, dtype=seed_uv.dtype)
    grad = jnp.stack([(at(one[k]) - at(-one[k])) * 0.5 for k in range(2)], -1)  # (L, P, 2)
    lam, V = jnp.linalg.eigh(jnp.einsum("lpi,lpj->lij", grad, grad))
    inv = jnp.where(lam >= cfg.klt_rcond * lam[:, -1:], 1.0 / jnp.maximum(lam, 1e-12), 0.0)
    return SeedPatches(template=_zero_mean(at(0.0)), grad=grad, hinv=jnp.einsum("lik,lk,ljk->lij", V, inv, V))


def align_to_seed(patches: SeedPatches, cur, uv, cfg: TrackConfig = TrackConfig()):
    """Re-align chained track positions to their first frame: translation-only inverse-compositional
    Lucas-Kanade of each track's seed patch (:func:`seed_patches`) against the gray image ``cur``
    (H, W, 1), from the chained positions ``uv`` (L, 2).

    Chaining per-frame flow adds each frame's error, and dense flow shrinks the small motions
    between consecutive frames (DIS moves a track 0.88x as far as the true flow over 10 frames of a
    slow pan on the held-out world, 0.96x re-aligned here). Returns the positions (L, 2): the
    aligned one where it lowers the patch's error and moves at most ``cfg.klt_max_px``, else
    ``uv``. Along a direction the patch hardly constrains (structure-tensor eigenvalue below
    ``cfg.klt_rcond`` of the largest: an edge) the chained position is kept."""
    r = cfg.klt_radius
    if r <= 0:
        return uv
    L = uv.shape[0]
    n = 2 * r + 2
    img = jnp.pad(cur[..., 0], r + 1, mode="edge")  # edge values: bilinear's clamping outside the image

    def residual(p):
        """Zero-mean bilinear patch around p minus the template: the patch's pixels share p's
        fraction, so one (2r + 2)² block per track is gathered and interpolated."""
        i0 = jnp.floor(p)
        f = (p - i0)[:, None, None, :]
        start = jnp.clip(i0.astype(jnp.int32) + 1, 0, jnp.asarray(img.shape[::-1]) - n)  # padded: +r+1, -r
        block = jax.vmap(lambda s: jax.lax.dynamic_slice(img, (s[1], s[0]), (n, n)))(start)
        fx, fy = f[..., 0], f[..., 1]
        top = block[:, :-1, :-1] * (1 - fx) + block[:, :-1, 1:] * fx
        bottom = block[:, 1:, :-1] * (1 - fx) + block[:, 1:, 1:] * fx
        return _zero_mean((top * (1 - fy) + bottom * fy).reshape(L, -1)) - patches.template

    def gn(_, carry):
        p, res = carry
        p = p - jnp.einsum("lij,lj->li", patches.hinv, jnp.einsum("lpi,lp->li", patches.grad, res))
        return p, residual(p)

    res0 = residual(uv)
    p, res = jax.lax.fori_loop(0, cfg.klt_iterations, gn, (uv, res0))
    better = jnp.sum(res ** 2, -1) < jnp.sum(res0 ** 2, -1)
    ok = better & (jnp.linalg.norm(p - uv, axis=-1) <= cfg.klt_max_px) & jnp.all(jnp.isfinite(p), -1)
    return jnp.where(ok[:, None], p, uv)


def chain_tracks(flow, static, seeds_uv, seeds_valid, seed_frames, cfg: TrackConfig = TrackConfig(),
                 flow_bwd=None) -> Tracks:
    """Follow seed pixels through the sequence by chaining forward flow -> :class:`Tracks` (F * C tracks).

    flow: (S−1, H, W, 2) forward flow; static: (S, H, W) bool; seeds_uv: (F, C, 2), seeds_valid: (F, C)
    at keyframes seed_frames (F,); flow_bwd: optional backward flow for a forward-backward check. A
    track stops out of the image, on a dynamic pixel, on a failed check or at the last frame.
    """
    S, H, W = static.shape
    F_, C = seeds_valid.shape
    uv0 = seeds_uv.reshape(F_ * C, 2).astype(jnp.result_type(seeds_uv.dtype, flow.dtype))
    ok0 = seeds_valid.reshape(-1)
    frame = jnp.repeat(seed_frames.astype(jnp.int32), C)
    b = cfg.border * 0.5

    def step(carry, t):
        uv, ok = carry
        f = frame + t  # frame of uv
        fi = jnp.clip(f, 0, S - 2)
        fl = bilinear(flow, fi, uv).astype(uv.dtype)
        nxt = uv + fl
        inside = (nxt[:, 0] >= b) & (nxt[:, 0] <= W - 1 - b) & (nxt[:, 1] >= b) & (nxt[:, 1] <= H - 1 - b)
        ri = jnp.clip(jnp.round(nxt[:, 1]).astype(jnp.int32), 0, H - 1)
        ci = jnp.clip(jnp.round(nxt[:, 0]).astype(jnp.int32), 0, W - 1)
        stat = static[jnp.clip(f + 1, 0, S - 1), ri, ci]
        good = ok & (f + 1 < S) & inside & stat
        if flow_bwd is not None:
            back = bilinear(flow_bwd, fi, nxt).astype(uv.dtype)
            good &= jnp.linalg.norm(nxt + back - uv, axis=-1) <= cfg.fb_max_px
        nxt = jnp.where(good[:, None], nxt, uv)
        return (nxt, good), (nxt, good)

    _, (uvs, oks) = jax.lax.scan(step, (uv0, ok0), jnp.arange(cfg.track_length - 1))
    uv = jnp.concatenate([uv0[None], uvs], 0).transpose(1, 0, 2)
    valid = jnp.concatenate([ok0[None], oks], 0).T
    length = jnp.sum(valid, -1)
    valid &= (length >= cfg.min_track)[:, None]
    return Tracks(uv=uv, valid=valid, frame=frame)


def chain_keypoint_tracks(uv0, uv1, mvalid, static, seeds_uv, seeds_valid, seed_frames,
                          cfg: TrackConfig = TrackConfig(), radius: float = 1.0) -> Tracks:
    """Tracks from chained keypoint matches (:func:`cm3d.ops.keypoints.sequence_matches`).

    uv0, uv1: (S−1, N, 2) matches of frames t -> t+1, mvalid: (S−1, N); seeds as :func:`chain_tracks`.
    A track continues with the match whose ``uv0`` is within ``radius`` px of its position; it stops
    as :func:`chain_tracks` does.
    """
    S, H, W = static.shape
    F_, C = seeds_valid.shape
    pos0 = seeds_uv.reshape(F_ * C, 2).astype(jnp.result_type(seeds_uv.dtype, uv0.dtype))
    ok0 = seeds_valid.reshape(-1)
    frame = jnp.repeat(seed_frames.astype(jnp.int32), C)

    def step(carry, t):
        pos, ok = carry
        f = frame + t
        fi = jnp.clip(f, 0, S - 2)
        d2 = jnp.sum((uv0[fi] - pos[:, None, :]) ** 2, -1)
        d2 = jnp.where(mvalid[fi], d2, jnp.inf)
        j = jnp.argmin(d2, -1)
        near = jnp.take_along_axis(d2, j[:, None], -1)[:, 0] <= radius * radius
        nxt = uv1[fi, j].astype(pos.dtype)
        inside = (nxt[:, 0] >= 0) & (nxt[:, 0] <= W - 1) & (nxt[:, 1] >= 0) & (nxt[:, 1] <= H - 1)
        ri = jnp.clip(jnp.round(nxt[:, 1]).astype(jnp.int32), 0, H - 1)
        ci = jnp.clip(jnp.round(nxt[:, 0]).astype(jnp.int32), 0, W - 1)
        good = ok & (f + 1 < S) & near & inside & static[jnp.clip(f + 1, 0, S - 1), ri, ci]
        nxt = jnp.where(good[:, None], nxt, pos)
        return (nxt, good), (nxt, good)

    _, (ps, oks) = jax.lax.scan(step, (pos0, ok0), jnp.arange(cfg.track_length - 1))
    uv = jnp.concatenate([pos0[None], ps], 0).transpose(1, 0, 2)
    valid = jnp.concatenate([ok0[None], oks], 0).T
    valid &= (jnp.sum(valid, -1) >= cfg.min_track)[:, None]
    return Tracks(uv=uv, valid=valid, frame=frame)


def lift_landmarks(tracks: Tracks, depth, intrinsics, poses):
    """World landmarks (L, 3) from the prior depth at each track's first pixel, its keyframe's
    intrinsics and prior pose; and which are valid (L,)."""
    uv = tracks.uv[:, 0]
    f = tracks.frame
    r = jnp.round(uv[:, 1]).astype(jnp.int32)
    c = jnp.round(uv[:, 0]).astype(jnp.int32)
    d = depth[f, r, c]
    pw = camera.backproject(uv[:, None], d[:, None], intrinsics[f], poses[f])[:, 0]
    return pw, tracks.valid[:, 0] & (d > 0)


def track_observations(tracks: Tracks, memory=None) -> Observations:
    """Flatten tracks into padded observations (K = L * T): pose = frame + t, point = track id."""
    L, T = tracks.valid.shape
    t = jnp.arange(T, dtype=jnp.int32)
    pose = (tracks.frame[:, None] + t[None]).reshape(-1)
    point = jnp.repeat(jnp.arange(L, dtype=jnp.int32), T)
    mem = jnp.zeros(L, bool) if memory is None else memory
    valid = tracks.valid.reshape(-1)
    return Observations(pose_idx=jnp.where(valid, pose, 0), point_idx=point,
                        uv=tracks.uv.reshape(-1, 2), valid=valid, memory=jnp.repeat(mem, T))


def association_threshold(d_scene, cfg: AssociationConfig = AssociationConfig()):
    """``τ_dist = max(τ_min, d_scene · α)``."""
    return jnp.maximum(cfg.tau_min, d_scene * cfg.ratio)


def associate_landmarks(points, valid, bank, bank_valid, d_scene, cfg: AssociationConfig = AssociationConfig()):
    """Nearest bank landmark within ``τ_dist`` of each candidate.

    points: (L, 3), valid: (L,); bank: (B, 3) stored landmarks (memory), bank_valid: (B,).
    Returns (index (L,) int32 into the bank, matched (L,) bool, τ_dist).
    """
    d2 = jnp.sum((points[:, None, :] - bank[None, :, :]) ** 2, -1)
    d2 = jnp.where(bank_valid[None, :], d2, jnp.inf)
    idx = jnp.argmin(d2, -1).astype(jnp.int32)
    tau = association_threshold(d_scene, cfg)
    best = jnp.take_along_axis(d2, idx[:, None], -1)[:, 0]
    return idx, valid & (best <= tau * tau), tau


def add_memory_landmarks(points, valid, bank, bank_valid, d_scene, cfg: AssociationConfig = AssociationConfig()):
    """Associate candidates with the memory bank; matched ones take the stored 3D position -> (points, memory flags)."""
    idx, matched, _ = associate_landmarks(points, valid, bank, bank_valid, d_scene, cfg)
    return jnp.where(matched[:, None], bank[idx], points), matched


@struct.dataclass
class MemorySurface:
    """A remembered map in the window's frame for :func:`refine_trajectory`: points (P, 3), unit
    normals (P, 3), valid (P,), voxel () its voxel size, d_scene () the window's scene depth."""

    points: jnp.ndarray
    normals: jnp.ndarray
    valid: jnp.ndarray
    voxel: jnp.ndarray
    d_scene: jnp.ndarray


def associate_surface(points, valid, mem: MemorySurface, cfg: AssociationConfig = AssociationConfig()):
    """Landmarks (L, 3) on the remembered surface (see :class:`AssociationConfig`): (index (L,) of
    the nearest map point, matched (L,) bool, point-to-plane distance (L,))."""
    d2 = jnp.sum((points[:, None, :] - mem.points[None, :, :]) ** 2, -1)
    d2 = jnp.where(mem.valid[None, :], d2, jnp.inf)
    idx = jnp.argmin(d2, -1).astype(jnp.int32)
    best = jnp.take_along_axis(d2, idx[:, None], -1)[:, 0]
    tau = association_threshold(mem.d_scene, cfg)
    radius = jnp.maximum(tau, cfg.radius_voxels * mem.voxel)
    plane = jnp.abs(jnp.sum(mem.normals[idx] * (points - mem.points[idx]), -1))
    n_ok = jnp.sum(mem.normals[idx] ** 2, -1) > 0.5
    matched = valid & (best <= radius * radius) & (plane <= tau) & n_ok & jnp.all(jnp.isfinite(points), -1)
    return idx, matched, plane


def align_to_surface(points, valid, mem: MemorySurface, cfg: AssociationConfig = AssociationConfig(),
                     iterations: int = 3):
    """The similarity (4, 4) that puts landmarks (L, 3) on the remembered surface (point-to-plane
    Gauss-Newton, Cauchy-weighted at ``τ_dist``, re-associated each iteration; identity below 12).
    Why: a recalled map is placed from the window's prior-posed cloud; this removes the prior's share."""
    tau = association_threshold(mem.d_scene, cfg)
    radius = jnp.maximum(tau, cfg.radius_voxels * mem.voxel)
    c = jnp.sum(jnp.where(valid[:, None], points, 0.0), 0) / jnp.maximum(jnp.sum(valid), 1)

    def body(_, T):
        p = points @ T[:3, :3].T + T[:3, 3]
        d2 = jnp.where(mem.valid[None, :], jnp.sum((p[:, None, :] - mem.points[None, :, :]) ** 2, -1), jnp.inf)
        idx = jnp.argmin(d2, -1)
        near = valid & (jnp.min(d2, -1) <= radius * radius) & (jnp.sum(mem.normals[idx] ** 2, -1) > 0.5)
        n, q = mem.normals[idx], mem.points[idx]
        r = jnp.sum(n * (p - q), -1)
        w = near / (1.0 + (r / tau) ** 2)
        # rotation about the landmarks' centre, translation, scale about the centre
        J = jnp.concatenate([jnp.cross(p - c, n), n, jnp.sum(n * (p - c), -1, keepdims=True)], -1)
        H = jnp.einsum("l,li,lj->ij", w, J, J) + 1e-9 * jnp.eye(7)
        dx = -jnp.linalg.solve(H, jnp.einsum("l,li,l->i", w, J, r))
        ok = (jnp.sum(near) >= 12) & jnp.all(jnp.isfinite(dx))
        dx = jnp.where(ok, dx, 0.0)
        th = jnp.linalg.norm(dx[:3])
        k = dx[:3] / jnp.maximum(th, 1e-12)
        Kx = jnp.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]], points.dtype)
        dR = jnp.eye(3, dtype=points.dtype) + jnp.sin(th) * Kx + (1 - jnp.cos(th)) * Kx @ Kx
        sc = jnp.exp(dx[6])
        D = jnp.eye(4, dtype=points.dtype).at[:3, :3].set(sc * dR).at[:3, 3].set(c - sc * dR @ c + dx[3:6])
        return D @ T

    return jax.lax.fori_loop(0, iterations, body, jnp.eye(4, dtype=points.dtype))


def move_surface(mem: MemorySurface, T) -> MemorySurface:
    """The surface moved by the inverse of the similarity ``T = [s R, t]`` (landmarks ``T p`` on it
    <=> ``p`` on the moved one)."""
    s, R, t = sim3.scale(T), sim3.rotation(T), T[:3, 3]
    return mem.replace(points=(mem.points - t) @ R / s, normals=mem.normals @ R, voxel=mem.voxel / s)


def memory_point_prior(graph: factors.FactorGraph, points, point_valid, mem: MemorySurface,
                       cfg: AssociationConfig = AssociationConfig(), sigma=None):
    """``graph`` with point-to-plane priors on the landmarks (L, 3) on the remembered surface, their
    projections flagged as memory (``σ² ← α σ²``); ``sigma`` default ``cfg.plane_sigma_ratio · d_scene``.
    Returns (graph, matched (L,))."""
    idx, matched, _ = associate_surface(points, point_valid, mem, cfg)
    n = mem.normals[idx]
    sigma = cfg.plane_sigma_ratio * mem.d_scene if sigma is None else sigma
    sigma = jnp.maximum(sigma, 1e-9)
    S = jnp.zeros((points.shape[0], 3, 3), points.dtype).at[:, 0, :].set(n / sigma)
    g = factors.with_point_prior(graph, mem.points[idx], S, matched)
    f = g.projection
    return g.replace(projection=f.replace(memory=f.memory | matched[f.point_idx])), matched


@struct.dataclass
class Refinement:
    """Result of :func:`refine_trajectory`: poses (S, 4, 4) (after the gate), points (L, 3), the final
    LM result, inlier mask (K,), outlier threshold (px), the gate's decision ``refined`` with its
    statistic and threshold, ``refined_poses`` whatever the gate said, the final ``graph``, ``memory``
    (L,) landmarks held on the remembered surface, ``alignment`` (4, 4) the surface re-fit."""

    poses: jnp.ndarray
    points: jnp.ndarray
    result: lm.LMResult
    inlier: jnp.ndarray
    tau_px: jnp.ndarray
    refined: jnp.ndarray
    gate_stat: jnp.ndarray
    gate_threshold: jnp.ndarray
    refined_poses: jnp.ndarray
    graph: factors.FactorGraph | None = None
    memory: jnp.ndarray | None = None
    alignment: jnp.ndarray | None = None


def refine_trajectory(prior_poses, intrinsics, points, obs: Observations,
                      cfg: RefineConfig = RefineConfig(), pose_valid=None, memory: MemorySurface | None = None,
                      assoc: AssociationConfig = AssociationConfig(), realign=False) -> Refinement:
    """The paper's factor-graph refinement of the prior poses (S, 4, 4) with landmarks (L, 3).

    ``cfg.rounds`` solves with outlier rejection between them, SVD re-orthonormalisation, then
    (``cfg.gate``) the prior poses are kept unless the refinement is significant (:class:`RefineConfig`).
    The solves are stages of one ``lax.scan`` (one solver in the compiled program).
    ``memory``: a remembered surface in the poses' frame; after the first solve, landmarks on it get
    point-to-plane priors (:func:`memory_point_prior`), which tie the window's poses to the map.
    ``realign``: first re-fit the surface's placement to the landmarks (:func:`align_to_surface`),
    returned as ``Refinement.alignment``.
    """
    graph = factors.build_graph(prior_poses, intrinsics, obs.pose_idx, obs.point_idx, obs.uv,
                                obs.valid, obs.memory, pose_valid, cfg.graph, obs.depth,
                                None if obs.depth is None else cfg.depth_sigma_init)
    L = points.shape[0]
    if memory is not None:  # the same pytree structure in every stage of the scan: empty priors first
        graph = factors.with_point_prior(graph, jnp.zeros_like(points), jnp.zeros((L, 3, 3), points.dtype),
                                         jnp.zeros(L, bool))
    pvalid = jnp.zeros(L, bool).at[obs.point_idx].max(obs.valid)
    dt = prior_poses.dtype
    rounds = cfg.rounds
    gate_stage = rounds if cfg.gate else -1
    x0 = factors.Variables(prior_poses, points)

    def stage(carry, k):
        graph, x, inlier, tau, align = carry
        gate = k == gate_stage
        g = graph.replace(pose_fixed=jnp.where(gate, jnp.ones_like(graph.pose_fixed), graph.pose_fixed))
        init = factors.Variables(jnp.where(gate, prior_poses, x.poses), x.points)
        res = lm.solve(g, init, cfg.solver)
        reject = k < rounds - 1
        g2, inl2, tau2 = factors.reject_outliers(graph, res.params, cfg.outliers)
        if obs.depth is not None:  # the depth factors' per-frame scale and noise from this solve's inliers
            g2 = factors.calibrate_depth(g2, res.params, inl2, cfg.depth_sigma_floor)
        A2 = align
        if memory is not None:  # associate once, after the first solve (lax.cond: skipped in the other stages)
            def attach(g2):
                kept = jnp.zeros(L, bool).at[g2.projection.point_idx].max(g2.projection.weight > 0)
                A2 = jax.lax.cond(realign, lambda: align_to_surface(res.params.points, pvalid & kept, memory, assoc),
                                  lambda: align)
                g2, _ = memory_point_prior(g2, res.params.points, pvalid & kept, move_surface(memory, A2), assoc)
                return g2, A2

            g2, A2 = jax.lax.cond(reject, attach, lambda g2: (g2, align), g2)
        pick = lambda a, b: jax.tree.map(lambda u, v: jnp.where(reject, u, v), a, b)  # noqa: E731
        graph, inlier, tau, align = pick((g2, inl2, tau2, A2), (graph, inlier, tau, align))
        x = jax.tree.map(lambda u, v: jnp.where(gate, u, v), x, res.params)
        return (graph, x, inlier, tau, align), res

    n_stages = rounds + (1 if cfg.gate else 0)
    carry0 = (graph, x0, obs.valid, jnp.zeros((), dt), jnp.eye(4, dtype=dt))
    (graph, x, inlier, tau, align), results = jax.lax.scan(stage, carry0, jnp.arange(n_stages))
    res = jax.tree.map(lambda a: a[rounds - 1], results)
    refined_poses = factors.orthonormalize_poses(res.params.poses)
    stat = thr = jnp.zeros((), dt)
    use = jnp.ones((), bool)
    points_out = res.params.points
    if cfg.gate:
        fixed = jax.tree.map(lambda a: a[rounds], results)
        w = graph.projection.weight > 0
        stat = 2.0 * (fixed.cost - res.cost)
        n_pose = jnp.sum(jnp.zeros(prior_poses.shape[0], jnp.int32).at[obs.pose_idx].max(w.astype(jnp.int32)))
        thr = robust.chi2_quantile(cfg.gate_quantile, 6.0 * jnp.maximum(n_pose - 1, 1).astype(dt))
        use = stat > thr
        points_out = jnp.where(use, res.params.points, fixed.params.points)
    poses = jnp.where(use, refined_poses, prior_poses)
    mem = graph.point_prior.weight > 0 if memory is not None else jnp.zeros(L, bool)
    return Refinement(poses=poses, points=points_out, result=res, inlier=inlier, tau_px=tau, refined=use,
                      gate_stat=stat, gate_threshold=thr, refined_poses=refined_poses, graph=graph, memory=mem,
                      alignment=align)


def prepare_landmarks(depth, conf, static, intrinsics, prior_poses, flow, flow_bwd=None,
                      track_cfg: TrackConfig = TrackConfig(), memory_bank=None, memory_valid=None,
                      assoc_cfg: AssociationConfig = AssociationConfig()):
    """Keyframe landmarks from static, confident pixels; flow tracks; optional memory association.
    depth, conf, static (S, H, W); intrinsics (S, 3, 3); prior_poses (S, 4, 4); flow, flow_bwd
    (S−1, H, W, 2); memory_bank (B, 3). Returns (points (L, 3), Observations, Tracks, d_scene)."""
    S = depth.shape[0]
    kf = keyframes(S, track_cfg)
    uv, ok = jax.vmap(lambda d, c, m: select_landmark_pixels(d, c, m, track_cfg))(depth[kf], conf[kf], static[kf])
    tracks = chain_tracks(flow, static, uv, ok, kf, track_cfg, flow_bwd)
    points, pvalid = lift_landmarks(tracks, depth, intrinsics, prior_poses)
    tracks = tracks.replace(valid=tracks.valid & pvalid[:, None])
    d_scene = scene_scale(depth, static)
    memory = None
    if memory_bank is not None:
        bv = jnp.ones(memory_bank.shape[0], bool) if memory_valid is None else memory_valid
        points, memory = add_memory_landmarks(points, tracks.valid[:, 0], memory_bank, bv, d_scene, assoc_cfg)
    return points, track_observations(tracks, memory), tracks, d_scene
