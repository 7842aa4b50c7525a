"""Voxel grids in JAX: a fixed-capacity hash of integer cells, voxel downsampling and a pyramid.

Fixed shapes: padded inputs and outputs with validity masks; a too-small capacity is reported
(``overflow``), never silently dropped. The cell hash is open addressing with linear probing, built
without sorting by rounds of scatter-min (XLA:CPU scatters are much faster than its sort).
Cell of a point: ``floor((p - origin) / cell)``, Open3D's rule, with ``origin = min - voxel / 2``.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from flax import struct
from jax import lax

EMPTY = jnp.iinfo(jnp.int32).max
_MAX_PROBE = 64  # rounds of linear probing before a key counts as overflow (load <= 1/4)
_CELL_LIMIT = 1 << 30  # integer cell coordinates are clipped to +-this (|p / cell| beyond is garbage)


# Hash of integer cells


@struct.dataclass
class CellHash:
    """Open-addressing hash of int32 cell triples (capacity ``H``, a power of two). slot_item (H,): the
    owner (smallest item id of that key) or ``EMPTY``; slot_key (H, 3); max_probe (): longest chain;
    overflow (): keys left unplaced."""

    slot_item: jnp.ndarray
    slot_key: jnp.ndarray
    max_probe: jnp.ndarray
    overflow: jnp.ndarray

    @property
    def size(self) -> int:
        return self.slot_item.shape[-1]


def table_size(n: int) -> int:
    """Hash capacity for ``n`` keys: the power of two >= 4 n (load <= 1/4), at least 2."""
    return max(2, 1 << math.ceil(math.log2(max(4 * n, 1))))


def _home(keys: jnp.ndarray, size: int) -> jnp.ndarray:
    """Home slot in [0, size) of int32 triples (..., 3): xor of prime products, then a mixer."""
    k = keys.astype(jnp.uint32)
    h = (k[..., 0] * jnp.uint32(73856093)) ^ (k[..., 1] * jnp.uint32(19349663)) ^ (k[..., 2] * jnp.uint32(83492791))
    h = h ^ (h >> 16)
    h = h * jnp.uint32(0x7FEB352D)
    h = h ^ (h >> 15)
    h = h * jnp.uint32(0x846CA68B)
    h = h ^ (h >> 16)
    return (h & jnp.uint32(size - 1)).astype(jnp.int32)


def hash_insert(keys: jnp.ndarray, active: jnp.ndarray, size: int | None = None):
    """Insert int32 cell triples ``keys`` (n, 3) where ``active`` (n,) -> (CellHash, slot (n,)).
    Equal keys share one slot (``size`` for inactive or overflowing items); ``size`` (static, a power
    of two) defaults to :func:`table_size` (n). Deterministic."""
    n = keys.shape[0]
    size = table_size(n) if size is None else int(size)
    if size & (size - 1):
        raise ValueError(f"hash size must be a power of two, got {size}")
    keys = keys.astype(jnp.int32)
    ids = jnp.arange(n, dtype=jnp.int32)
    home = _home(keys, size)
    mask = size - 1

    def cond(c):
        return jnp.any(c[2]) & (c[3] < _MAX_PROBE)

    def body(c):
        """One probing round: pending items claim their probe slot if free (smallest id wins), then
        each checks whether the slot's owner has its key (placed) or moves on next round."""
        table, slot, pending, r = c
        s = (home + r) & mask
        free = table[s] == EMPTY
        table = table.at[jnp.where(pending & free, s, size)].min(ids, mode="drop")
        owner = table[s]
        same = jnp.all(keys[jnp.clip(owner, 0, max(n - 1, 0))] == keys, axis=-1) & (owner != EMPTY)
        placed = pending & same
        return table, jnp.where(placed, s, slot), pending & ~placed, r + 1

    init = (jnp.full((size,), EMPTY, jnp.int32), jnp.full((n,), size, jnp.int32), active.astype(bool), jnp.int32(0))
    table, slot, pending, rounds = lax.while_loop(cond, body, init) if n else init
    slot_key = (jnp.where((table != EMPTY)[:, None], keys[jnp.clip(table, 0, n - 1)], 0) if n
                else jnp.zeros((size, 3), jnp.int32))
    h = CellHash(slot_item=table, slot_key=slot_key.astype(jnp.int32), max_probe=rounds,
                 overflow=jnp.sum(pending).astype(jnp.int32))
    return h, slot


