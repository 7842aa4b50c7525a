"""Updating the memory: relocalising a verified query's cameras, merging it into its map, and
:func:`remember` (identify, then update the recalled map or store a new one)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from cm3d.memory.bank import GRID_CELL, MemoryBank, insert_map
from cm3d.memory.config import MemoryConfig
from cm3d.memory.entry import (Keypoints, MapEntry, cloud_descriptor, downsample_to_capacity, evenly_spread,
                              fit_keypoints)
from cm3d.memory.identify import Identification, identify
from cm3d.ops import descriptors, sim3
from cm3d.ops.grid import grid_nearest, sort_by_cell
from cm3d.ops.neighbors import estimate_normals
from cm3d.ops.voxel import voxel_downsample


def relocalize(transform, cam_to_world):
    """Cameras (..., 4, 4) of the query frame moved into the map frame by a Sim(3) ``transform``
    (``[s R, t]``): rotation ``R R_c``, centre ``s R t_c + t``; the result is a rigid pose."""
    A, t = transform[:3, :3], transform[:3, 3]
    R = A / sim3.scale(transform)
    out = cam_to_world.at[..., :3, :3].set(R @ cam_to_world[..., :3, :3])
    return out.at[..., :3, 3].set(jnp.einsum("ij,...j->...i", A, cam_to_world[..., :3, 3]) + t)


def merge_evenly(old_valid, new_valid):
    """Which of the concatenated old and new items (old first) to keep at the old capacity: all valid
    ones when they fit, else an evenly spread subset, so both visits stay represented
    (:func:`~cm3d.memory.entry.evenly_spread`): (indices into the concatenation, kept)."""
    return evenly_spread(jnp.concatenate([old_valid, new_valid]), old_valid.shape[0])


def update_map(bank: MemoryBank, map_id, entry: MapEntry, transform, cfg: MemoryConfig,
               same_frame=False) -> MemoryBank:
    """Merge a verified query into map ``map_id``: its voxels moved by ``transform`` (query ->
    map), pooled with the map's (weighted by confidence), downsampled again at the map's voxel
    size (grown if over capacity); keyframes and keypoints merged; 3D descriptor and normals
    recomputed. With ``cfg.merge_new_surface_only`` a query placed by an estimated ``transform`` (a recall)
    leaves the stored points as they are and adds only its voxels farther than one grid cell (the verifying
    ICP's inlier distance) from every stored point, downsampled at the map's voxel: the revisit adds what it
    newly saw (when that does not fit the capacity, all are pooled and the voxel grows, as without the
    option). ``same_frame`` (bool, may be traced): the query is already in the map's frame (a sequence's
    window into its own map, ``transform`` the identity), so its voxels are pooled whatever the option."""
    m = map_id
    A, t = transform[:3, :3], transform[:3, 3]
    q = entry.points @ A.T + t
    pts = jnp.concatenate([bank.points[m], q])
    valid = jnp.concatenate([bank.point_valid[m], entry.point_valid])
    feats = jnp.concatenate([jnp.concatenate([bank.colors[m], entry.colors]).astype(jnp.float32),
                             jnp.concatenate([bank.conf[m], entry.conf])[:, None]], axis=1)
    P = bank.points.shape[1]
    vox, vs = downsample_to_capacity(pts, valid, feats, bank.voxel_size[m], P)
    # the stored points as they are + the new surface at the map's voxel, when it fits (not even traced when the
    # caller knows the query is in the map's frame)
    if cfg.merge_new_surface_only and same_frame is not True:
        cell = GRID_CELL * jnp.maximum(bank.voxel_size[m], 1e-12)  # what the map holds: within an ICP inlier's distance
        _, d2 = grid_nearest(q, bank.points[m], bank.point_valid[m], cell, per_cell=cfg.grid_per_cell)
        add = voxel_downsample(q, bank.voxel_size[m], entry.point_valid & ~(d2 < cell**2), feats[P:], capacity=P)
        both = jnp.concatenate([bank.point_valid[m], add.valid])
        keep = jnp.argsort(~both, stable=True)[:P]
        fits = (jnp.sum(bank.point_valid[m]) + add.count <= P) & ~jnp.asarray(same_frame, bool)
        pick = lambda kept, pooled: jnp.where(fits, kept, pooled)  # noqa: E731
        vox = vox.replace(points=pick(jnp.concatenate([bank.points[m], add.points])[keep], vox.points),
                          valid=pick(both[keep], vox.valid),
                          features=pick(jnp.concatenate([feats[:P], add.features])[keep], vox.features))
        vs = jnp.where(fits, bank.voxel_size[m], vs)
    normals = estimate_normals(vox.points, vox.valid, k=16, radius=cfg.normal_radius)
    normals = jnp.where(vox.valid[:, None], normals, 0.0)
    vpts, vvalid, normals, vfeat = sort_by_cell(vox.points, vox.valid, jnp.maximum(vs, 1e-12) * GRID_CELL, normals,
                                                vox.features)
    vox = vox.replace(points=vpts, valid=vvalid, features=vfeat)
    idx, kfv = merge_evenly(bank.kf_valid[m], entry.kf_valid)
    kf = jnp.concatenate([bank.kf_desc[m], entry.kf_desc])[idx]

    def merged(new, points, desc, valid):  # the query's keypoints of one kind moved into the map and merged
        new = fit_keypoints(new, valid.shape[1], desc.shape[2])
        idx, kv = merge_evenly(valid[m], new.valid)
        moved = jnp.where(new.valid[:, None], new.points @ A.T + t, 0.0)
        pick = lambda old, add: jnp.where(kv[:, None], jnp.concatenate([old, add])[idx], 0.0)  # noqa: E731
        return Keypoints(pick(points[m], moved), pick(desc[m], new.desc), kv)

    kp = merged(entry.keypoints, bank.kp_points, bank.kp_desc, bank.kp_valid)
    fkp = merged(entry.floor_keypoints, bank.floor_kp_points, bank.floor_kp_desc, bank.floor_kp_valid)
    return bank.replace(
        points=bank.points.at[m].set(vox.points), normals=bank.normals.at[m].set(normals),
        conf=bank.conf.at[m].set(vox.features[:, 3]),
        colors=bank.colors.at[m].set(jnp.clip(jnp.round(vox.features[:, :3]), 0, 255).astype(jnp.uint8)),
        point_valid=bank.point_valid.at[m].set(vox.valid),
        cloud_desc=bank.cloud_desc.at[m].set(cloud_descriptor(vox.points, vox.valid, cfg)),
        kf_desc=bank.kf_desc.at[m].set(kf), kf_codes=bank.kf_codes.at[m].set(descriptors.hash_codes(kf, bank.planes)),
        kf_valid=bank.kf_valid.at[m].set(kfv), visits=bank.visits.at[m].add(1), voxel_size=bank.voxel_size.at[m].set(vs),
        kp_points=bank.kp_points.at[m].set(kp.points), kp_desc=bank.kp_desc.at[m].set(kp.desc),
        kp_valid=bank.kp_valid.at[m].set(kp.valid), floor_kp_points=bank.floor_kp_points.at[m].set(fkp.points),
        floor_kp_desc=bank.floor_kp_desc.at[m].set(fkp.desc), floor_kp_valid=bank.floor_kp_valid.at[m].set(fkp.valid))


@struct.dataclass
class Report:
    """What :func:`remember` decided: the identification (recall and verification), the accepted
    map (-1 if none), the map written to (-1 if the bank was full), the transform query -> map
    (identity for a new map) and whether a new map was created."""

    identification: Identification
    recalled: jax.Array
    map_id: jax.Array
    transform: jax.Array
    created: jax.Array


def remember(bank: MemoryBank, entry: MapEntry, cfg: MemoryConfig, key) -> tuple[MemoryBank, Report]:
    """Recall, verify, then update the recalled map or store a new one (pure, jittable).

    ``entry`` is the query sequence built by :func:`build_entry` (its own frame and scale).
    :func:`identify` picks and verifies a candidate; an accepted one is updated with the query
    moved into its frame (:func:`update_map`), else the query becomes a new map (map_id -1 when full).
    """
    ident = identify(bank, entry, cfg, key)
    hit = ident.map_id >= 0
    recalled = ident.map_id
    T = jnp.where(hit, ident.verification.transform, jnp.eye(4, dtype=ident.verification.transform.dtype))

    def on_hit(b):
        return update_map(b, jnp.maximum(recalled, 0), entry, T, cfg), recalled

    def on_miss(b):
        return insert_map(b, entry)

    bank, map_id = jax.lax.cond(hit, on_hit, on_miss, bank)
    return bank, Report(identification=ident, recalled=recalled, map_id=map_id.astype(jnp.int32), transform=T,
                        created=~hit & (map_id >= 0))
