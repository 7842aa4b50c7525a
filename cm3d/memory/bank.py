"""The memory bank: an immutable pytree of static maps with fixed capacities, and its slot operations.

Per map ``m < max_maps``: a static point cloud (``points``, ``normals``, ``conf``, ``colors``,
``point_valid``; voxel downsampled, in the map's own frame and scale, sorted by grid cells of
``GRID_CELL`` map voxels, :func:`cm3d.ops.grid.sort_by_cell`, so that ICP searches it with no index),
its 3D descriptor ``cloud_desc``, up to ``max_keyframes`` keyframe descriptors ``kf_desc`` with hash
codes ``kf_codes``, up to ``max_keypoints`` 3D keypoints (local RootSIFT descriptors lifted to the map
frame) and up to ``max_floor_keypoints`` floor keypoints (:func:`cm3d.ops.keypoints.floor_features`).
The *global feature table* is the flat view ``kf_desc.reshape(max_maps * max_keyframes, dim)`` with
``map_id = row // max_keyframes`` (:func:`global_table`), so it never goes out of sync with the maps.

Capacity policy: inserting into a full bank is refused. The pure :func:`insert_map` returns the
bank unchanged and ``map_id = -1``; the host-side :func:`add_map` raises :class:`MemoryFullError`.
Maps are never evicted silently; :func:`remove_map` frees a slot explicitly.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from cm3d.memory.config import MemoryConfig, MemoryFullError
from cm3d.memory.entry import Keypoints, MapEntry, fit_keypoints
from cm3d.ops import descriptors
from cm3d.ops.grid import sort_by_cell

GRID_CELL = 1.5  # a map's points are sorted by grid cells of this many map voxels; the verifying ICP
# searches the 27 cells around a point, so its correspondence distance is one cell


@struct.dataclass
class MemoryBank:
    """See :mod:`cm3d.memory.bank`. ``M = max_maps``, ``P = max_points``, ``K = max_keyframes``."""

    points: jax.Array  # (M, P, 3) float32
    normals: jax.Array  # (M, P, 3) float32
    conf: jax.Array  # (M, P) float32
    colors: jax.Array  # (M, P, 3) uint8
    point_valid: jax.Array  # (M, P) bool
    cloud_desc: jax.Array  # (M, D3) float32
    kf_desc: jax.Array  # (M, K, D2) float32
    kf_codes: jax.Array  # (M, K, W) uint32
    kf_valid: jax.Array  # (M, K) bool
    map_valid: jax.Array  # (M,) bool
    visits: jax.Array  # (M,) int32: how many sequences built or updated the map
    voxel_size: jax.Array  # (M,) float32: the map's voxel size (its own units)
    planes: jax.Array  # (bits, D2) float32: the LSH hyperplanes the codes were made with
    kp_points: jax.Array  # (M, N, 3) float32: 3D keypoints in the map frame (N = max_keypoints)
    kp_desc: jax.Array  # (M, N, Dk) float32: their unit local descriptors
    kp_valid: jax.Array  # (M, N) bool
    floor_kp_points: jax.Array  # (M, F, 3) float32: floor keypoints (F = max_floor_keypoints), map frame
    floor_kp_desc: jax.Array  # (M, F, Dk) float32
    floor_kp_valid: jax.Array  # (M, F) bool

    @property
    def num_maps(self) -> jax.Array:
        return jnp.sum(self.map_valid)


@struct.dataclass
class MapCloud:
    """One stored map's voxel cloud, in the map's frame: points, normals (P, 3), colours (P, 3) uint8,
    validity (P,) (all False when the map id was negative) and the map's voxel size."""

    points: jax.Array
    normals: jax.Array
    colors: jax.Array
    valid: jax.Array
    voxel_size: jax.Array


def map_cloud(bank: MemoryBank, map_id) -> MapCloud:
    """The cloud of map ``map_id`` (jittable; ``map_id < 0`` gives an all-invalid cloud)."""
    m = jnp.maximum(map_id, 0)
    return MapCloud(points=bank.points[m], normals=bank.normals[m], colors=bank.colors[m],
                    valid=bank.point_valid[m] & (map_id >= 0), voxel_size=bank.voxel_size[m])


