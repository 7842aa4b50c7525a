"""Uniform grids over point clouds: cell ranges and radius neighbourhoods, and the one grid
nearest-neighbour search.

Two layouts of the same idea (points sorted so that a cell is a contiguous range):

* :class:`Grid` (:func:`build_grid`): occupied cells in a hash, each slot's ``start`` / ``count``;
  :func:`grid_candidates` gathers the points of the 27 cells around a query (nearest cells first),
  :func:`radius_neighbors` the neighbourhoods of FPFH features;
* the *sorted layout* (:func:`sort_by_cell`): points sorted by an integer cell code
  (:func:`cell_codes`, x fastest) and nothing else, so a cloud stored that way (a memory map)
  needs no index: :func:`grid_nearest` finds each row of cells by binary search.
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax import lax

from cm3d.ops.voxel import CellHash, cell_coords, hash_insert, hash_lookup, masked_bounds, valid_points

# The 27 cell offsets, nearest first (centre, 6 faces, 12 edges, 8 corners).
OFFSETS27 = np.array(sorted(itertools.product((-1, 0, 1), repeat=3), key=lambda o: (sum(map(abs, o)), o)),
                     np.int32)


def compact_apply(mask: jnp.ndarray, fn, init, chunk: int = 512):
    """Run ``fn(idx, ok)`` on the indices where ``mask`` (n,) in chunks; write results into ``init``.

    fn gets ``idx`` (chunk,) int32 (clipped) and ``ok`` (chunk,) bool and returns a pytree of
    (chunk, ...) arrays, scattered into the matching leaves of ``init`` (n, ...) at ``idx``. The loop
    runs ``ceil(sum(mask) / chunk)`` times (a ``while_loop``), so the cost follows the number of
    selected items while all shapes stay fixed; with nothing selected not even the compaction runs
    (a ``cond``). The compaction is a prefix sum and a scatter (cheaper than ``jnp.nonzero`` on
    XLA CPU).
    """
    n = mask.shape[0]
    if n == 0:
        return init
    chunk = max(1, min(chunk, n))
    nch = -(-n // chunk)
    count = jnp.sum(mask)

    def run(out):
        pos = jnp.cumsum(mask.astype(jnp.int32)) - 1
        idx = jnp.full((nch * chunk,), n, jnp.int32).at[jnp.where(mask, pos, nch * chunk)].set(
            jnp.arange(n, dtype=jnp.int32), mode="drop")

        def cond(c):
            return c[0] * chunk < count

        def body(c):
            it, out = c
            sl = lax.dynamic_slice(idx, (it * chunk,), (chunk,))
            ok = sl < n
            vals = fn(jnp.clip(sl, 0, n - 1), ok)
            dst = jnp.where(ok, sl, n)
            out = jax.tree.map(lambda o, v: o.at[dst].set(v, mode="drop"), out, vals)
            return it + 1, out

        return lax.while_loop(cond, body, (jnp.int32(0), out))[1]

    return lax.cond(count > 0, run, lambda out: out, init)


def _cells_within(q, key, origin, cell, dmax):
    """(B, 27) bool: which of the 27 cells around int keys (B, 3) of queries q (B, 3) come within
    ``dmax`` (B,) of the query (box distance; a small margin keeps boundary cases in)."""
    lo = origin + (key[:, None, :] + jnp.asarray(OFFSETS27)[None]).astype(q.dtype) * cell  # (B, 27, 3)
    gap = jnp.maximum(jnp.maximum(lo - q[:, None, :], q[:, None, :] - (lo + cell)), 0.0)
    return jnp.sum(gap * gap, axis=-1) <= (dmax[:, None] * (1 + 1e-4) + 1e-4 * cell) ** 2


def _gather_candidates(h: CellHash, start, count, key, j, cell_mask=None, full_cells: bool = False):
    """First ``len(j)`` points (sorted positions) of the 27 cells around int keys (B, 3) (only
    those where ``cell_mask`` (B, 27), if given) -> (cand (B, C), valid (B, C), total (B,) number
    of points in those cells); full_cells (with ``j = arange(C)``): also the number of leading
    cells (OFFSETS27 order) whose points are all among the C (B,)."""
    ranges = _cell_ranges(h, start, count, key, cell_mask)
    return _range_candidates(ranges, j, full_cells)


def _cell_ranges(h: CellHash, start, count, key, cell_mask=None):
    """The point ranges of the 27 cells around int keys (B, 3) (only where ``cell_mask``):
    (first sorted position (B, 27), count (B, 27), inclusive cumulative count (B, 27))."""
    nb = hash_lookup(h, key[:, None, :] + jnp.asarray(OFFSETS27)[None])  # (B, 27)
    if cell_mask is not None:
        nb = jnp.where(cell_mask, nb, -1)
    nbc = jnp.clip(nb, 0, h.size - 1)
    cnt = jnp.where(nb >= 0, count[nbc], 0)
    return start[nbc], cnt, jnp.cumsum(cnt, axis=1)


def _range_candidates(ranges, j, full_cells: bool = False):
    """Candidates number ``j`` (C,) of the concatenated cell ranges of :func:`_cell_ranges`, as
    :func:`_gather_candidates` returns them."""
    st, cnt, cum = ranges
    total = cum[:, -1]
    cellidx = jnp.zeros((st.shape[0], j.shape[0]), jnp.int32)
    for c in range(26):
        cellidx = cellidx + (cum[:, c : c + 1] <= j[None, :])
    excl = jnp.take_along_axis(cum - cnt, cellidx, axis=1)
    cand = jnp.take_along_axis(st, cellidx, axis=1) + j[None, :] - excl
    valid = j[None, :] < total[:, None]
    if full_cells:
        return jnp.where(valid, cand, 0), valid, total, jnp.sum(cum <= j.shape[0], axis=1).astype(jnp.int32)
    return jnp.where(valid, cand, 0), valid, total


@struct.dataclass
class RadiusNeighbors:
    """The nearest neighbours within a radius of every point of a cloud (itself excluded).

    idx: (n, K) int32 input indices, ascending distance, -1 padding; dist2: (n, K) squared
    distances (inf padding); count: (n,) neighbours found (<= K, the ``K`` nearest when more lie
    within the radius); truncated: () int32 points whose 27 grid cells held more than
    ``max_candidates`` points (their list may miss the farthest neighbours).
    """

    idx: jnp.ndarray
    dist2: jnp.ndarray
    count: jnp.ndarray
    truncated: jnp.ndarray


@struct.dataclass
class Grid:
    """A cloud bucketed by a uniform grid (cell may be traced): the hash of occupied cells, the
    points sorted by cell (``order`` (n,) input index per sorted position) and each hash slot's
    ``start`` / ``count`` range. points (n, 3) and valid (n,) are the caller's (input order)."""

    points: jnp.ndarray
    valid: jnp.ndarray
    hash: CellHash
    order: jnp.ndarray
    start: jnp.ndarray
    count: jnp.ndarray
    origin: jnp.ndarray
    cell: jnp.ndarray