def hash_lookup(h: CellHash, keys: jnp.ndarray) -> jnp.ndarray:
    """Slot of each int32 triple in ``keys`` (..., 3), or -1 where the key is absent."""
    size = h.size
    shape = keys.shape[:-1]
    home = _home(keys, size)

    def cond(c):
        _, todo, r = c
        return jnp.any(todo) & (r < h.max_probe)

    def body(c):
        found, todo, r = c
        s = (home + r) & (size - 1)
        occ = h.slot_item[s]
        hit = todo & (occ != EMPTY) & jnp.all(h.slot_key[s] == keys, axis=-1)
        found = jnp.where(hit, s, found)
        todo = todo & ~hit & (occ != EMPTY)
        return found, todo, r + 1

    init = (jnp.full(shape, -1, jnp.int32), jnp.ones(shape, bool), jnp.int32(0))
    found, _, _ = lax.while_loop(cond, body, init)
    return found


def cell_coords(points: jnp.ndarray, origin: jnp.ndarray, cell) -> jnp.ndarray:
    """Integer cell (..., 3) int32 of points (..., 3): ``floor((p - origin) / cell)`` (clipped)."""
    c = jnp.floor((points - origin) / cell)
    c = jnp.where(jnp.isfinite(c), c, 0.0)
    return jnp.clip(c, -_CELL_LIMIT, _CELL_LIMIT).astype(jnp.int32)


def valid_points(points: jnp.ndarray, valid=None) -> jnp.ndarray:
    """(n,) bool: the given mask (default all) and finite coordinates."""
    ok = jnp.all(jnp.isfinite(points), axis=-1)
    if valid is not None:
        ok = ok & jnp.asarray(valid).astype(bool)
    return ok


def masked_bounds(points: jnp.ndarray, valid: jnp.ndarray):
    """(min (3,), max (3,)) over valid points; (0, 0) when none is valid."""
    big = jnp.asarray(jnp.finfo(points.dtype).max, points.dtype)
    lo = jnp.min(jnp.where(valid[:, None], points, big), axis=0, initial=big)
    hi = jnp.max(jnp.where(valid[:, None], points, -big), axis=0, initial=-big)
    anyv = jnp.any(valid)
    return jnp.where(anyv, lo, 0.0), jnp.where(anyv, hi, 0.0)


# Voxel downsampling


@struct.dataclass
class Voxels:
    """A voxel-downsampled cloud padded to a static capacity ``C``.

    points (C, 3) and features (C, F) or None: per-voxel means; weight (C,): points (or weight) per
    voxel; keys (C, 3) int32 cells; valid (C,); count (): occupied voxels (may exceed C); overflow ():
    what did not fit; origin (3,) and voxel_size () define the cells.
    """

    points: jnp.ndarray
    features: jnp.ndarray | None
    weight: jnp.ndarray
    keys: jnp.ndarray
    valid: jnp.ndarray
    count: jnp.ndarray
    overflow: jnp.ndarray
    origin: jnp.ndarray
    voxel_size: jnp.ndarray


def _reduce_cells(keys, active, values, weights, capacity: int):
    """Weighted means of ``values`` (n, D) over equal int keys (n, 3) -> padded per-cell arrays."""
    n = keys.shape[0]
    h, slot = hash_insert(keys, active)
    occupied = h.slot_item != EMPTY
    cid = jnp.cumsum(occupied.astype(jnp.int32)) - 1
    count = jnp.sum(occupied).astype(jnp.int32)
    vid = jnp.where(active & (slot < h.size), cid[jnp.clip(slot, 0, h.size - 1)], capacity)
    vid = jnp.where(vid < capacity, vid, capacity)
    w = jnp.where(active, weights, 0.0).astype(values.dtype)
    sums = jax.ops.segment_sum(jnp.concatenate([values * w[:, None], w[:, None]], axis=1), vid,
                               num_segments=capacity + 1)[:capacity]
    wsum = sums[:, -1]
    filled = jnp.zeros((capacity,), bool).at[vid].set(True, mode="drop")
    mean = sums[:, :-1] / jnp.where(wsum > 0, wsum, 1.0)[:, None]
    # the key of each output voxel: the key of its owning item
    owner_slot_key = jnp.zeros((capacity, 3), jnp.int32).at[vid].set(keys, mode="drop")
    overflow = jnp.maximum(count - capacity, 0) + h.overflow
    del n
    return mean, wsum, owner_slot_key, filled, count, overflow