def without_map(bank: MemoryBank, map_id) -> MemoryBank:
    """The bank with map ``map_id`` hidden from recall (jittable; ``map_id < 0`` hides nothing)."""
    M = bank.map_valid.shape[0]
    return bank.replace(map_valid=bank.map_valid & (jnp.arange(M) != map_id))


def stored_entry(bank: MemoryBank, map_id) -> MapEntry:
    """Map ``map_id``'s contents as a :class:`MapEntry` at the bank's capacities (jittable)."""
    m = jnp.maximum(map_id, 0)
    return MapEntry(points=bank.points[m], normals=bank.normals[m], conf=bank.conf[m], colors=bank.colors[m],
                    point_valid=bank.point_valid[m], kf_desc=bank.kf_desc[m], kf_valid=bank.kf_valid[m],
                    cloud_desc=bank.cloud_desc[m], voxel_size=bank.voxel_size[m],
                    keypoints=Keypoints(bank.kp_points[m], bank.kp_desc[m], bank.kp_valid[m]),
                    floor_keypoints=Keypoints(bank.floor_kp_points[m], bank.floor_kp_desc[m], bank.floor_kp_valid[m]))


def map_counts(bank: MemoryBank, map_id: int) -> dict[str, int]:
    """What map ``map_id`` holds (host side): points, keyframes, keypoints, floor keypoints, visits."""
    return dict(points=int(bank.point_valid[map_id].sum()), keyframes=int(bank.kf_valid[map_id].sum()),
                keypoints=int(bank.kp_valid[map_id].sum()), floor_keypoints=int(bank.floor_kp_valid[map_id].sum()),
                visits=int(bank.visits[map_id]))


def capacities(bank: MemoryBank) -> dict[str, int]:
    """The bank's shape-fixing capacities, by their :class:`MemoryConfig` field names."""
    return dict(max_maps=bank.points.shape[0], max_points=bank.points.shape[1],
                max_keyframes=bank.kf_desc.shape[1], max_keypoints=bank.kp_points.shape[1],
                max_floor_keypoints=bank.floor_kp_points.shape[1])