def build_grid(points, valid=None, *, cell) -> Grid:
    """:class:`Grid` of points (n, 3) (valid: optional mask; non-finite points are dropped) with
    cubic cells of side ``cell`` (> 0, may be traced; a bad cell leaves the grid empty)."""
    points = jnp.asarray(points)
    n, dtype = points.shape[0], points.dtype
    c = jnp.asarray(cell, dtype)
    ok_c = jnp.isfinite(c) & (c > 0)
    ok = valid_points(points, valid) & ok_c
    c = jnp.where(ok_c, c, 1.0)
    lo, _ = masked_bounds(points, ok)
    h, slot = hash_insert(cell_coords(points, lo, c), ok)
    big = jnp.int32(np.iinfo(np.int32).max)
    sslot, order = lax.sort((jnp.where(ok, slot, big), jnp.arange(n, dtype=jnp.int32)), num_keys=1)
    pos = jnp.arange(n, dtype=jnp.int32)
    dst = jnp.where(sslot < h.size, sslot, h.size)
    start = jnp.full((h.size,), n, jnp.int32).at[dst].min(pos, mode="drop")
    count = jnp.zeros((h.size,), jnp.int32).at[dst].add(1, mode="drop")
    return Grid(points=points, valid=ok, hash=h, order=order, start=start, count=count, origin=lo, cell=c)


