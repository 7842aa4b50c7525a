"""The ICP target index: a cached nested grid, exact radius search, the k-nearest-neighbour graph and
the warm-started graph walk used by :mod:`cm3d.solvers.icp`.

:func:`build_target_index` builds, once per target cloud (jit, fixed capacities):

* a *coarse* grid whose cell is the index ``radius`` (the largest correspondence distance it
  serves): the target is sorted so that each coarse cell is a contiguous range; an exact nearest
  neighbour within ``r <= radius`` is among the 27 coarse cells around the query
  (:func:`nearest_within_radius`);
* a *fine* grid nested in it (cell ``radius / sub``, ``sub`` chosen from the point density so a cell
  holds about ``points_per_cell`` points) from which each point's k nearest neighbours are taken
  among the points of its 27 fine cells;
* the k-NN graph (self first), the coordinates of each point's neighbours laid out as one row
  ``(3, k)`` (a walk step is one row gather, XLA's fastest), PCA normals, and a *certified radius*
  ``rho``: every target point closer than ``rho[i]`` to point ``i`` is in its neighbour list.

The ICP correspondence search is a walk on the graph: a source point keeps its current match ``m``
and moves it to the closest of ``m``'s neighbours. When the walk stops at ``m`` with distance ``d``
and ``2 d < rho[m]``, ``m`` is provably the exact nearest neighbour (any closer point would lie within
``2 d`` of ``m``, hence in its list); :func:`certified_nearest` checks that and searches only the
remaining queries exactly: first in the table of the query's fine cell (the first ``max_candidates``
points of the 27 fine cells around it, kept from the build, or gathered from the fine grid when the
query's own cell is empty; exact when the nearest found is closer than the cells the table does not
hold), else in the coarse cells within ``1.3 d``. :func:`exact_nearest` also keeps a
:class:`NearestCache` of those searches: a query that moved less than half the gap between its
nearest and second-nearest point keeps its answer (ICP's last iterations barely move).

Plain grids, radius neighbourhoods and the grid nearest-neighbour search are in :mod:`cm3d.ops.grid`,
PCA normals in :mod:`cm3d.ops.normals` (both re-exported here). All positions returned by the walk
are *sorted* positions into ``index.points``; ``index.order`` maps them back to the caller's indices.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct
from jax import lax

from cm3d.ops.grid import (  # noqa: F401  (Grid, build_grid, radius_neighbors: re-exported)
    OFFSETS27,
    Grid,
    RadiusNeighbors,
    _cell_ranges,
    _cells_within,
    _gather_candidates,
    _range_candidates,
    build_grid,
    compact_apply,
    grid_candidates,
    radius_neighbors,
)
from cm3d.ops.normals import _pca_normals_soa, pca_normals  # noqa: F401  (pca_normals: re-exported)
from cm3d.ops.voxel import (
    EMPTY,
    CellHash,
    cell_coords,
    hash_insert,
    hash_lookup,
    masked_bounds,
    valid_points,
)

# The 27 cell offsets, nearest first (centre, 6 faces, 12 edges, 8 corners).
_MAX_SUB = 16


@struct.dataclass
class TargetIndex:
    """Everything ICP needs about a static target cloud, cached with a memory entry (a pytree).

    Sorted order (``M`` = capacity of the input cloud):
      points (M, 3), normals (M, 3) (zero where undefined), valid (M,), order (M,) input index of
      each sorted point, graph (M, k) sorted positions of the k nearest (self first), graph_pts
      (M, 3, k) their coordinates, rho (M,) certified radius of each list.
    Coarse grid (cell = ``radius``): coarse (CellHash), cell_start / cell_count / cell_seed (H,)
      per hash slot: first sorted position, number of points, the point nearest the cell centre.
    Fine grid (cell = ``fine_cell``, nested): fine (CellHash), fine_start / fine_count per slot;
      fine_row (H_f,) per slot: its row in block_cand (M, C) (the first C sorted positions of the
      27 fine cells around each occupied fine cell, nearest cells first) and block_total (M,) (how
      many points those 27 cells hold), block_full (M,) how many of those cells (nearest first) are
      complete in the row: the exact-search table (``C`` = ``max_candidates``).
    origin (3,), sub () int32 fine cells per coarse cell, fine_cell () metres.
    overflow () int32: hash keys that did not fit (0 in practice; results are not exact otherwise);
    truncated () int32: points whose k-NN candidates exceeded ``max_candidates`` (their list is
    exact only up to the nearest fine cell left out, which bounds rho).
    Static: radius (metres), k.
    """

    points: jnp.ndarray
    normals: jnp.ndarray
    valid: jnp.ndarray
    order: jnp.ndarray
    graph: jnp.ndarray
    graph_pts: jnp.ndarray
    rho: jnp.ndarray
    coarse: CellHash
    cell_start: jnp.ndarray
    cell_count: jnp.ndarray
    cell_seed: jnp.ndarray
    fine: CellHash
    fine_start: jnp.ndarray
    fine_count: jnp.ndarray
    fine_row: jnp.ndarray
    block_cand: jnp.ndarray
    block_total: jnp.ndarray
    block_full: jnp.ndarray
    origin: jnp.ndarray
    sub: jnp.ndarray
    fine_cell: jnp.ndarray
    overflow: jnp.ndarray
    truncated: jnp.ndarray
    radius: float = struct.field(pytree_node=False, default=0.0)
    k: int = struct.field(pytree_node=False, default=16)

    @property
    def num_valid(self):
        return jnp.sum(self.valid)


# --- Small helpers


def _sq_dist_soa(points, cand, q):
    """Squared distances (B, C) from queries q (B, 3) to points[cand] (cand (B, C)), gathered per
    coordinate (structure of arrays: XLA CPU gathers scalars much faster than (., 3) rows)."""
    d2 = 0.0
    for a in range(3):
        d2 = d2 + (points[:, a][cand] - q[:, a][:, None]) ** 2
    return d2


def _fine_keys(index_or_origin, q, fine_cell, sub):
    fk = cell_coords(q, index_or_origin, fine_cell)
    return fk, jnp.floor_divide(fk, sub)


def _unseen_gap2(q, fk, origin, cell, nfull):
    """Squared distance (B,) from queries q (B, 3) to the nearest of the 27 cells around their cell
    fk (B, 3) that is *not* among the first ``nfull`` (B,) (OFFSETS27 order); inf when all are."""
    lo = origin + (fk[:, None, :] + jnp.asarray(OFFSETS27)[None]).astype(q.dtype) * cell  # (B, 27, 3)
    gap = jnp.maximum(jnp.maximum(lo - q[:, None, :], q[:, None, :] - (lo + cell)), 0.0)
    g2 = jnp.sum(gap * gap, axis=-1)
    unseen = jnp.arange(27)[None, :] >= nfull[:, None]
    return jnp.min(jnp.where(unseen, g2, jnp.inf), axis=1)


# --- Build


def build_target_index(points, valid=None, *, radius: float, k: int = 16, cell_factor: float = 0.7,
                       max_candidates: int = 64) -> TargetIndex:
    """Build the :class:`TargetIndex` of a cloud (n, 3) (valid: optional (n,) mask), jittable.

    radius: static, metres: the coarse cell, i.e. the largest max-correspondence distance and
    exact-search radius the index serves. k: static graph degree (>= 2, self included).
    cell_factor: fine cell / estimated k-NN radius (density from the coarse occupancy);
    max_candidates: static cap of the k-NN candidates per point (>= k; points over it get
    ``rho = 0`` and an approximate list, counted in ``truncated``).
    """
    points = jnp.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (n, 3), got {points.shape}")
    if not radius > 0:
        raise ValueError(f"radius must be > 0, got {radius}")
    if k < 2:
        raise ValueError(f"k must be >= 2, got {k}")
    C = max(int(max_candidates), k)
    n = points.shape[0]
    dtype = points.dtype
    ok = valid_points(points, valid)
    if n == 0:
        return _empty_index(dtype, float(radius), k, C)
    lo, _ = masked_bounds(points, ok)
    origin = lo - 0.5 * radius

    # Density -> fine cell h ~ the k-NN radius of a surface sampled at that density; the coarse
    # cell is the multiple sub * h >= radius (fine cells nest in coarse ones).
    hc0, _ = hash_insert(cell_coords(points, origin, radius), ok)
    ncells = jnp.maximum(jnp.sum(hc0.slot_item != EMPTY), 1)
    nbar = jnp.maximum(jnp.sum(ok) / ncells, 1.0)
    sigma = nbar / (1.3 * radius**2)  # points per m^2 of surface
    rk = jnp.sqrt(k / (jnp.pi * sigma)) * cell_factor
    h = jnp.clip(rk, radius / _MAX_SUB, radius).astype(dtype)
    sub = jnp.ceil(radius / h).astype(jnp.int32)
    h = jnp.where(sub * h < radius, h * (1 + 1e-6), h)
    fk, ck = _fine_keys(origin, points, h, sub)
    hf, fslot = hash_insert(fk, ok)
    hc, cslot = hash_insert(ck, ok)

    # Sort: coarse cell, then fine cell (nested), invalid points last. Key: the coarse slot, then
    # the fine cell's place in its coarse cell (< sub^3 <= 4096), packed into one int32 when the
    # hash is small enough (one key sorts ~20 % faster than two on XLA CPU).
    big = jnp.int32(np.iinfo(np.int32).max)
    local = fk - ck * sub
    place = (local[:, 0] * sub + local[:, 1]) * sub + local[:, 2]
    iota = jnp.arange(n, dtype=jnp.int32)
    if hc.size * _MAX_SUB**3 < 2**31:
        _, order = lax.sort((jnp.where(ok, cslot * _MAX_SUB**3 + place, big), iota), num_keys=1)
    else:
        _, _, order = lax.sort((jnp.where(ok, cslot, big), jnp.where(ok, place, big), iota), num_keys=2)
    sp = points[order]
    sval = ok[order]
    pos = jnp.arange(n, dtype=jnp.int32)
    fs, cs = fslot[order], cslot[order]
    fine_start = jnp.full((hf.size,), n, jnp.int32).at[jnp.where(sval, fs, hf.size)].min(pos, mode="drop")
    fine_count = jnp.zeros((hf.size,), jnp.int32).at[jnp.where(sval, fs, hf.size)].add(1, mode="drop")
    cell_start = jnp.full((hc.size,), n, jnp.int32).at[jnp.where(sval, cs, hc.size)].min(pos, mode="drop")
    cell_count = jnp.zeros((hc.size,), jnp.int32).at[jnp.where(sval, cs, hc.size)].add(1, mode="drop")
    # Seed of a coarse cell: its point nearest to the cell centre.
    cks = ck[order]
    centre = origin + (cks.astype(dtype) + 0.5) * (h * sub)
    dc = jnp.sum((sp - centre) ** 2, axis=-1)
    big_f = jnp.asarray(np.finfo(np.float32).max, dtype)
    cmin = jnp.full((hc.size,), big_f, dtype).at[jnp.where(sval, cs, hc.size)].min(dc, mode="drop")
    is_best = sval & (dc <= cmin[jnp.clip(cs, 0, hc.size - 1)])
    cell_seed = jnp.full((hc.size,), n, jnp.int32).at[jnp.where(is_best, cs, hc.size)].min(pos, mode="drop")
    cell_seed = jnp.where(cell_seed < n, cell_seed, -1)

    # k-NN candidates, per occupied fine cell (a chunked loop over the cells that exist): the
    # points of its 27 fine cells, the first C of them.
    occupied = hf.slot_item != EMPTY
    (ucell,) = jnp.nonzero(occupied, size=n, fill_value=hf.size)
    ucount = jnp.sum(occupied)
    slot_to_u = jnp.zeros((hf.size,), jnp.int32).at[ucell].set(pos, mode="drop")
    j = jnp.arange(C, dtype=jnp.int32)

    def cell_candidates(i, _ok):
        key = hf.slot_key[jnp.clip(ucell[i], 0, hf.size - 1)]
        cand, _, total, nfull = _gather_candidates(hf, fine_start, fine_count, key, j, full_cells=True)
        return cand, total, nfull

    zi = jnp.zeros((n,), jnp.int32)
    ctab, ctot, cfull = compact_apply(pos < ucount, cell_candidates, (jnp.zeros((n, C), jnp.int32), zi, zi),
                                      chunk=1024)
    u = slot_to_u[jnp.clip(fs, 0, hf.size - 1)]
    cand = ctab[u]
    total = jnp.where(sval, ctot[u], 0)
    cvalid = j[None, :] < total[:, None]
    cand = jnp.where(cvalid, cand, pos[:, None])
    d2 = jnp.where(cvalid, _sq_dist_soa(sp, cand, sp), jnp.inf)
    neg, a = lax.top_k(-d2, k)
    graph = jnp.take_along_axis(cand, a, 1)
    d2k = -neg
    has = jnp.isfinite(d2k)
    graph = jnp.where(has, graph, pos[:, None])
    dk = jnp.sqrt(jnp.where(has[:, -1], d2k[:, -1], jnp.inf))
    truncated = sval & (total > C)
    # The 27 fine cells around a point's cell hold every point closer than h + (its distance to
    # its own cell's boundary), so a complete list is exact up to that or its k-th distance.
    # A truncated list holds the points of its leading full cells: it is exact up to the nearest
    # cell left out.
    fks = fk[order]
    lo_cell = origin + fks.astype(dtype) * h
    edge = jnp.min(jnp.minimum(sp - lo_cell, lo_cell + h - sp), axis=-1)
    unseen = compact_apply(truncated, lambda i, _ok: jnp.sqrt(_unseen_gap2(sp[i], fks[i], origin, h, cfull[u[i]])),
                           jnp.full((n,), jnp.inf, dtype), chunk=256)
    seen = jnp.minimum(h + jnp.maximum(edge, 0.0), unseen) * (1 - 1e-4)
    rho = jnp.where(sval, jnp.minimum(dk, seen), 0.0)

    # PCA normals over the neighbour list (self included), as Open3D's estimate_normals.
    nx, ny, nz = sp[:, 0][graph], sp[:, 1][graph], sp[:, 2][graph]  # (n, k) each
    normals = jnp.where(sval[:, None], _pca_normals_soa(nx, ny, nz, has), 0.0)

    overflow = hc0.overflow + hf.overflow + hc.overflow
    return TargetIndex(points=sp, normals=normals, valid=sval, order=order, graph=graph.astype(jnp.int32),
                       graph_pts=jnp.stack([nx, ny, nz], axis=1), rho=rho, coarse=hc, cell_start=cell_start,
                       cell_count=cell_count, cell_seed=cell_seed, fine=hf, fine_start=fine_start,
                       fine_count=fine_count, fine_row=jnp.where(occupied, slot_to_u, -1), block_cand=ctab,
                       block_total=ctot, block_full=cfull, origin=origin, sub=sub, fine_cell=h,
                       overflow=overflow.astype(jnp.int32), truncated=jnp.sum(truncated).astype(jnp.int32),
                       radius=float(radius), k=int(k))


def _empty_index(dtype, radius: float, k: int, max_candidates: int) -> TargetIndex:
    z = jnp.zeros
    hc = CellHash(slot_item=jnp.full((2,), EMPTY, jnp.int32), slot_key=z((2, 3), jnp.int32),
                  max_probe=jnp.int32(0), overflow=jnp.int32(0))
    return TargetIndex(points=z((0, 3), dtype), normals=z((0, 3), dtype), valid=z((0,), bool),
                       order=z((0,), jnp.int32), graph=z((0, k), jnp.int32), graph_pts=z((0, 3, k), dtype),
                       rho=z((0,), dtype), coarse=hc, cell_start=z((2,), jnp.int32), cell_count=z((2,), jnp.int32),
                       cell_seed=jnp.full((2,), -1, jnp.int32), fine=hc, fine_start=z((2,), jnp.int32),
                       fine_count=z((2,), jnp.int32), fine_row=jnp.full((2,), -1, jnp.int32),
                       block_cand=z((0, max_candidates), jnp.int32), block_total=z((0,), jnp.int32),
                       block_full=z((0,), jnp.int32),
                       origin=z((3,), dtype), sub=jnp.int32(1),
                       fine_cell=jnp.asarray(radius, dtype), overflow=jnp.int32(0), truncated=jnp.int32(0),
                       radius=radius, k=k)


# --- Queries


def _coarse_key(index: TargetIndex, q):
    return _fine_keys(index.origin, q, index.fine_cell, index.sub)[1]


def _top2(d2, cand):
    """(best position, its squared distance, second smallest squared distance) per row."""
    a = jnp.argmin(d2, axis=1)
    dmin = jnp.take_along_axis(d2, a[:, None], 1)[:, 0]
    second = jnp.min(jnp.where(jnp.arange(d2.shape[1])[None] == a[:, None], jnp.inf, d2), axis=1)
    return jnp.take_along_axis(cand, a[:, None], 1)[:, 0], dmin, second


def _exact_chunk(index: TargetIndex, q, radius, width: int = 128, dmax=None, with_second: bool = False):
    """Exact nearest within ``radius`` for queries q (B, 3) -> (pos (B,) or -1, squared dist (B,)).

    The candidates are the points of the 27 coarse cells around each query that come within
    ``bound = min(radius, dmax)`` (dmax (B,): a known upper bound of the nearest distance, up to
    one coarse cell), taken ``width`` at a time (a while loop over passes, as many as the most
    crowded query needs). with_second: also return a lower bound of the distance of every other
    point (the second nearest scanned, at most ``bound``) and of the nearest point (at most ``bound``).
    """
    B = q.shape[0]
    ck = _coarse_key(index, q)
    r2 = jnp.asarray(radius, q.dtype) ** 2
    cell = index.fine_cell * index.sub
    bound = jnp.broadcast_to(jnp.asarray(radius, q.dtype), (B,))
    if dmax is not None:
        bound = jnp.minimum(jnp.maximum(bound, dmax) if with_second else bound, dmax)
    bound = jnp.minimum(bound, cell)
    cmask = _cells_within(q, ck, index.origin, cell, bound)
    j0 = jnp.arange(width, dtype=jnp.int32)
    ranges = _cell_ranges(index.coarse, index.cell_start, index.cell_count, ck, cmask)  # once, not per pass
    total = ranges[2][:, -1]

    def cond(c):
        return c[0] * width < jnp.max(total, initial=0)

    def body(c):
        t, best, bd, sd = c
        cand, ok, _ = _range_candidates(ranges, t * width + j0)
        diff = index.points[cand] - q[:, None, :]
        d2 = jnp.where(ok, jnp.sum(diff * diff, axis=-1), jnp.inf)
        pmin, dmin, d2nd = _top2(d2, cand)
        better = (dmin < bd) | ((dmin == bd) & (pmin < best))
        sd = jnp.minimum(jnp.minimum(jnp.maximum(bd, dmin), sd), d2nd)
        return t + 1, jnp.where(better, pmin, best), jnp.minimum(bd, dmin), sd

    inf = jnp.full((B,), jnp.inf, q.dtype)
    init = (jnp.int32(0), jnp.full((B,), -1, jnp.int32), inf, inf)
    _, best, bd, sd = lax.while_loop(cond, body, init)
    inside = bd <= r2
    out = jnp.where(inside, best, -1), jnp.where(inside, bd, jnp.inf)
    if with_second:
        b2 = bound * bound
        return out + (jnp.minimum(bd, b2), jnp.minimum(sd, b2))
    return out


def _table_chunk(index: TargetIndex, q, dynamic: bool = False):
    """Nearest among the table candidates of the query's fine cell (the points of the 27 fine cells
    around it, ``index.block_cand``) for queries q (B, 3) -> (pos (B,) or -1, squared distance (B,),
    lower bound of the squared distance of every other point (B,), complete (B,): the answer is
    exact: the nearest lies closer than the block's boundary and than the cells the table row
    left out (a crowded block keeps its nearest cells), beyond which nothing was seen), has_row
    (B,): the query's fine cell holds target points, i.e. has a stored row).
    dynamic: gather the row from the fine grid instead (27 hash lookups: for queries whose own
    cell is empty, which have no stored row; same candidates and rule otherwise)."""
    h = index.fine_cell
    fk = cell_coords(q, index.origin, h)
    C = index.block_cand.shape[1]
    if dynamic:
        cand, ok, total, nfull = _gather_candidates(index.fine, index.fine_start, index.fine_count, fk,
                                                    jnp.arange(C, dtype=jnp.int32), full_cells=True)
        has_row = total > 0
        row = jnp.where(has_row, 0, -1)
    else:
        slot = hash_lookup(index.fine, fk)
        row = jnp.where(slot >= 0, index.fine_row[jnp.clip(slot, 0, index.fine.size - 1)], -1)
        has_row = row >= 0
        rc = jnp.clip(row, 0)
        cand = index.block_cand[rc]
        total = jnp.where(has_row, index.block_total[rc], 0)
        nfull = jnp.where(has_row, index.block_full[rc], 0)
        ok = jnp.arange(C, dtype=jnp.int32)[None, :] < total[:, None]
    d2 = jnp.where(ok, _sq_dist_soa(index.points, cand, q), jnp.inf)
    p, dmin, second = _top2(d2, cand)
    lo = index.origin + (fk - 1).astype(q.dtype) * h
    edge = jnp.min(jnp.minimum(q - lo, lo + 3 * h - q), axis=-1)
    edge = jnp.maximum(edge - 1e-4 * h - 8 * jnp.finfo(q.dtype).eps * jnp.max(jnp.abs(q), axis=-1), 0.0)
    e2 = edge * edge
    e2 = jnp.minimum(e2, _unseen_gap2(q, fk, index.origin, h, nfull))
    complete = has_row & (dmin <= e2)
    return jnp.where(jnp.isfinite(dmin), p, -1), dmin, jnp.minimum(second, e2), complete, has_row


def _check_radius(index: TargetIndex, radius):
    if radius is None:
        return index.radius
    if isinstance(radius, (int, float)) and radius > index.radius * (1 + 1e-6):
        raise ValueError(f"radius {radius} exceeds the index radius {index.radius}; rebuild the index")
    return jnp.minimum(jnp.asarray(radius), index.radius)


def nearest_within_radius(index: TargetIndex, queries, radius=None, valid=None, chunk: int = 512):
    """Exact nearest target point within ``radius`` (<= index.radius) of each query (q, 3).

    Returns (idx (q,) int32 input index of the target point or -1, dist (q,) metres or inf): the
    answer of a KD-tree (ties to the smaller sorted position). valid: optional (q,) query mask.
    """
    radius = _check_radius(index, radius)
    q = jnp.asarray(queries, index.points.dtype)
    m = valid_points(q, valid)
    if index.points.shape[0] == 0:
        return jnp.full(q.shape[:1], -1, jnp.int32), jnp.full(q.shape[:1], jnp.inf, q.dtype)
    init = (jnp.full(q.shape[:1], -1, jnp.int32), jnp.full(q.shape[:1], jnp.inf, q.dtype))
    pos, d2 = compact_apply(m, lambda i, ok: _exact_chunk(index, q[i], radius), init, chunk)
    idx = jnp.where(pos >= 0, index.order[jnp.clip(pos, 0)], -1)
    return idx, jnp.sqrt(d2)


def seed(index: TargetIndex, q, active, chunk: int = 512):
    """Initial matches (sorted positions, (N,)) for queries q (N, 3): a point of the query's fine
    cell, else the seed of its coarse cell, or for queries in an empty coarse cell the nearest seed
    of the 26 cells around (-1 if none). Only the queries a step misses pay for the next one
    (compacted)."""
    fs = hash_lookup(index.fine, cell_coords(q, index.origin, index.fine_cell))
    m = jnp.where(fs >= 0, index.fine_start[jnp.clip(fs, 0, index.fine.size - 1)], -1)

    def own(i, ok):
        s = hash_lookup(index.coarse, _coarse_key(index, q[i]))
        return jnp.where(s >= 0, index.cell_seed[jnp.clip(s, 0, index.coarse.size - 1)], -1)

    def around(i, ok):
        qq = q[i]
        sl = hash_lookup(index.coarse, _coarse_key(index, qq)[:, None, :] + jnp.asarray(OFFSETS27)[None])
        cand = jnp.where(sl >= 0, index.cell_seed[jnp.clip(sl, 0, index.coarse.size - 1)], -1)
        d2 = jnp.where(cand >= 0, jnp.sum((index.points[jnp.clip(cand, 0)] - qq[:, None]) ** 2, -1), jnp.inf)
        a = jnp.argmin(d2, axis=1)
        return jnp.where(jnp.isfinite(jnp.min(d2, axis=1)), jnp.take_along_axis(cand, a[:, None], 1)[:, 0], -1)

    m = compact_apply(active & (m < 0), own, m, chunk)
    return compact_apply(active & (m < 0), around, m, chunk)


def walk(index: TargetIndex, q, m):
    """One walk step: move each match m (N,) (sorted positions, -1 = none) to the closest of its
    graph neighbours to q (N, 3) -> (new m, squared distance (N,), changed (N,)).

    Ties go to the earlier list entry (as ``argmin``), found as the first entry equal to the
    minimum: a plain ``min`` reduction, cheaper on XLA CPU than a variadic ``argmin``."""
    mc = jnp.clip(m, 0)
    c = index.graph_pts[mc]  # (N, 3, k)
    d2 = (c[:, 0] - q[:, 0:1]) ** 2 + (c[:, 1] - q[:, 1:2]) ** 2 + (c[:, 2] - q[:, 2:3]) ** 2
    dm = jnp.min(d2, axis=1)
    k = d2.shape[1]
    a = jnp.min(jnp.where(d2 == dm[:, None], jnp.arange(k, dtype=jnp.int32)[None], k - 1), axis=1)
    new = jnp.take_along_axis(index.graph[mc], a[:, None], 1)[:, 0]
    has = m >= 0
    return jnp.where(has, new, -1), jnp.where(has, dm, jnp.inf), has & (new != m)


def walk_to_convergence(index: TargetIndex, q, m, max_steps: int = 16, full_steps: int = 2,
                        chunk: int = 256, return_moved: bool = False):
    """Walk steps until no match moves (at most ``max_steps``) -> (m, squared distance), and with
    ``return_moved`` also whether each match's last step moved it (False: m is a local minimum
    of the walk, its own list scanned).

    The first ``full_steps`` steps move every query; the few still moving after them walk on in
    compacted chunks (the tail of a walk is short but would otherwise cost full steps)."""
    full = max(1, min(full_steps, max_steps))
    for _ in range(full):
        m, d2, ch = walk(index, q, m)
    if max_steps <= full:
        return (m, d2, ch) if return_moved else (m, d2)

    def fn(i, ok):
        qi = q[i]

        def cond(c):
            return (c[3] < max_steps - full) & jnp.any(c[2] & ok)

        def body(c):
            mm, _, _, it = c
            m2, dd, chi = walk(index, qi, mm)
            return m2, dd, chi, it + 1

        mm, dd, chi, _ = lax.while_loop(cond, body, (m[i], d2[i], ch[i], jnp.int32(0)))
        return mm, dd, chi

    m, d2, ch = compact_apply(ch, fn, (m, d2, ch), chunk)
    return (m, d2, ch) if return_moved else (m, d2)


@struct.dataclass
class NearestCache:
    """The last exact grid-search answers of a set of queries, reusable while a query stays within
    ``slack`` of where it was searched: q (N, 3) query positions then, pos (N,) the answer (sorted
    position, -1: nothing within the radius), slack (N,) metres (< 0: nothing cached)."""

    q: jnp.ndarray
    pos: jnp.ndarray
    slack: jnp.ndarray


def empty_cache(q) -> NearestCache:
    """A :class:`NearestCache` for queries like q (N, 3) that holds nothing."""
    return NearestCache(q=jnp.zeros_like(q), pos=jnp.full(q.shape[:1], -1, jnp.int32),
                        slack=jnp.full(q.shape[:1], -1.0, q.dtype))


def certified_nearest(index: TargetIndex, q, m, d2, active, radius, chunk: int = 512, settled=None):
    """Exact nearest within ``radius`` given walk matches (m, d2): keep a match when the graph
    certifies it (``2 d < rho[m]``: m is the nearest; or ``d + radius < rho[m]`` with ``d > radius``:
    nothing within radius), search the rest exactly: the fine cells within the walk distance when
    it is below the fine cell (and they are not crowded), else the coarse cells.
    settled: optional (N,) bool, where m is known to be a local minimum of the walk (the last walk
    step did not move it; default all): only those are certified (the certificate needs m's own
    list to have been scanned).
    -> (pos (N,) sorted position or -1, squared distance (N,) or inf, number searched exactly)."""
    return exact_nearest(index, q, m, d2, active, radius, None, chunk, settled)[:3]


def exact_nearest(index: TargetIndex, q, m, d2, active, radius, cache: NearestCache | None, chunk: int = 512,
                  settled=None):
    """:func:`certified_nearest` that also reuses the answers of a :class:`NearestCache` (a query
    that moved by ``delta < slack`` since its search keeps its answer: every other point was at
    least ``2 slack`` farther, resp. nothing within ``radius + slack``) and returns the cache
    updated with this call's searches -> (pos, squared distance, number searched, cache).
    cache None: nothing cached (as :func:`empty_cache`, without the work of checking it)."""
    mc = jnp.clip(m, 0)
    rho = jnp.where(m >= 0, index.rho[mc], 0.0)
    d = jnp.sqrt(d2)
    sure_in = d < 0.5 * rho
    sure_out = (d > radius) & (d + radius < rho)
    if settled is not None:
        sure_in, sure_out = sure_in & settled, sure_out & settled
    need = active & ~(sure_in | sure_out)
    inside = active & sure_in & (d <= radius)
    pos = jnp.where(inside, m, -1)
    dist2 = jnp.where(inside, d2, jnp.inf)
    if index.points.shape[0] == 0:
        return pos, dist2, jnp.int32(0), empty_cache(q) if cache is None else cache
    r = jnp.asarray(radius, q.dtype)
    r2 = r * r
    if cache is not None:
        # Cached answers still valid.
        eps = 8 * jnp.finfo(q.dtype).eps * (jnp.max(jnp.abs(q), axis=-1) + r)  # rounding margin
        reuse = need & (jnp.sqrt(jnp.sum((q - cache.q) ** 2, axis=-1)) + eps < cache.slack)
        cd2 = jnp.sum((index.points[jnp.clip(cache.pos, 0)] - q) ** 2, axis=-1)
        hit = reuse & (cache.pos >= 0) & (cd2 <= r2)
        pos = jnp.where(hit, cache.pos, pos)
        dist2 = jnp.where(hit, cd2, dist2)
        need = need & ~reuse
    else:
        cache = empty_cache(q)
    # The table of the query's fine cell (the points of the 27 fine cells around it) answers
    # exactly when the nearest is closer than the block's boundary; the rest searches the coarse
    # cells within the walk distance.

    def slack(p, dd, lb2):
        return jnp.where(p >= 0, 0.5 * (jnp.sqrt(lb2) - jnp.sqrt(dd)), jnp.sqrt(lb2) - r)

    def table(dynamic):
        def fn(i, ok):
            p, dd, lb2, complete, has_row = _table_chunk(index, q[i], dynamic)
            inside = dd <= r2
            p = jnp.where(inside, p, -1)
            return p, jnp.where(inside, dd, jnp.inf), complete, has_row, jnp.where(inside, slack(p, dd, lb2), -1.0)
        return fn

    init = (pos, dist2, jnp.zeros_like(need), jnp.zeros_like(need), jnp.full_like(d, -1.0))
    pos, dist2, complete, has_row, sl = compact_apply(need, table(False), init, chunk)
    # queries in an empty fine cell (no stored row): the same table gathered from the fine grid
    pos, dist2, complete, _, sl = compact_apply(need & ~has_row, table(True), (pos, dist2, complete, has_row, sl),
                                                max(chunk // 2, 1))
    coarse = need & ~complete

    # the nearest lies within the walk distance and within the table's nearest (when it found one)
    dbound = jnp.sqrt(jnp.minimum(d2, dist2))

    def far(i, ok):
        p, dd, lb1, lb2 = _exact_chunk(index, q[i], radius, dmax=1.3 * dbound[i], with_second=True)
        return p, dd, jnp.where(p >= 0, slack(p, dd, lb2), jnp.sqrt(lb1) - r)

    pos, dist2, sl = compact_apply(coarse, far, (pos, dist2, sl), max(chunk // 4, 1))
    new = NearestCache(q=jnp.where(need[:, None], q, cache.q), pos=jnp.where(need, pos, cache.pos),
                       slack=jnp.where(need, sl, cache.slack))
    return pos, dist2, jnp.sum(need).astype(jnp.int32), new


# --- Convenience on plain clouds


def knn_graph(index: TargetIndex):
    """The k-NN graph in input indices -> (nbr (n, k) input index per input point, exact (n,) bool:
    the list is the exact k nearest, i.e. its k-th distance is below the certified radius)."""
    n = index.points.shape[0]
    inv = jnp.zeros((n,), jnp.int32).at[index.order].set(jnp.arange(n, dtype=jnp.int32))
    g = index.order[index.graph][inv]
    dk = jnp.sqrt(jnp.sum((index.graph_pts[:, :, -1] - index.points) ** 2, axis=-1))
    full = index.graph[:, -1] != jnp.arange(n, dtype=jnp.int32)  # k found (padding repeats self)
    exact = (index.valid & full & (dk <= index.rho))[inv]
    return g, exact


def estimate_normals(points, valid=None, k: int = 16, radius: float | None = None):
    """PCA normals (n, 3) over the k nearest neighbours (self included), up to sign, as Open3D's
    ``estimate_normals(KDTreeSearchParamKNN(k))``; zero where fewer than 3 neighbours.
    radius: static coarse cell of the temporary index (default: 1/16 of the largest extent)."""
    points = jnp.asarray(points)
    if radius is None:
        p = np.asarray(points)
        m = np.all(np.isfinite(p), axis=1) if valid is None else np.asarray(valid, bool)
        ext = float(np.max(np.ptp(p[m], axis=0))) if m.any() else 1.0
        radius = max(ext / 16.0, 1e-6)
    index = build_target_index(points, valid, radius=radius, k=k)
    n = points.shape[0]
    inv = jnp.zeros((n,), jnp.int32).at[index.order].set(jnp.arange(n, dtype=jnp.int32))
    return index.normals[inv]