def voxel_downsample(points, voxel_size, valid=None, features=None, capacity: int | None = None,
                     weights=None, origin=None) -> Voxels:
    """Mean point (and mean features) per occupied voxel, as Open3D's ``voxel_down_sample``.

    points: (n, 3); voxel_size: scalar > 0 (may be traced); valid: optional (n,) mask (non-finite
    points are dropped); features: optional (n, F); capacity: static output size (default n);
    weights: optional (n,); origin: optional (3,). Returns :class:`Voxels` in hash order
    (deterministic). A non-positive or non-finite voxel size gives an empty result.
    """
    points = jnp.asarray(points)
    if points.ndim != 2 or points.shape[-1] != 3:
        raise ValueError(f"points must be (n, 3), got {points.shape}")
    n = points.shape[0]
    if isinstance(voxel_size, (int, float)) and not voxel_size > 0:
        raise ValueError(f"voxel_size must be > 0, got {voxel_size}")
    capacity = n if capacity is None else int(capacity)
    dtype = points.dtype
    vs = jnp.asarray(voxel_size, dtype)
    ok_size = jnp.isfinite(vs) & (vs > 0)
    active = valid_points(points, valid) & ok_size
    if origin is None:
        lo, _ = masked_bounds(points, active)
        origin = lo - 0.5 * vs
    origin = jnp.asarray(origin, dtype)
    keys = cell_coords(points, origin, jnp.where(ok_size, vs, 1.0))
    feats = None if features is None else jnp.asarray(features, dtype).reshape(n, -1)
    values = points if feats is None else jnp.concatenate([points, feats], axis=1)
    w = jnp.ones((n,), dtype) if weights is None else jnp.asarray(weights, dtype)
    if capacity == 0 or n == 0:
        F = 0 if feats is None else feats.shape[1]
        z = jnp.zeros((capacity,), dtype)
        return Voxels(points=jnp.zeros((capacity, 3), dtype),
                      features=None if feats is None else jnp.zeros((capacity, F), dtype),
                      weight=z, keys=jnp.zeros((capacity, 3), jnp.int32), valid=jnp.zeros((capacity,), bool),
                      count=jnp.int32(0), overflow=jnp.int32(0), origin=origin, voxel_size=vs)
    mean, wsum, vkeys, filled, count, overflow = _reduce_cells(keys, active, values, w, capacity)
    return Voxels(points=mean[:, :3], features=None if feats is None else mean[:, 3:], weight=wsum,
                  keys=vkeys, valid=filled, count=count, overflow=overflow, origin=origin, voxel_size=vs)


def adaptive_voxel_size(points, valid=None, resolution: float = 100.0):
    """Voxel size from the scene extent: largest bounding-box side / ``resolution`` (0 when empty)."""
    points = jnp.asarray(points)
    ok = valid_points(points, valid)
    lo, hi = masked_bounds(points, ok)
    return jnp.max(hi - lo) / resolution


def voxel_pyramid(points, voxel_size, num_levels: int, valid=None, features=None,
                  capacities: tuple[int, ...] | None = None) -> tuple[Voxels, ...]:
    """Octree-like levels, finest first: level ``l`` has voxels of ``voxel_size * 2**l`` on one grid origin.
    Level ``l + 1`` merges the 2x2x2 children of level ``l`` (count-weighted), which equals a direct
    downsample of the input; capacities: static per-level sizes (default n each)."""
    points = jnp.asarray(points)
    n = points.shape[0]
    if capacities is None:
        capacities = (n,) * num_levels
    if len(capacities) != num_levels:
        raise ValueError("capacities needs one entry per level")
    levels = [voxel_downsample(points, voxel_size, valid, features, capacities[0])]
    for l in range(1, num_levels):
        prev = levels[-1]
        keys = jnp.floor_divide(prev.keys, 2)
        vals = prev.points if prev.features is None else jnp.concatenate([prev.points, prev.features], axis=1)
        mean, wsum, vkeys, filled, count, overflow = _reduce_cells(keys, prev.valid, vals, prev.weight, capacities[l])
        levels.append(Voxels(points=mean[:, :3], features=None if prev.features is None else mean[:, 3:],
                             weight=wsum, keys=vkeys, valid=filled, count=count,
                             overflow=overflow + prev.overflow, origin=prev.origin,
                             voxel_size=prev.voxel_size * 2))
    return tuple(levels)