def grid_candidates(grid: Grid, q, max_candidates: int):
    """The first ``max_candidates`` grid points (input indices) of the 27 cells around queries
    q (B, 3), nearest cells first -> (idx (B, C), valid (B, C), total (B,) points in the 27 cells).
    Every point within one cell of a query is among them unless ``total > max_candidates``."""
    keys = cell_coords(q, grid.origin, grid.cell)
    cand, ok, total = _gather_candidates(grid.hash, grid.start, grid.count, keys,
                                         jnp.arange(max_candidates, dtype=jnp.int32))
    return grid.order[cand], ok, total


def radius_neighbors(points, valid=None, *, radius, max_nn: int = 64, max_candidates: int = 512,
                     chunk: int = 1024) -> RadiusNeighbors:
    """Up to ``max_nn`` nearest neighbours within ``radius`` of each point of a cloud (n, 3), as
    Open3D's ``KDTreeSearchParamHybrid(radius, max_nn + 1)`` without the point itself.

    A :class:`Grid` of cell ``radius`` (may be traced); a point's candidates are the first
    ``max_candidates`` points of its 27 cells, nearest cells first (both static). Invalid (masked
    or non-finite) points have no neighbours and are nobody's neighbour; a non-positive radius
    gives none.
    """
    points = jnp.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (n, 3), got {points.shape}")
    K, C = int(max_nn), int(max_candidates)
    if not 1 <= K <= C:
        raise ValueError(f"need 1 <= max_nn <= max_candidates, got {max_nn}, {max_candidates}")
    n, dtype = points.shape[0], points.dtype
    if n == 0:
        return RadiusNeighbors(idx=jnp.zeros((0, K), jnp.int32), dist2=jnp.zeros((0, K), dtype),
                               count=jnp.zeros((0,), jnp.int32), truncated=jnp.int32(0))
    grid = build_grid(points, valid, cell=radius)
    r2 = jnp.asarray(radius, dtype) ** 2

    def fn(i, _ok):
        ci, cvalid, total = grid_candidates(grid, points[i], C)
        d2 = jnp.sum((points[ci] - points[i][:, None, :]) ** 2, axis=-1)
        m = cvalid & (ci != i[:, None]) & (d2 <= r2)
        neg, a = lax.top_k(jnp.where(m, -d2, -jnp.inf), K)  # top_k: fast to compile and run here
        return jnp.take_along_axis(ci, a, 1), -neg, total > C

    init = (jnp.full((n, K), -1, jnp.int32), jnp.full((n, K), jnp.inf, dtype), jnp.zeros((n,), bool))
    idx, d2, trunc = compact_apply(grid.valid, fn, init, chunk)
    has = jnp.isfinite(d2)
    return RadiusNeighbors(idx=jnp.where(has, idx, -1), dist2=d2, count=jnp.sum(has, axis=1).astype(jnp.int32),
                           truncated=jnp.sum(trunc).astype(jnp.int32))


# --- The sorted layout


def first_argmin(x, axis: int):
    """``jnp.argmin(x, axis)`` for arrays without NaN (the first index of the minimum) as two plain
    reductions (the min, then the smallest index reaching it): XLA's CPU backend runs them faster than
    argmin's (value, index) reduction."""
    x = jnp.asarray(x)
    low = jnp.min(x, axis=axis, keepdims=True)
    shape = [1] * x.ndim
    shape[axis] = x.shape[axis]
    iota = jnp.arange(x.shape[axis], dtype=jnp.int32).reshape(shape)
    return jnp.min(jnp.where(x == low, iota, x.shape[axis] - 1), axis=axis)