def empty(cfg: MemoryConfig = MemoryConfig()) -> MemoryBank:
    """A bank with every slot free."""
    if cfg.hash_bits % 32:
        raise ValueError(f"MemoryConfig.hash_bits: must be a multiple of 32, got {cfg.hash_bits}")
    M, P, K = cfg.max_maps, cfg.max_points, cfg.max_keyframes
    return MemoryBank(
        points=jnp.zeros((M, P, 3), jnp.float32), normals=jnp.zeros((M, P, 3), jnp.float32),
        conf=jnp.zeros((M, P), jnp.float32), colors=jnp.zeros((M, P, 3), jnp.uint8),
        point_valid=jnp.zeros((M, P), bool), cloud_desc=jnp.zeros((M, cfg.cloud_dim), jnp.float32),
        kf_desc=jnp.zeros((M, K, cfg.image_dim), jnp.float32),
        kf_codes=jnp.zeros((M, K, cfg.hash_bits // 32), jnp.uint32), kf_valid=jnp.zeros((M, K), bool),
        map_valid=jnp.zeros((M,), bool), visits=jnp.zeros((M,), jnp.int32), voxel_size=jnp.zeros((M,), jnp.float32),
        planes=descriptors.hash_planes(cfg.image_dim, cfg.hash_bits, cfg.hash_seed).astype(jnp.float32),
        kp_points=jnp.zeros((M, cfg.max_keypoints, 3), jnp.float32),
        kp_desc=jnp.zeros((M, cfg.max_keypoints, cfg.keypoint_dim), jnp.float32),
        kp_valid=jnp.zeros((M, cfg.max_keypoints), bool),
        floor_kp_points=jnp.zeros((M, cfg.max_floor_keypoints, 3), jnp.float32),
        floor_kp_desc=jnp.zeros((M, cfg.max_floor_keypoints, cfg.keypoint_dim), jnp.float32),
        floor_kp_valid=jnp.zeros((M, cfg.max_floor_keypoints), bool),
    )


def insert_map(bank: MemoryBank, entry: MapEntry) -> tuple[MemoryBank, jax.Array]:
    """Put ``entry`` in the first free slot: ``(bank, map_id)``; a full bank is returned
    unchanged with ``map_id = -1`` (pure and jittable; see :func:`add_map` for the host check)."""
    free = ~bank.map_valid
    slot = jnp.argmax(free)
    ok = free[slot]
    codes = descriptors.hash_codes(entry.kf_desc, bank.planes)
    kp = fit_keypoints(entry.keypoints, bank.kp_valid.shape[1], bank.kp_desc.shape[2])
    fkp = fit_keypoints(entry.floor_keypoints, bank.floor_kp_valid.shape[1], bank.floor_kp_desc.shape[2])
    vs = jnp.maximum(jnp.asarray(entry.voxel_size, jnp.float32), 1e-12)
    points, point_valid, normals, conf, colors = sort_by_cell(
        jnp.asarray(entry.points, jnp.float32), jnp.asarray(entry.point_valid, bool), vs * GRID_CELL,
        jnp.asarray(entry.normals), jnp.asarray(entry.conf), jnp.asarray(entry.colors))

    def put(field, value):
        return field.at[slot].set(jnp.where(ok, value.astype(field.dtype), field[slot]))

    new = bank.replace(
        points=put(bank.points, points), normals=put(bank.normals, normals),
        conf=put(bank.conf, conf), colors=put(bank.colors, colors),
        point_valid=put(bank.point_valid, point_valid), cloud_desc=put(bank.cloud_desc, entry.cloud_desc),
        kf_desc=put(bank.kf_desc, entry.kf_desc), kf_codes=put(bank.kf_codes, codes),
        kf_valid=put(bank.kf_valid, entry.kf_valid), map_valid=put(bank.map_valid, jnp.bool_(True)),
        visits=put(bank.visits, jnp.int32(1)), voxel_size=put(bank.voxel_size, entry.voxel_size),
        kp_points=put(bank.kp_points, kp.points), kp_desc=put(bank.kp_desc, kp.desc),
        kp_valid=put(bank.kp_valid, kp.valid), floor_kp_points=put(bank.floor_kp_points, fkp.points),
        floor_kp_desc=put(bank.floor_kp_desc, fkp.desc), floor_kp_valid=put(bank.floor_kp_valid, fkp.valid),
    )
    return new, jnp.where(ok, slot, -1).astype(jnp.int32)


def add_map(bank: MemoryBank, entry: MapEntry) -> tuple[MemoryBank, int]:
    """Host-side :func:`insert_map` that raises :class:`MemoryFullError` instead of returning -1."""
    if bool(jnp.all(bank.map_valid)):
        raise MemoryFullError(f"memory bank is full ({bank.map_valid.shape[0]} maps): remove a map "
                              "(cm3d memory rm) or use a larger MemoryConfig.max_maps")
    bank, map_id = insert_map(bank, entry)
    return bank, int(map_id)


def remove_map(bank: MemoryBank, map_id) -> MemoryBank:
    """Free slot ``map_id`` (its data is zeroed)."""
    keep = jnp.arange(bank.map_valid.shape[0]) != map_id

    def clear(x):
        return jnp.where(keep.reshape((-1,) + (1,) * (x.ndim - 1)), x, jnp.zeros_like(x))

    fields = {f.name: clear(getattr(bank, f.name)) for f in dataclasses.fields(bank) if f.name != "planes"}
    return bank.replace(**fields)


def global_table(bank: MemoryBank):
    """The global feature table: descriptors (M*K, D2), codes (M*K, W), valid (M*K,), map_id (M*K,)."""
    M, K, D = bank.kf_desc.shape
    valid = (bank.kf_valid & bank.map_valid[:, None]).reshape(-1)
    return (bank.kf_desc.reshape(M * K, D), bank.kf_codes.reshape(M * K, -1), valid,
            jnp.repeat(jnp.arange(M, dtype=jnp.int32), K))
