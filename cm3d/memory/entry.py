"""Map entries: a sequence's static cloud, keyframe descriptors and 3D keypoints, voxelised to the
bank's capacities (:func:`build_entry`), in the sequence's own frame and scale."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from cm3d.memory.config import MemoryConfig
from cm3d.ops import camera, descriptors
from cm3d.ops.neighbors import estimate_normals
from cm3d.ops.voxel import adaptive_voxel_size, voxel_downsample


@struct.dataclass
class Keypoints:
    """3D keypoints of a sequence or map in its own frame: points (N, 3), unit local descriptors
    desc (N, Dk), valid (N,)."""

    points: jax.Array
    desc: jax.Array
    valid: jax.Array


def lift_keypoints(uv, desc, valid, depth, K, cam_to_world, capacity: int) -> Keypoints:
    """Detected keypoints lifted to 3D with the prior depth and poses, up to ``capacity``.

    uv (S, N, 2) pixels, desc (S, N, Dk), valid (S, N) (per frame, strongest first: e.g.
    :func:`cm3d.ops.keypoints.detect_sequence` on static pixels); depth (S, H, W); K (S, 3, 3);
    cam_to_world (S, 4, 4). A keypoint is kept when the depth at its pixel is positive and finite;
    the kept ones are taken round robin over frames (each frame's strongest first), so every
    frame is represented. Returns :class:`Keypoints` with N = ``capacity``.
    """
    uv, desc, valid, depth, K, cam_to_world = (jnp.asarray(a) for a in (uv, desc, valid, depth, K, cam_to_world))
    S, N = valid.shape
    H, W = depth.shape[1:]
    ui = jnp.clip(jnp.round(uv[..., 0]).astype(jnp.int32), 0, W - 1)
    vi = jnp.clip(jnp.round(uv[..., 1]).astype(jnp.int32), 0, H - 1)
    d = depth[jnp.arange(S)[:, None], vi, ui]
    ok = valid & (d > 0) & jnp.isfinite(d)
    world = camera.backproject(uv, jnp.where(ok, d, 0.0), K, cam_to_world)
    rank = jnp.cumsum(ok, axis=1) - 1
    priority = jnp.where(ok, rank * S + jnp.arange(S)[:, None], S * N + 1).reshape(-1)
    order = jnp.argsort(priority, stable=True)
    order = order[jnp.arange(capacity) % (S * N)]
    kv = ok.reshape(-1)[order] & (jnp.arange(capacity) < S * N)
    return Keypoints(points=jnp.where(kv[:, None], world.reshape(-1, 3)[order], 0.0),
                     desc=jnp.where(kv[:, None], desc.reshape(S * N, -1)[order], 0.0), valid=kv)


def fit_keypoints(kp: "Keypoints | None", capacity: int, dim: int) -> Keypoints:
    """Keypoints padded (invalid) or cut to ``capacity`` (static shapes); None gives none."""
    if kp is None:
        return Keypoints(jnp.zeros((capacity, 3), jnp.float32), jnp.zeros((capacity, dim), jnp.float32),
                         jnp.zeros((capacity,), bool))
    n = kp.valid.shape[-1]
    if kp.desc.shape[-1] != dim:
        raise ValueError(f"keypoint descriptors: expected dimension {dim}, got {kp.desc.shape[-1]}")
    if n >= capacity:
        return Keypoints(kp.points[:capacity].astype(jnp.float32), kp.desc[:capacity].astype(jnp.float32),
                         kp.valid[:capacity].astype(bool))
    pad = capacity - n
    return Keypoints(jnp.pad(jnp.asarray(kp.points, jnp.float32), ((0, pad), (0, 0))),
                     jnp.pad(jnp.asarray(kp.desc, jnp.float32), ((0, pad), (0, 0))),
                     jnp.pad(jnp.asarray(kp.valid, bool), (0, pad)))


def evenly_spread(valid, capacity: int):
    """At most ``capacity`` of the valid items of ``valid`` (N,): all of them (in index order) when they
    fit, else an evenly spread subset (first and last included), so coverage is kept. Returns
    (indices (capacity,), kept (capacity,) bool)."""
    order = jnp.argsort(~valid, stable=True)  # the valid items first, in index order
    n = jnp.sum(valid)
    pos = jnp.round(jnp.linspace(0.0, 1.0, capacity) * jnp.maximum(n - 1, 0)).astype(jnp.int32)
    idx = jnp.where(n > capacity, order[pos], order[jnp.arange(capacity) % valid.shape[0]])
    return idx, jnp.arange(capacity) < jnp.minimum(n, capacity)


@struct.dataclass
class MapEntry:
    """One map's contents, already at the bank's capacities (P points, K keyframes); ``keypoints`` and
    ``floor_keypoints`` may have any capacity (padded or cut to the bank's when stored) or be None."""

    points: jax.Array  # (P, 3)
    normals: jax.Array  # (P, 3)
    conf: jax.Array  # (P,)
    colors: jax.Array  # (P, 3) uint8
    point_valid: jax.Array  # (P,)
    kf_desc: jax.Array  # (K, D2)
    kf_valid: jax.Array  # (K,)
    cloud_desc: jax.Array  # (D3,)
    voxel_size: jax.Array  # ()
    keypoints: Keypoints | None = None  # (Nq,) 3D keypoints in the entry's frame
    floor_keypoints: Keypoints | None = None  # (Fq,) floor orthophoto keypoints (ops.keypoints.floor_features)


@struct.dataclass
class SequenceCloud:
    """The static, confident part of one sequence in its own (prior) frame: points (N, 3),
    colors (N, 3) uint8, conf (N,), valid (N,); N = frames x pixels / stride^2."""

    points: jax.Array
    colors: jax.Array
    conf: jax.Array
    valid: jax.Array


def sequence_cloud(depth, conf, K, cam_to_world, images, static, cfg: MemoryConfig) -> SequenceCloud:
    """Lift every ``cfg.pixel_stride``-th static pixel whose confidence is above the sequence's
    ``cfg.min_conf_quantile`` quantile (depth > 0, confidence > 0: a filled sensor hole is never
    lifted) to the world: (S, H, W) inputs."""
    st = cfg.pixel_stride
    d = depth[:, ::st, ::st]
    c = conf[:, ::st, ::st]
    Ks = K.at[..., :2, :].divide(st)  # pixel (u, v) of the strided grid is (st u, st v) in full
    pts = camera.unproject(d, Ks, cam_to_world)
    ok = static[:, ::st, ::st] & (d > 0) & jnp.isfinite(d) & (c > 0)
    thr = jnp.nanquantile(jnp.where(ok, c, jnp.nan), cfg.min_conf_quantile)
    ok = ok & (c >= thr)
    return SequenceCloud(points=pts.reshape(-1, 3), colors=images[:, ::st, ::st].reshape(-1, 3),
                         conf=c.reshape(-1), valid=ok.reshape(-1))


def cloud_descriptor(points, valid, cfg: MemoryConfig):
    """The map's 3D global descriptor (cfg.cloud_dim,) of a voxelised cloud, per ``cfg.descriptor_3d``:
    the handcrafted similarity-invariant histogram or the learned PointNet++ encoder (shipped weights)."""
    if cfg.descriptor_3d == "pointnet2":
        from cm3d.models import pointnet2  # imported on use: the handcrafted default needs no model

        return pointnet2.cloud_descriptor(points, valid)
    return descriptors.cloud_descriptor(points, valid)


def downsample_to_capacity(points, valid, features, voxel_size, capacity: int):
    """Voxel downsample, growing the voxel by 1.25x until the occupied voxels fit ``capacity``."""
    def grid(vs):
        return voxel_downsample(points, vs, valid, features, capacity=capacity)

    def cond(c):
        vs, i = c
        return (grid(vs).count > capacity) & (i < 12)

    vs, _ = jax.lax.while_loop(cond, lambda c: (c[0] * 1.25, c[1] + 1), (jnp.asarray(voxel_size, jnp.float32), 0))
    return grid(vs), vs


def _entry_from_points(points, colors, conf, valid, kf_desc, kf_valid, voxel_size, cfg: MemoryConfig,
                       min_support: float = 0.0) -> MapEntry:
    """Downsample to the bank's capacity and describe (see :func:`build_entry`)."""
    feats = jnp.concatenate([colors.astype(jnp.float32), conf[:, None]], axis=1)
    vox, vs = downsample_to_capacity(points, valid, feats, voxel_size, cfg.max_points)
    if not (isinstance(min_support, (int, float)) and min_support <= 0):  # may be traced (0: nothing dropped)
        # voxels that few samples fell into: stray points, not surface (build_entry)
        med = jnp.nanmedian(jnp.where(vox.valid, vox.weight, jnp.nan))
        keep = vox.valid & (vox.weight >= min_support * med)
        on = jnp.asarray(min_support) > 0
        vox = vox.replace(points=jnp.where(on & ~keep[:, None], 0.0, vox.points), valid=jnp.where(on, keep, vox.valid))
    normals = estimate_normals(vox.points, vox.valid, k=16, radius=cfg.normal_radius)
    return MapEntry(points=vox.points, normals=jnp.where(vox.valid[:, None], normals, 0.0),
                    conf=vox.features[:, 3], colors=jnp.clip(jnp.round(vox.features[:, :3]), 0, 255).astype(jnp.uint8),
                    point_valid=vox.valid, kf_desc=kf_desc, kf_valid=kf_valid,
                    cloud_desc=cloud_descriptor(vox.points, vox.valid, cfg), voxel_size=vs)


def _clean_keypoints(kp: Keypoints | None) -> Keypoints | None:
    """Keypoints with non-finite points or descriptors marked invalid (and zeroed), float32."""
    if kp is None:
        return None
    ok = jnp.asarray(kp.valid, bool) & jnp.all(jnp.isfinite(kp.points), -1) & jnp.all(jnp.isfinite(kp.desc), -1)
    return Keypoints(jnp.where(ok[:, None], kp.points, 0.0).astype(jnp.float32),
                     jnp.where(ok[:, None], kp.desc, 0.0).astype(jnp.float32), ok)


def build_entry(cloud: SequenceCloud, kf_desc, kf_valid, cfg: MemoryConfig,
                keypoints: Keypoints | None = None, min_support: float = 0.0,
                floor_keypoints: Keypoints | None = None) -> MapEntry:
    """A new map from a sequence: adaptive voxel size from the scene extent, mean point, colour and
    confidence per voxel, PCA normals, the 3D descriptor, the keyframe descriptors and (optional)
    the sequence's 3D keypoints (:func:`lift_keypoints`, same frame as ``cloud``) and (optional) its
    floor keypoints (:func:`cm3d.ops.keypoints.floor_features` on the same priors, as :class:`Keypoints`).

    ``min_support`` (a share, 0 = keep all; may be traced): voxels with fewer samples than this share of the
    median voxel's are dropped: in a capacity-bound map a stray sample (a mover the mask missed, a grazing or
    far pixel) weighs as much as a voxel of surface (docs/memory.md)."""
    vs = adaptive_voxel_size(cloud.points, cloud.valid, cfg.voxel_resolution)
    entry = _entry_from_points(cloud.points, cloud.colors, cloud.conf, cloud.valid, kf_desc, kf_valid, vs, cfg,
                               min_support)
    return entry.replace(keypoints=_clean_keypoints(keypoints), floor_keypoints=_clean_keypoints(floor_keypoints))