_CELL_BITS = 10  # cell coordinates in [0, 1024) per axis after the offset below
_NO_CELL = jnp.iinfo(jnp.int32).max


def _cell_of(points, cell, origin):
    return jnp.floor((points - origin) / cell).astype(jnp.int32) + (1 << (_CELL_BITS - 1))


def cell_codes(points, valid, cell, origin=0.0):
    """Integer code (N,) int32 of each point's grid cell ``floor((p - origin) / cell)`` (offset so that
    the grid spans +-512 cells around ``origin``; farther points are clipped); invalid: INT32_MAX."""
    c = jnp.clip(_cell_of(points, cell, origin), 0, (1 << _CELL_BITS) - 1)
    code = c[..., 0] + (c[..., 1] << _CELL_BITS) + (c[..., 2] << (2 * _CELL_BITS))
    return jnp.where(valid, code, _NO_CELL)


def sort_by_cell(points, valid, cell, *others, origin=0.0):
    """Reorder points (and any per-point arrays ``others``) by :func:`cell_codes` (invalid last): the
    layout :func:`grid_nearest` searches (a memory map is stored in it)."""
    order = jnp.argsort(cell_codes(points, valid, cell, origin), stable=True)
    return (points[order], valid[order]) + tuple(o[order] for o in others)


def grid_nearest(q, points, valid, cell, reach: int = 1, per_cell: int = 2, origin=0.0):
    """Nearest point to each query q (n, 3) among the points of the cells within ``reach`` cells
    (``points`` (P, 3) in the layout of :func:`sort_by_cell` at the same ``cell`` and ``origin``).

    Exact for neighbours closer than ``reach * cell`` when no row of ``2 reach + 1`` cells holds more
    than ``(2 reach + 1) per_cell`` points (a cloud voxel-downsampled finer than ``cell`` holds one or
    two per cell). Codes run along x first, so each (y, z) row of cells is one contiguous range: one
    binary search per row. Returns (index (n,), squared distance (n,), inf if none).
    """
    q, points, valid = jnp.asarray(q), jnp.asarray(points), jnp.asarray(valid, bool)
    codes = cell_codes(points, valid, cell, origin)
    r = jnp.arange(-reach, reach + 1)
    dy, dz = (a.reshape(-1) for a in jnp.meshgrid(r, r, indexing="ij"))
    base = _cell_of(q, cell, origin)
    hi_c = (1 << _CELL_BITS) - 1
    x0 = jnp.clip(base[:, 0] - reach, 0, hi_c)[:, None]
    x1 = jnp.clip(base[:, 0] + reach, 0, hi_c)[:, None]
    y = base[:, 1:2] + dy[None]
    z = base[:, 2:3] + dz[None]
    inside = (y >= 0) & (y <= hi_c) & (z >= 0) & (z <= hi_c) & (base[:, 0:1] + reach >= 0) & (base[:, 0:1] - reach <= hi_c)
    row = (y << _CELL_BITS) + (z << (2 * _CELL_BITS))
    lo, hi = x0 + row, x1 + row  # (n, R) code range of each row
    start = jnp.searchsorted(codes, lo.reshape(-1), side="left").reshape(lo.shape)
    width = (2 * reach + 1) * per_cell
    idx = jnp.minimum(start[..., None] + jnp.arange(width), points.shape[0] - 1)  # (n, R, width)
    c = codes[idx]
    hit = inside[..., None] & (c >= lo[..., None]) & (c <= hi[..., None])
    d2 = jnp.where(hit, jnp.sum((points[idx] - q[:, None, None, :]) ** 2, -1), jnp.inf).reshape(q.shape[0], -1)
    k = first_argmin(d2, 1)
    n = jnp.arange(q.shape[0])
    return idx.reshape(q.shape[0], -1)[n, k], d2[n, k]
