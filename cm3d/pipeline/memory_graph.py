"""Recall / verify / update inside the window: identify the refined window, hold its landmarks on the
recalled surface in a second LM solve (kept when a χ² test accepts it), update the bank."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct
from jax.scipy.special import betainc

from cm3d import memory, trajectory
from cm3d.ops import robust, sim3, warp
from cm3d.pipeline import photometric as ph
from cm3d.pipeline.config import PipelineConfig
from cm3d.pipeline.state import Landmarks, MemoryCursor, Window
from cm3d.pipeline.window import chi2_threshold, rescale_window, structure_only_cost
from cm3d.solvers import factors, lm


@struct.dataclass
class RecallReport:
    """One window's memory decision: the recall's candidates (top_k,) (-1 none) with votes, scores
    and keypoint inliers; the verification (accepted, recalled map, inliers, RMSE, fitness, scale,
    its Sim(3) ``transform`` query -> map); the map written (-1 bank full), created; ``placement``:
    the Sim(3) sequence -> map the memory priors and the merge used; the acceptance tests of the
    verified candidate: the model's ``acceptance`` score (accept >= 0; NaN without a model), the chance
    test's ``pose_inliers`` / ``chance_inliers`` and ``log_nfa`` (accept < ``max_log_nfa``), and the
    ``placement_error`` of the final pose's keypoint inliers."""

    candidates: Any
    votes: Any
    scores: Any
    keypoint_inliers: Any
    accepted: Any
    recalled: Any
    inlier_count: Any
    inlier_rmse: Any
    fitness: Any
    scale: Any
    transform: Any
    map_id: Any
    created: Any
    placement: Any = None
    acceptance: Any = None
    pose_inliers: Any = None
    chance_inliers: Any = None
    log_nfa: Any = None
    placement_error: Any = None

    @classmethod
    def empty(cls, top_k: int) -> "RecallReport":
        zi = jnp.zeros(top_k, jnp.int32)
        return cls(candidates=zi - 1, votes=jnp.zeros(top_k), scores=jnp.zeros(top_k), keypoint_inliers=zi,
                   accepted=jnp.zeros((), bool), recalled=-jnp.ones((), jnp.int32),
                   inlier_count=jnp.zeros((), jnp.int32), inlier_rmse=jnp.zeros(()), fitness=jnp.zeros(()),
                   scale=jnp.ones(()), transform=jnp.eye(4, dtype=jnp.float32),
                   map_id=-jnp.ones((), jnp.int32), created=jnp.zeros((), bool),
                   placement=jnp.eye(4, dtype=jnp.float32), acceptance=jnp.full((), jnp.nan, jnp.float32),
                   pose_inliers=jnp.zeros((), jnp.int32), chance_inliers=jnp.zeros((), jnp.float32),
                   log_nfa=jnp.zeros((), jnp.float32), placement_error=jnp.full((), jnp.inf, jnp.float32))


@struct.dataclass
class MemoryStep:
    """What the memory did to one window: final poses (W, 4, 4), report, landmarks held on the
    remembered surface, whether the memory solution was used, its χ² test (stat, threshold) and its
    photometric test (grey error of the memory-free and the memory solution, and the sign test's p-value,
    :func:`photometric_test`)."""

    poses: Any
    report: RecallReport
    landmarks: Any
    used: Any
    stat: Any
    threshold: Any
    photo_free: Any
    photo_memory: Any
    photo_p: Any

    @classmethod
    def off(cls, poses, top_k: int) -> "MemoryStep":
        """Memory switched off: the memory-free poses, an empty report."""
        z = jnp.zeros((), jnp.float32)
        return cls(poses=poses, report=RecallReport.empty(top_k), landmarks=jnp.zeros((), jnp.int32),
                   used=jnp.zeros((), bool), stat=z, threshold=z, photo_free=z, photo_memory=z, photo_p=z)


