"""Geometric verification of a candidate map, the paper's three stages: keypoint matching ->
Sim(3) RANSAC (:func:`keypoint_poses`) -> ICP validation of the best-screened pose (:func:`refine_pose`)
-> decision (:func:`decide`). :func:`verify` runs them for one map."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from cm3d.memory.bank import GRID_CELL, MemoryBank, map_cloud
from cm3d.memory.config import MemoryConfig
from cm3d.memory.entry import Keypoints, MapEntry, fit_keypoints
from cm3d.memory.matching import keypoint_clusters, nearest_descriptors, up_axis
from cm3d.ops import sim3
from cm3d.ops.grid import grid_nearest
from cm3d.solvers.icp import icp_grid
from cm3d.solvers.ransac import sim3_consensus, triangle_hypotheses, upright_frame, upright_pairs


@struct.dataclass
class Verification:
    """Geometric verification of one candidate map: accepted; transform (4, 4) query -> map
    (Sim(3) ``[s R, t]``) and its scale; keypoint ``matches`` and RANSAC ``keypoint_inliers``;
    ICP ``fitness`` (share of the query's ICP points with a map point within ``icp_distance``),
    ``inlier_count``, ``inlier_rmse`` (map units) and ``colour_agreement`` (share of ICP inliers
    whose stored colour agrees with the query's)."""

    accepted: jax.Array
    transform: jax.Array
    scale: jax.Array
    matches: jax.Array
    keypoint_inliers: jax.Array
    fitness: jax.Array
    inlier_count: jax.Array
    inlier_rmse: jax.Array
    colour_agreement: jax.Array


def even_subsample(points, valid, n: int):
    """``n`` of the valid points, evenly spread over them (the first n when fewer): points (n, 3), valid
    (n,) and their indices (n,) (slots past the valid count hold invalid points, masked). The k-th
    valid point is found by a binary search of the running count, not by sorting the mask (a sort of
    8192 flags cost as much as the screening it feeds)."""
    valid = jnp.asarray(valid, bool)
    count = jnp.sum(valid)
    i = jnp.arange(n)
    pos = jnp.where(count > n, (i * count) // n, i)
    first_valid = jnp.searchsorted(jnp.cumsum(valid), pos + 1)  # the first index whose running count is pos + 1
    first_invalid = jnp.searchsorted(jnp.cumsum(~valid), pos - count + 1)
    idx = jnp.minimum(jnp.where(pos < count, first_valid, first_invalid), valid.shape[0] - 1)
    return points[idx], i < count, idx


def query_keypoints(entry: MapEntry, cfg: MemoryConfig):
    """The query's keypoints (none: three invalid ones), its floor keypoints (None when it has none or
    the bank holds none: ``cfg.max_floor_keypoints == 0``), the :func:`keypoint_clusters` of both
    (image keypoints first), its upright frame (:func:`upright_frame` of :func:`up_axis`) and the
    cluster separation (query units)."""
    kp = fit_keypoints(None, 3, cfg.keypoint_dim) if entry.keypoints is None else entry.keypoints
    floor = entry.floor_keypoints if cfg.max_floor_keypoints > 0 else None
    sep = cfg.cluster_separation * jnp.maximum(jnp.asarray(entry.voxel_size, jnp.float32), 1e-12)
    frame = upright_frame(up_axis(entry.normals, entry.point_valid, cfg.up_prior, cfg.up_max_angle))
    both = kp if floor is None else jax.tree.map(lambda a, b: jnp.concatenate([a, b]), kp, floor)
    return kp, floor, keypoint_clusters(both.points, both.valid, sep), frame, sep


def keypoint_poses(bank: MemoryBank, m, query: Keypoints, floor: Keypoints | None, cluster, frame_q, sep_q,
                    cfg: MemoryConfig, key):
    """Match the query's keypoints with map ``m``'s and fit Sim(3) by RANSAC: (T (G, 4, 4), scale
    (G,), strict matches, distinct inliers (G,), the scored matches (src (S, 3), dst (S, 3), valid (S,):
    one per query keypoint cluster, what :func:`cm3d.memory.acceptance.chance_test` shuffles)), one
    pose per hypothesis generator (G = 1, or 2 with
    ``cfg.upright_hypotheses``: the triangle RANSAC's, then the upright pairs'). Triangle hypotheses
    come from the strict matches (mutual + ratio test); they are scored on the strict and the loose
    matches (mutual, descriptor distance below ``cfg.loose_descriptor``, no ratio test), one per
    query keypoint cluster (its best match; at most ``cfg.ransac_scored``), so a hypothesis is
    scored by distinct 3D points, not by views of one point. ``cluster``: :func:`keypoint_clusters`
    of the query. With ``cfg.upright_hypotheses`` a second consensus
    draws 2-point hypotheses (:func:`upright_pairs`) from the strict *and* loose matches, given the
    query's upright frame ``frame_q`` and the map's (both :func:`upright_frame` of :func:`up_axis`),
    scored the same way; pairs closer than ``sep_q`` (query units: one cluster) are not drawn.
    ``floor`` (None: none): the query's floor keypoints, matched with the map's floor keypoints only
    (another kind of descriptor); their matches join the image keypoints' (``cluster`` covers both,
    image keypoints first)."""
    vs = jnp.maximum(bank.voxel_size[m], 1e-12)
    thr = cfg.ransac_distance * vs
    kinds = [(query, Keypoints(bank.kp_points[m], bank.kp_desc[m], bank.kp_valid[m]))]
    if floor is not None:
        kinds.append((floor, Keypoints(bank.floor_kp_points[m], bank.floor_kp_desc[m], bank.floor_kp_valid[m])))
    parts = []
    for q, mk in kinds:  # (match_keypoints per kind)
        j, best, mutual, ratio_ok = nearest_descriptors(q, mk, cfg.ratio, thr)
        parts.append((q.points, mk.points[j], q.valid & mutual & ratio_ok, q.valid & mutual, best))
    src, dst, strict, mutual, best = (jnp.concatenate(x) for x in zip(*parts))
    n = jnp.arange(src.shape[0])
    ok = strict | (mutual & (best < cfg.loose_descriptor**2))
    rank = jnp.where(ok, best, jnp.inf)
    tops = ok & (rank <= jax.ops.segment_min(rank, cluster, num_segments=n.shape[0])[cluster])
    first = jax.ops.segment_min(jnp.where(tops, n, n.shape[0]), cluster, num_segments=n.shape[0])
    rep = tops & (first[cluster] == n)  # one per cluster: its best match (ties: the first)
    # the scored matches, compacted: the ransac_scored closest in descriptor space when there are more
    sel = jnp.argsort(jnp.where(rep, best, jnp.inf), stable=True)[: min(cfg.ransac_scored, n.shape[0])]
    scored = (src[sel], dst[sel], rep[sel])
    gens = [triangle_hypotheses(src, dst, strict, key, cfg.ransac_hypotheses)]
    if cfg.upright_hypotheses:
        frame_m = upright_frame(up_axis(bank.normals[m], bank.point_valid[m], cfg.up_prior, cfg.up_max_angle))
        gens.append(upright_pairs(src, dst, ok, jax.random.fold_in(key, 1), cfg.upright_hypotheses, frame_q, frame_m,
                                  sep_q, cfg.scale_range))
    # one scored match per query cluster: inliers are distinct 3D points, and a plain count counts them
    Ts, scales, inls = zip(*(sim3_consensus(*scored[:2], h, scored[2], thr, cfg.scale_range) for h in gens))
    inls = jnp.sum(jnp.stack(inls), -1)
    return jnp.stack(Ts), jnp.stack(scales), jnp.sum(strict).astype(jnp.int32), inls.astype(jnp.int32), scored


def screen_poses(bank: MemoryBank, m, entry: MapEntry, Ts, cfg: MemoryConfig):
    """Colour-consistent overlap (G,) of the query under each pose Ts (G, 4, 4): how many of
    ``cfg.screen_points`` query voxels have a map point within one grid cell whose colour agrees
    (one nearest-neighbour step, no ICP)."""
    src, sv, idx = even_subsample(entry.points, entry.point_valid, cfg.screen_points)
    mc = map_cloud(bank, m)
    cell = GRID_CELL * jnp.maximum(mc.voxel_size, 1e-12)

    def one(T):
        j, d2 = grid_nearest(src @ T[:3, :3].T + T[:3, 3], mc.points, mc.valid, cell, per_cell=cfg.grid_per_cell)
        dc = jnp.linalg.norm(entry.colors[idx].astype(jnp.float32) - mc.colors[j].astype(jnp.float32), axis=-1)
        return jnp.sum(sv & (d2 < cell**2) & (dc <= cfg.max_colour_difference))

    return jax.vmap(one)(Ts)


def icp_validation(bank: MemoryBank, m, entry: MapEntry, init, cfg: MemoryConfig):
    """ICP of an even subsample of the query's voxels against map ``m`` from ``init``: (T, inlier count,
    fitness, rmse, colour agreement: share of inliers whose colour is within ``cfg.max_colour_difference``
    of their map point's). With ``cfg.icp_scale`` False (the default) T keeps ``init``'s scale (the
    keypoints' RANSAC scale) and ICP fits rotation and translation; True fits Sim(3), whose scale a
    partial overlap of voxel maps pulls down (docs/memory.md, stop 48)."""
    src, sv, idx = even_subsample(entry.points, entry.point_valid, cfg.icp_points)
    mc = map_cloud(bank, m)
    cell = GRID_CELL * jnp.maximum(mc.voxel_size, 1e-12)
    # without icp_scale the query is scaled by the keypoints' scale and fitted rigidly from init's rigid part
    s0 = 1.0 if cfg.icp_scale else sim3.scale(init)
    r = icp_grid(src * s0, sv, mc.points, mc.valid, init if cfg.icp_scale else sim3.to_rigid(init), distance=cell,
                 iterations=cfg.icp_iterations, cell=cell, per_cell=cfg.grid_per_cell, with_scale=cfg.icp_scale)
    dc = jnp.linalg.norm(entry.colors[idx].astype(jnp.float32) - mc.colors[r.matches].astype(jnp.float32), axis=-1)
    agree = jnp.sum(r.inliers & (dc <= cfg.max_colour_difference)) / jnp.maximum(r.inlier_count, 1)
    return r.transform.at[:3, :3].multiply(s0), r.inlier_count, r.fitness, r.inlier_rmse, agree


def decide(bank, m, T, scale, matches, kp_inliers, icp, cfg: MemoryConfig) -> Verification:
    """Acceptance per ``cfg.verification`` (see :func:`verify`)."""
    vs = jnp.maximum(bank.voxel_size[m], 1e-12)
    present = (m >= 0) & bank.map_valid[jnp.maximum(m, 0)]
    if cfg.verification == "none":
        eye = jnp.eye(4, dtype=jnp.float32)
        z = jnp.zeros((), jnp.float32)
        return Verification(accepted=present, transform=eye, scale=jnp.ones((), jnp.float32), matches=matches,
                            keypoint_inliers=kp_inliers, fitness=z, inlier_count=jnp.zeros((), jnp.int32), inlier_rmse=z,
                            colour_agreement=z)
    ok = present & (kp_inliers >= cfg.min_keypoint_inliers) & jnp.all(jnp.isfinite(T))
    if icp is None:
        z = jnp.zeros((), jnp.float32)
        return Verification(accepted=ok, transform=T, scale=scale, matches=matches, keypoint_inliers=kp_inliers,
                            fitness=z, inlier_count=jnp.zeros((), jnp.int32), inlier_rmse=z, colour_agreement=z)
    T2, count, fitness, rmse, agree = icp
    scale2 = sim3.scale(T2)
    ok = (ok & (count >= cfg.min_inliers) & (fitness >= cfg.min_fitness) & (rmse <= cfg.max_rmse * vs)
          & (agree >= cfg.min_colour_agreement) & (jnp.abs(jnp.log(scale2 / jnp.maximum(scale, 1e-12))) < 0.2)
          & (scale2 >= cfg.scale_range[0]) & (scale2 <= cfg.scale_range[1]) & jnp.all(jnp.isfinite(T2)))
    return Verification(accepted=ok, transform=T2, scale=scale2, matches=matches, keypoint_inliers=kp_inliers,
                        fitness=fitness, inlier_count=count.astype(jnp.int32), inlier_rmse=rmse, colour_agreement=agree)


def refine_pose(bank, m, entry: MapEntry, Ts, scales, matches, inliers, cfg: MemoryConfig):
    """Verify candidate ``m`` (-1: none) from its keypoint poses Ts (G, 4, 4) (:func:`keypoint_poses`):
    with ICP (``cfg.verification == "full"``) the pose with the largest colour-consistent overlap
    (:func:`screen_poses`; a wrong pose of a box room can fit its geometry well, but rarely its
    colours) is refined by ICP, else the one with most keypoint inliers; then :func:`decide`.
    Returns (Verification, the chosen pose's screening overlap as a share of ``cfg.screen_points``
    (0 without ICP), its RANSAC scale): the last two feed :func:`acceptance_features`."""
    mm = jnp.maximum(m, 0)
    if cfg.verification != "full":
        g = jnp.argmax(inliers)
        return (decide(bank, m, Ts[g], scales[g], matches, inliers[g], None, cfg), jnp.zeros((), jnp.float32),
                scales[g])
    screen = screen_poses(bank, mm, entry, Ts, cfg)
    g = jnp.argmax(screen * (cfg.ransac_scored + 1) + inliers)  # colour-consistent overlap first, inliers break ties
    icp = icp_validation(bank, mm, entry, Ts[g], cfg)
    return (decide(bank, m, Ts[g], scales[g], matches, inliers[g], icp, cfg), screen[g] / cfg.screen_points,
            scales[g])


def verify(bank: MemoryBank, map_id, entry: MapEntry, cfg: MemoryConfig, key) -> Verification:
    """Verify that the query ``entry`` (its own frame and scale) shows map ``map_id``.

    1. keypoint matches (:func:`match_keypoints`) and Sim(3) RANSAC (3-point hypotheses, plus
       ``cfg.upright_hypotheses`` 2-point ones about both frames' up axes, :func:`upright_pairs`;
       scored by distinct 3D points, see :func:`keypoint_poses`): at least
       ``cfg.min_keypoint_inliers`` distinct inliers within ``cfg.ransac_distance`` map voxels;
    2. (``cfg.verification == "full"``) of the RANSAC poses the one with the most colour-consistent
       overlap (:func:`screen_poses`) is refined by ICP (at its scale, see :func:`icp_validation`) of
       ``cfg.icp_points`` query voxels against the map's (:func:`cm3d.solvers.icp.icp_grid`), accepted
       on absolute inlier count
       (``cfg.min_inliers``), fitness (``cfg.min_fitness``) and inlier RMSE (``cfg.max_rmse`` voxels).
    Geometry is what rejects look-alike scenes. ``cfg.verification == "none"`` accepts any stored map.
    These thresholds decide here; :func:`identify` decides by its acceptance model instead (it needs
    the 2D recall's scores, which a single-map check does not have).
    """
    m = jnp.maximum(map_id, 0)
    Ts, scales, matches, inliers, _ = keypoint_poses(bank, m, *query_keypoints(entry, cfg), cfg, key)
    return refine_pose(bank, jnp.where(map_id >= 0, m, -1), entry, Ts, scales, matches, inliers, cfg)[0]