def window_entry(win: Window, mem_cfg: memory.MemoryConfig, cfg: PipelineConfig,
                 min_support: float = 0.0) -> memory.MapEntry:
    """The window as a memory entry (:func:`cm3d.memory.build_entry`): static cloud, keyframe
    descriptors and 3D keypoints posed by ``win.poses``; ``min_support``: see ``map_min_support``."""
    cloud_cfg = dataclasses.replace(mem_cfg, pixel_stride=max(1, mem_cfg.pixel_stride // cfg.stride))
    static = win.static & win.valid[:, None, None]
    cloud = memory.sequence_cloud(win.depth, win.conf, win.intrinsic, win.poses, win.image, static, cloud_cfg)
    idx, kv = memory.select_keyframes(win.desc, win.valid, cfg.keyframe_threshold, mem_cfg.max_keyframes)
    fvalid = win.feat_valid & win.valid[:, None]
    kp = memory.lift_keypoints(win.feat_uv, win.feat_desc, fvalid, win.depth, win.intrinsic, win.poses,
                               mem_cfg.max_keypoints)
    return memory.build_entry(cloud, win.desc[idx], kv, mem_cfg, keypoints=kp, min_support=min_support)


def recall_report(ident: memory.Identification, map_id, transform, created, placement) -> RecallReport:
    """The :class:`RecallReport` of an identification and the update that followed it."""
    rc, ver = ident.recall, ident.verification
    cand = rc.candidates
    safe = jnp.maximum(cand, 0)
    return RecallReport(
        candidates=cand.astype(jnp.int32), votes=jnp.where(cand >= 0, rc.votes[safe], 0.0).astype(jnp.float32),
        scores=jnp.where(cand >= 0, rc.scores[safe], 0.0).astype(jnp.float32),
        keypoint_inliers=ident.candidate_inliers.astype(jnp.int32),
        accepted=ident.map_id >= 0, recalled=ident.map_id.astype(jnp.int32),
        inlier_count=ver.inlier_count.astype(jnp.int32), inlier_rmse=ver.inlier_rmse.astype(jnp.float32),
        fitness=ver.fitness.astype(jnp.float32), scale=ver.scale.astype(jnp.float32),
        transform=jnp.asarray(transform, jnp.float32), map_id=jnp.asarray(map_id, jnp.int32),
        created=jnp.asarray(created, bool), placement=jnp.asarray(placement, jnp.float32),
        acceptance=(jnp.full((), jnp.nan, jnp.float32) if ident.acceptance is None
                    else jnp.asarray(ident.acceptance, jnp.float32)),
        pose_inliers=jnp.asarray(0 if ident.pose_inliers is None else ident.pose_inliers, jnp.int32),
        chance_inliers=jnp.asarray(0.0 if ident.chance_inliers is None else ident.chance_inliers, jnp.float32),
        log_nfa=jnp.asarray(0.0 if ident.log_nfa is None else ident.log_nfa, jnp.float32),
        placement_error=jnp.asarray(jnp.inf if ident.placement_error is None else ident.placement_error,
                                    jnp.float32))


def memory_surface(bank: memory.MemoryBank, map_id, transform, d_scene) -> trajectory.MemorySurface:
    """Map ``map_id`` moved into the sequence's frame (inverse of the Sim(3) ``transform``
    sequence -> map) as a :class:`cm3d.trajectory.MemorySurface` (empty when ``map_id < 0``)."""
    cloud = memory.map_cloud(bank, map_id)
    T = transform.astype(jnp.float32)
    scale = jnp.maximum(sim3.scale(T), 1e-12)
    R = T[:3, :3] / scale
    return trajectory.MemorySurface(points=sim3.apply(sim3.inverse(T), cloud.points),
                                    normals=cloud.normals @ R,  # map -> sequence: R^T n, as rows
                                    valid=cloud.valid, voxel=cloud.voxel_size / scale,
                                    d_scene=jnp.asarray(d_scene, jnp.float32))


def sequence_query(bank: memory.MemoryBank, written, entry: memory.MapEntry, mem_cfg: memory.MemoryConfig):
    """The identification's query: the window's entry merged with the map its sequence stored so far
    (``written``, in the sequence's frame: the sequence up to this window); the entry alone when
    ``written < 0``."""
    m = jnp.maximum(written, 0)
    merged = jax.lax.cond(written >= 0,
                          lambda b: memory.update_map(b, m, entry, jnp.eye(4, dtype=jnp.float32), mem_cfg,
                                                      same_frame=True), lambda b: b, bank)
    return _query_of(merged, written, entry)


def _query_of(merged: memory.MemoryBank, written, entry: memory.MapEntry) -> memory.MapEntry:
    """:func:`sequence_query` from the bank after the merge (``merged``, any bank when ``written < 0``)."""
    return jax.lax.cond(written >= 0, lambda: memory.stored_entry(merged, written).replace(
        floor_keypoints=entry.floor_keypoints), lambda: entry)


def memory_refinement(win: Window, lm_: Landmarks, ref0: trajectory.Refinement, obs: trajectory.Observations,
                      first, surface: trajectory.MemorySurface, cfg: PipelineConfig, realign=False):
    """The window's factor graph again with the remembered surface, from the memory-free optimum
    ``ref0`` at the prior depth's scale: landmarks within ``τ = max(τ_min, d_scene α)`` of its tangent
    planes get point-to-plane priors of std ``max(plane_sigma_ratio d_scene, robust spread,
    memory_sigma_voxels · voxel)``, projection covariance scaled by ``α_mem``
    (:func:`cm3d.trajectory.memory_point_prior`; ``realign``: placement first re-fitted,
    :func:`cm3d.trajectory.align_to_surface`); one LM solve. Consistency test:
    ``2 (C_own(poses_mem) − C_own(poses_free)) <= χ²_q(6 (n − 1))`` (``C_own`` without memory terms,
    landmarks re-estimated at held poses) on at least ``min_memory_landmarks`` landmarks.
    Returns (poses (W, 4, 4), accept, alignment (4, 4), memory landmarks (L,), stat, threshold)."""
    rc = cfg.refine
    L = lm_.points.shape[0]
    g0 = ref0.graph
    x0 = ref0.result.params
    x0 = factors.Variables(*rescale_window(x0.poses, x0.points, win.poses, lm_.points, lm_.seed, first))
    f = g0.projection
    pvalid = jnp.zeros(L, bool).at[f.point_idx].max(f.weight > 0)
    eye = jnp.eye(4, dtype=x0.points.dtype)
    A = jax.lax.cond(realign, lambda: trajectory.align_to_surface(x0.points, pvalid, surface, cfg.assoc), lambda: eye)
    placed = trajectory.move_surface(surface, A)
    _, near, plane = trajectory.associate_surface(x0.points, pvalid, placed, cfg.assoc)
    spread = robust.robust_sigma(plane, near)
    sigma = jnp.maximum(cfg.assoc.plane_sigma_ratio * surface.d_scene,
                        jnp.where(jnp.sum(near) >= cfg.min_memory_landmarks, spread, 0.0))
    sigma = jnp.maximum(sigma, cfg.memory_sigma_voxels * placed.voxel)
    g1, matched = trajectory.memory_point_prior(g0, x0.points, pvalid, placed, cfg.assoc, sigma=sigma)
    res = lm.solve(g1, x0, rc.solver)
    poses1 = factors.orthonormalize_poses(res.params.poses)
    cost_own, _ = structure_only_cost(g0, poses1, res.params.points, min_observations=rc.solver.min_observations)
    stat = (2.0 * (cost_own - ref0.result.cost)).astype(win.poses.dtype)
    thr = chi2_threshold(obs, ref0.inlier, win.poses.shape[0], rc.gate_quantile, win.poses.dtype)
    fixed = rescale_window(poses1, res.params.points, win.poses, lm_.points, lm_.seed, first)[0]
    fixed = jnp.where(win.valid[:, None, None], fixed, win.poses)
    accept = (jnp.sum(matched) >= cfg.min_memory_landmarks) & (stat <= thr) & jnp.all(jnp.isfinite(fixed))
    return fixed, accept, A, matched, stat, thr


def sign_test(better, worse):
    """One-sided sign test: P(at least ``better`` of ``better + worse`` fair coin flips come up heads),
    the chance that a solution no better than the other wins ``better`` of the units that tell them apart
    (ties left out). Pure; 1 without a win."""
    k = jnp.asarray(better, jnp.float32)
    n = k + jnp.asarray(worse, jnp.float32)
    tail = betainc(jnp.maximum(k, 1.0), jnp.maximum(n - k + 1.0, 1.0), jnp.float32(0.5))
    return jnp.where(k > 0, tail, 1.0)


def photometric_test(win: Window, free, with_memory):
    """Do the memory solution's poses make the window's static pixels agree *better* than the
    memory-free ones, by more than the images resolve (:func:`cm3d.ops.warp.pair_warp_errors`, prior
    depth, the run-level check's gaps, pixel budget and tie ``TIE``, :mod:`cm3d.pipeline.photometric`),
    and on more frame pairs than chance gives? The mean grey error over the pairs must be lower by more
    than the tie, and the pairs where the memory solution is the better one (by more than the tie)
    against those where it is the worse must pass a one-sided sign test at ``SIGN_ALPHA``
    (:func:`sign_test`): a mean can be lowered by a few pairs the images pair badly (stop 62: a
    window across the kitchen's 62-frame jump, 0.56 % lower, moved its chunk's ATE from 0.0101 to
    0.0140), a count over the pairs cannot. (The pairs share frames, so they are not independent units:
    the level is nominal, and the test is no stricter than it.)
    Evidence neither solution was fitted to: the χ² test only asks whether the memory solution still
    fits the window's own tracks, which it can while it moves the poses away from the truth. A tie
    keeps the memory-free poses: the memory must earn its place (until stop 47 a tie went to the memory,
    and `camera_pose.py`'s scene 1 used two memory solutions 0.09 % and 0.02 % worse in the images,
    1.4 % worse in ATE). Fewer than ``MIN_PIXELS`` paired pixels: no evidence, no objection (the χ² test
    decides). Returns (ok, error free, error memory, the sign test's p-value)."""
    _, h, w = win.depth.shape
    per, n_pair = warp.pair_warp_errors(win.image, win.depth, win.conf, win.static, win.intrinsic,
                                        jnp.stack([free, with_memory]).astype(jnp.float32), win.valid, ph.GAPS,
                                        warp.sample_step(h, w, ph.MAX_PIXELS), ph.TRUNCATE)
    return photometric_decision(per, n_pair)


def photometric_decision(per, n_pair):
    """:func:`photometric_test`'s decision from the frame pairs' grey errors ``per`` (P, 2) (memory-free,
    memory) and paired pixels ``n_pair`` (P,): (ok, error free, error memory, sign test p-value)."""
    has = n_pair > 0
    err = warp.mean_over_pairs(per, n_pair)
    better = jnp.sum(has & (per[:, 1] < per[:, 0] * (1 - ph.TIE)))
    worse = jnp.sum(has & (per[:, 1] > per[:, 0] * (1 + ph.TIE)))
    p = sign_test(better, worse)
    mean_ok, pairs_ok = ph.memory_wins(err[0], err[1], p)
    ok = (jnp.sum(n_pair) < ph.MIN_PIXELS) | (mean_ok & pairs_ok)
    return ok, err[0].astype(jnp.float32), err[1].astype(jnp.float32), p.astype(jnp.float32)


@struct.dataclass
class _Phases:
    """The carry of :func:`recall_verify_update`'s two passes: what the pass stores (the window at
    ``poses`` into map ``target`` by ``transform``, ``same_frame``; a new map when ``target < 0`` and
    ``insert``; voxels under ``min_support`` dropped) into ``bank``, and what the first pass decided."""

    bank: Any
    map_id: Any
    poses: Any
    target: Any
    transform: Any
    same_frame: Any
    insert: Any
    min_support: Any
    cursor: MemoryCursor
    step: MemoryStep


def _store(st: _Phases, win: Window, mem_cfg: memory.MemoryConfig, cfg: PipelineConfig):
    """One pass's write: (bank, map written (-1 none), the window's entry)."""
    entry = window_entry(win.replace(poses=st.poses), mem_cfg, cfg, st.min_support)

    def merge(b):
        return memory.update_map(b, jnp.maximum(st.target, 0), entry, st.transform, mem_cfg,
                                 same_frame=st.same_frame), st.target

    def other(b):
        return jax.lax.cond(st.insert, lambda b: memory.insert_map(b, entry), lambda b: (b, -jnp.ones((), jnp.int32)),
                            b)

    bank, map_id = jax.lax.cond(st.target >= 0, merge, other, st.bank)
    return bank, map_id.astype(jnp.int32), entry


def recall_verify_update(bank: memory.MemoryBank, cursor: MemoryCursor, key, win: Window, lm_: Landmarks,
                         ref: trajectory.Refinement, poses, obs: trajectory.Observations,
                         mem_cfg: memory.MemoryConfig, cfg: PipelineConfig):
    """The memory's part of a window after its memory-free graph (``ref``, ``poses``): **identify** the
    window merged with its sequence's map (:func:`sequence_query`); **factor graph with memory**
    (:func:`memory_refinement`), used only when both the gate and the memory's test pass; **update**
    the bank (the recalled map, else the sequence's own, else a new one). Returns (bank, cursor, MemoryStep).

    The window becomes an entry merged into a map twice (the query: the memory-free window into the
    sequence's own map by the identity; the update: the final window into its target, else a new map).
    Both writes are the one body (:func:`_store`) of a two-pass ``fori_loop`` whose first pass also
    decides (identify, graph with memory, tests), so the compiled program holds the entry and the merge
    once: each copy was ~6 % of the sequence program's instructions, and a stored program loads in time
    proportional to them (docs/pipeline.md, stop 65). Bitwise the results of the two writes inlined."""
    top_k = mem_cfg.top_k
    f32 = jnp.float32

    def decide(st: _Phases, merged, entry0):
        query = _query_of(merged, cursor.written, entry0)  # sequence_query's, merged by the first pass
        ident = memory.identify(memory.without_map(bank, cursor.written), query, mem_cfg, key)
        hit = ident.map_id >= 0
        new_map = hit & (ident.map_id != cursor.recalled)
        use_map = jnp.where(new_map, ident.map_id, cursor.recalled).astype(jnp.int32)
        use_T = jnp.where(new_map, ident.verification.transform, cursor.transform).astype(f32)
        d_scene = trajectory.scene_scale(win.depth, win.static & win.valid[:, None, None])
        surface = memory_surface(bank, use_map, use_T, d_scene)
        first = obs.valid.reshape(lm_.obs_valid.shape)[:, 0]  # tracks that passed the prior check
        pm, ok, A, matched, stat, thr = memory_refinement(win, lm_, ref, obs, first, surface, cfg, new_map)
        used = (use_map >= 0) & ref.refined & ok
        e_free = e_mem = p_photo = jnp.full((), jnp.nan, f32)
        if cfg.memory_photometric:  # static: switched off, the warps are not computed at all
            photo_ok, e_free, e_mem, p_photo = photometric_test(win, poses, pm)
            used = used & photo_ok
        final = jnp.where(used, pm.astype(f32), poses)
        use_T = (use_T @ A.astype(f32)).astype(f32)
        # else the sequence's own map, whose frame is the sequence's (identity: exact, no ICP noise)
        target = jnp.where(use_map >= 0, use_map, cursor.written).astype(jnp.int32)
        target_T = jnp.where(use_map >= 0, use_T, jnp.eye(4)).astype(f32)
        report = recall_report(ident, -jnp.ones((), jnp.int32), jnp.where(hit, ident.verification.transform,
                                                                           jnp.eye(4)), False, target_T)
        step = MemoryStep(poses=final, report=report, landmarks=jnp.sum(matched).astype(jnp.int32), used=used,
                          stat=stat.astype(f32), threshold=thr.astype(f32), photo_free=e_free, photo_memory=e_mem,
                          photo_p=p_photo)
        return st.replace(poses=final, target=target, transform=target_T, same_frame=use_map < 0,
                          insert=jnp.ones((), bool), min_support=jnp.asarray(cfg.map_min_support, f32),
                          cursor=MemoryCursor(recalled=use_map, transform=use_T, written=cursor.written), step=step)

    def body(k, st: _Phases):
        merged, map_id, entry = _store(st, win, mem_cfg, cfg)
        return jax.lax.cond(k == 0, lambda: decide(st, merged, entry),
                            lambda: st.replace(bank=merged, map_id=map_id))

    st = _Phases(bank=bank, map_id=-jnp.ones((), jnp.int32), poses=poses.astype(f32),
                 target=jnp.asarray(cursor.written, jnp.int32), transform=jnp.eye(4, dtype=f32),
                 same_frame=jnp.ones((), bool), insert=jnp.zeros((), bool), min_support=jnp.zeros((), f32),
                 cursor=cursor, step=MemoryStep.off(poses.astype(f32), top_k))  # the first pass sets step
    st = jax.lax.fori_loop(0, 2, body, st)
    known = st.target >= 0
    created = ~known & (st.map_id >= 0)
    cur = st.cursor.replace(written=jnp.where(created, st.map_id, cursor.written).astype(jnp.int32))
    report = st.step.report.replace(map_id=st.map_id, created=created)
    return st.bank, cur, st.step.replace(report=report)
