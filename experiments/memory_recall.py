"""Memory bank recall, verification, relocalisation and map update (the paper's Tables 5 and 9).

    .venv/bin/python experiments/memory_recall.py [--quick] [--json PATH] [--no-cache] [--no-tune] [--size HxW]
    .venv/bin/python experiments/memory_recall.py --fit-acceptance   # refit the MemoryConfig accept_* defaults

Synthetic worlds (:mod:`cm3d.data.synthetic`, 120x160 renders (``--size``: another size, measured
worse at 240x320, docs/memory.md), 1 frame per second): scene ``i``
is stored from a 32-frame look-around visit (visit 0); a *revisit* query is a 12-frame visit of
the same room from another place and direction (visit 1, other moving objects, its own prior
scale and frame); an *unseen* query is a 12-frame visit of a room never stored (seeds from 10000).
Priors are VGGT-like at the "slight" noise level; static pixels come from the ground-truth
dynamic mask (the motion stage is evaluated elsewhere).

Preparation (host, timed separately): image descriptors and keyframes, SIFT keypoints on static
pixels (OpenCV) lifted to 3D with the prior depth and poses (a map keeps 1024, 32 per frame; a query
256), *floor keypoints*: SIFT of a top-down orthophoto of the floor (:func:`cm3d.ops.keypoints.floor_features`:
the floor plane fitted to the prior points, every frame's floor pixels warped onto it; a map keeps 512,
a query 128; matched only among themselves), static cloud, map entry. Queries
(jit, vmapped over a batch of prepared queries, CPU): hashed 2D recall of ``top_k`` candidates,
keypoint matching + Sim(3) RANSAC per candidate (3-point hypotheses from the strict matches and
2-point *upright* hypotheses, both frames' up axes estimated from floor/ceiling normals), the pose
with the largest colour-consistent overlap, Sim(3) ICP of the best, accepted by the acceptance model (a
linear score of the pipeline's scores, :data:`cm3d.memory.ACCEPTANCE_FEATURES`).

Held-out split: scenes (and unseen rooms) with an even index form the *tuning* split, odd ones
the *test* split. The verification thresholds (keypoint inliers, ICP inlier count, fitness, RMSE,
colour agreement) are chosen on the tuning split only (:func:`tune_thresholds`, at 200 maps: the
accuracy plateau with no false accept, a tuning revisit counting only with a right pose
(:data:`POSE_TOLERANCE`), then the median of each threshold over that plateau); every
reported figure below comes from the test split with those thresholds (``--no-tune``: the
``MemoryConfig`` defaults, which were set from this tuning). The acceptance model
(:func:`fit_acceptance`, the headline rows) is fitted on the tuning split too: a logistic regression
on the standardised features ``ACCEPT_USED`` (right map with a right pose vs everything else), its
threshold halfway between the highest-scoring tuning wrong candidate (unseen room, wrong map or wrong
pose) and the next right revisit; ``--fit-acceptance`` only fits it and prints it as ``MemoryConfig``
defaults (they are that output). Each query's RANSAC key depends on its index only
(:func:`identify_batch`), so tuning sees the same draws as the evaluation.

Tables:
- recall per bank size (1, 50, 100, 200 maps; the bank holds all scenes below n, tuning and test):
  accuracy on test revisits (accepted as the right map *with a right pose*, :data:`POSE_TOLERANCE`;
  "map only": the right map whatever the pose), false accepts on test unseen rooms,
  queries/s (all queries, batched, compile excluded); size 1 averages the single-map banks of the
  50 test scenes below 100; at 200 maps also the accuracy counting only right poses;
- ablation at 200 maps (test split): 2D only / 2D+3D keypoints (no ICP) / 2D+3D+ICP without the
  upright pairs / full with the AND of the tuned thresholds / full with the acceptance model (the
  headline) / the previous configuration (no floor keypoints, cluster separation 2, 512 ICP points;
  model refitted on the tuning split; q/s ratio in the same process), and the 2D stage's recall@1/2/3
  (the true map among the candidates: what verification can reach);
- failure analysis of the test revisits at 200 maps (:func:`failure_analysis`): geometric and
  keypoint overlap with the true map under the ground-truth transform, accepted vs missed; each
  miss's acceptance score against the unseen rooms' scores (:func:`model_failure_analysis`);
- relocalisation error of accepted test revisits (rotation deg; translation of the relocalised first
  camera, metres), median and mean;
- map update: reconstruction Accuracy / Completion (metres, against the ground-truth static points
  of both visits) of a map after its first visit and after merging a verified revisit.

``--quick`` (the smoke test): 3 stored rooms, 2 unseen, 6-frame visits, one bank size (3), no
ablation or map update: it checks that the script runs, not the figures (its time is mostly
compilation).
Generated and prepared visits are cached in ``~/.cache/cm3d/memory_recall`` (``--no-cache``: off), their
floor keypoints in files of their own (``floor-*.npz``, ``FLOOR_CACHED`` strongest; ~1 s per visit), with
*all* their lifted keypoints (``RAW_KP_PER_FRAME`` = 128 per frame, files ``raw-*.npz``): a keypoint
capacity is a cut of that list (:func:`cut_keypoints`), so changing it re-renders nothing (the first
full run renders ~600 visits: ~15-25 min of one core). Older files holding one capacity are still read
when no raw file exists.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from cm3d import memory
from cm3d.data import synthetic
from cm3d.data.atomic import atomic_write
from cm3d.ops import descriptors, keypoints
from cm3d.outputs import write_json
from cm3d.pipeline.config import PipelineConfig

WORLD = synthetic.WorldConfig(height=120, width=160, supersample=1, fps=1.0)
# the product configuration (cm3d run's, the demo's: memory.MemoryConfig's defaults) with this bank's
# capacities only: 200 maps, 1024 RootSIFT + 512 floor keypoints per map (issue 22)
CFG = memory.with_capacities(max_maps=200, max_points=4096, max_keyframes=16, max_keypoints=1024,
                             max_floor_keypoints=512)
QUERY_KEYPOINTS = 256  # image keypoints of a query (a map: CFG.max_keypoints)
QUERY_FLOOR_KEYPOINTS = 128  # floor keypoints of a query (a map: CFG.max_floor_keypoints)
# the previous configuration (stop 16), an ablation row: no floor keypoints, its cluster separation and ICP points
PREVIOUS = dict(max_floor_keypoints=0, cluster_separation=2.0, icp_points=512)
KP_PER_FRAME = 64  # (the legacy cache files' detection capacity per frame; see RAW_KP_PER_FRAME)
RAW_KP_PER_FRAME = 128  # SIFT keypoints per frame lifted and cached before the capacity cut (see load_visits)
FLOOR = keypoints.FloorConfig()  # floor orthophoto keypoints (cm3d.ops.keypoints.floor_features)
FLOOR_CACHED = 1024  # floor keypoints cached per visit (strongest first); a capacity is a prefix
# the product's detection (PipelineConfig.keypoints): SIFT at contrast 0.01 (OpenCV's default 0.04 finds
# almost nothing on weakly textured rooms at 120x160), each frame's keypoints a round robin over an 8 x 8
# image grid (stop 44; --spread-cells 0: strongest first, the benchmark's order before stop 45)
SIFT_CONTRAST = PipelineConfig().keypoints.contrast_threshold
SPREAD_CELLS = PipelineConfig().keypoints.spread_cells
KEYFRAME_THRESHOLD = 0.1
LEVEL = "slight"
UNSEEN_SEED = 10_000
CACHE = Path(os.environ.get("CM3D_CACHE", Path.home() / ".cache" / "cm3d")) / "memory_recall"


@dataclasses.dataclass
class Visit:
    """A prepared visit: the entry (numpy pytree) and what the evaluation needs."""

    entry: memory.MapEntry
    prior_from_world: np.ndarray  # (4, 4) similarity world -> this visit's prior frame
    static_world: np.ndarray  # (n, 3) ground-truth static points (metres), subsampled
    prep_s: dict


@jax.jit
def _frame_descriptors(images, static):
    return jax.vmap(descriptors.image_descriptor)(images, static)


def _prepare_fn(cfg: memory.MemoryConfig, capacity: int):
    @jax.jit
    def prep(depth, conf, K, c2w, images, static, desc, uv, kdesc, kvalid):
        idx, ok = memory.select_keyframes(desc, jnp.ones(desc.shape[0], bool), KEYFRAME_THRESHOLD, cfg.max_keyframes)
        cloud = memory.sequence_cloud(depth, conf, K, c2w, images, static, cfg)
        kp = memory.lift_keypoints(uv, kdesc, kvalid, depth, K, c2w, capacity)
        return memory.build_entry(cloud, desc[idx], ok, cfg, kp)

    return prep


_PREP = {}


def prepare(scene_seed: int, visit: int, frames: int, capacity: int, cfg: memory.MemoryConfig = CFG,
            per_frame: int = KP_PER_FRAME) -> Visit:
    """Render, prior and prepare one visit (host + jit); timings per stage in ``prep_s``. ``per_frame``
    SIFT keypoints per frame (strongest first), lifted and cut to ``capacity`` round robin over frames."""
    t0 = time.perf_counter()
    seq = synthetic.generate(scene_seed, visit, frames, LEVEL, WORLD)
    t1 = time.perf_counter()
    static = ~seq.gt.dynamic_mask
    desc = _frame_descriptors(jnp.asarray(seq.images), jnp.asarray(static))
    feats = keypoints.detect_sequence(seq.images, static, per_frame, keypoints.KeypointConfig(spread_cells=SPREAD_CELLS),
                                      contrast_threshold=SIFT_CONTRAST)
    t2 = time.perf_counter()
    key = (capacity, frames)
    if key not in _PREP:
        _PREP[key] = _prepare_fn(cfg, capacity)
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    entry = _PREP[key](f32(seq.depth), f32(seq.depth_conf), f32(seq.intrinsic), f32(seq.cam_to_world),
                       jnp.asarray(seq.images), jnp.asarray(static), desc, jnp.asarray(feats.uv),
                       jnp.asarray(feats.desc), jnp.asarray(feats.valid))
    entry = jax.tree.map(np.asarray, entry)
    t3 = time.perf_counter()
    s = seq.meta["prior_scale"]
    prior_from_world = np.diag([s, s, s, 1.0]) @ np.linalg.inv(seq.gt.cam_to_world[0])
    pts = seq.gt.static_points(stride=4)
    return Visit(entry, prior_from_world, pts[:: max(1, len(pts) // 20000)].astype(np.float32),
                 {"render": t1 - t0, "features": t2 - t1, "entry": t3 - t2})


def _cache_key(args, per_frame: int = KP_PER_FRAME, version: int = 2) -> str:
    """What a prepared visit depends on (verification thresholds do not invalidate the cache)."""
    prep = {k: getattr(CFG, k) for k in ("max_points", "max_keyframes", "image_dim", "cloud_dim", "keypoint_dim",
                                         "voxel_resolution", "min_conf_quantile", "pixel_stride", "normal_radius")}
    text = json.dumps([args, dataclasses.asdict(WORLD), prep, per_frame, SIFT_CONTRAST, KEYFRAME_THRESHOLD, LEVEL,
                       version])
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def raw_path(seed: int, visit: int, frames: int) -> Path:
    """The cache file of a visit with *all* its lifted keypoints (``RAW_KP_PER_FRAME`` per frame, round
    robin over frames, before any capacity cut): any keypoint capacity is a prefix of it."""
    args = [seed, visit, frames] + ([{"spread_cells": SPREAD_CELLS}] if SPREAD_CELLS else [])
    return CACHE / f"raw-{_cache_key(args, RAW_KP_PER_FRAME, 3)}.npz"


def cut_keypoints(v: Visit, capacity: int) -> Visit:
    """The visit with its keypoints cut (or padded) to ``capacity``. :func:`cm3d.memory.lift_keypoints`
    orders keypoints round robin over frames, each frame's strongest first, so the first ``capacity``
    of a larger lift are exactly a lift at ``capacity`` (for ``capacity <= frames x per-frame`` of the
    smaller detection: tested in ``tests/test_memory.py``)."""
    kp = v.entry.keypoints
    n = kp.valid.shape[0]
    if n >= capacity:
        cut = memory.Keypoints(kp.points[:capacity], kp.desc[:capacity], kp.valid[:capacity])
    else:
        pad = lambda a: np.concatenate([a, np.zeros((capacity - n,) + a.shape[1:], a.dtype)])  # noqa: E731
        cut = memory.Keypoints(pad(kp.points), pad(kp.desc), pad(kp.valid))
    return dataclasses.replace(v, entry=v.entry.replace(keypoints=cut))


def floor_path(seed: int, visit: int, frames: int) -> Path:
    """The cache file of a visit's floor keypoints (``FLOOR_CACHED``, strongest first)."""
    key = _cache_key([seed, visit, frames, dataclasses.asdict(FLOOR), FLOOR_CACHED], RAW_KP_PER_FRAME, 4)
    return CACHE / f"floor-{key}.npz"


def floor_keypoints(seed: int, visit: int, frames: int, use_cache: bool) -> keypoints.FloorFeatures:
    """A visit's floor orthophoto keypoints in its prior frame (:func:`cm3d.ops.keypoints.floor_features`
    on the visit's images, prior depth and poses and ground-truth static mask), cached."""
    path = floor_path(seed, visit, frames)
    if use_cache and path.exists():
        z = np.load(path, allow_pickle=False)
        return keypoints.FloorFeatures(z["points"], z["desc"], z["valid"])
    seq = synthetic.generate(seed, visit, frames, LEVEL, WORLD)
    f = keypoints.floor_features(seq.images, seq.depth, seq.intrinsic, seq.cam_to_world, ~seq.gt.dynamic_mask,
                                 FLOOR_CACHED, FLOOR, seed=seed)
    if use_cache:
        CACHE.mkdir(parents=True, exist_ok=True)
        with atomic_write(path) as fh:
            np.savez(fh, points=f.points, desc=f.desc, valid=f.valid)
    return f


def add_floor(v: Visit, f: keypoints.FloorFeatures, count: int) -> Visit:
    """The visit with its first ``count`` floor keypoints as the entry's ``floor_keypoints``."""
    if count <= 0:
        return v
    floor = memory.Keypoints(f.points[:count].astype(np.float32), f.desc[:count].astype(np.float32), f.valid[:count])
    return dataclasses.replace(v, entry=v.entry.replace(floor_keypoints=floor))


def _read(path: Path, capacity: int) -> Visit:
    z = np.load(path, allow_pickle=False)
    leaves = [z[f"leaf{i}"] for i in range(int(z["n"]))]
    treedef = jax.tree.structure(_template(capacity))
    return Visit(jax.tree.unflatten(treedef, leaves), z["pfw"], z["static"], json.loads(str(z["prep"])))


def _write(path: Path, v: Visit) -> None:
    CACHE.mkdir(parents=True, exist_ok=True)
    leaves = jax.tree.leaves(v.entry)
    with atomic_write(path) as f:
        np.savez(f, n=len(leaves), pfw=v.prior_from_world, static=v.static_world, prep=json.dumps(v.prep_s),
                 **{f"leaf{i}": a for i, a in enumerate(leaves)})


def load_visits(specs, use_cache: bool, raw: bool = False, floor: int = 0) -> list[Visit]:
    """Prepared visits for (seed, visit, frames, capacity) specs, from the cache when present: the *raw*
    file (all lifted keypoints, :func:`raw_path`, cut to ``capacity``) when there is one, else the legacy
    file of that exact capacity (``KP_PER_FRAME`` per frame); a visit in neither is prepared and cached
    raw. ``raw``: only raw files (a keypoint capacity sweep; missing ones are prepared). ``floor``: this
    many floor keypoints (:func:`floor_keypoints`, strongest first) as each entry's ``floor_keypoints``."""
    if floor > 0:
        return [add_floor(v, floor_keypoints(*spec[:3], use_cache), floor)
                for v, spec in zip(load_visits(specs, use_cache, raw), specs)]
    out = []
    for spec in specs:
        seed, visit, frames, capacity = spec
        rp, legacy = raw_path(seed, visit, frames), CACHE / f"{_cache_key(spec)}.npz"
        if use_cache and rp.exists():
            out.append(cut_keypoints(_read(rp, frames * RAW_KP_PER_FRAME), capacity))
            continue
        if use_cache and not raw and not SPREAD_CELLS and legacy.exists():
            out.append(_read(legacy, capacity))
            continue
        v = prepare(seed, visit, frames, frames * RAW_KP_PER_FRAME, per_frame=RAW_KP_PER_FRAME)
        if use_cache:
            _write(rp, v)
        out.append(cut_keypoints(v, capacity))
    return out


def _template(capacity):
    P, K = CFG.max_points, CFG.max_keyframes
    z = np.zeros
    return memory.MapEntry(points=z((P, 3)), normals=z((P, 3)), conf=z(P), colors=z((P, 3)), point_valid=z(P),
                           kf_desc=z((K, CFG.image_dim)), kf_valid=z(K), cloud_desc=z(CFG.cloud_dim), voxel_size=z(()),
                           keypoints=memory.Keypoints(z((capacity, 3)), z((capacity, CFG.keypoint_dim)), z(capacity)))


def build_bank(maps: list[Visit], cfg: memory.MemoryConfig) -> memory.MemoryBank:
    insert = jax.jit(memory.insert_map)
    bank = memory.empty(cfg)
    for v in maps:
        bank, m = insert(bank, v.entry)
        if int(m) < 0:
            raise memory.MemoryFullError("bank full while building the experiment bank")
    return bank


def stack(visits: list[Visit]):
    return jax.tree.map(lambda *a: jnp.asarray(np.stack(a)), *[v.entry for v in visits])


_IDENTIFY = {}


def identify_batch(bank, queries, cfg: memory.MemoryConfig, batch: int = 50, full: bool = False, query_ids=None):
    """Identify every query (a stacked entry) against the bank, ``batch`` at a time (jit + vmap).
    Query ``i``'s RANSAC key is ``fold_in(PRNGKey(0), query_ids[i])`` (default ``i``): a query gets the same
    key whichever subset it is identified in (the tuning split's fits see the evaluation's draws).
    Returns (map_id (Q,), transform (Q, 4, 4), seconds excluding compilation) and, when ``full``,
    the whole :class:`memory.Identification` (numpy, (Q, ...))."""
    if cfg not in _IDENTIFY:
        _IDENTIFY[cfg] = jax.jit(jax.vmap(lambda b, e, k: memory.identify(b, e, cfg, k), in_axes=(None, 0, 0)))
    fn = _IDENTIFY[cfg]
    Q = queries.kf_desc.shape[0]
    batch = min(batch, Q)
    ids = np.arange(Q) if query_ids is None else np.asarray(query_ids)
    keys = jax.vmap(jax.random.fold_in, in_axes=(None, 0))(jax.random.PRNGKey(0), jnp.asarray(ids, jnp.uint32))
    chunks = [(i, min(i + batch, Q)) for i in range(0, Q, batch)]

    def take(i, j):
        sl = jax.tree.map(lambda a: a[i:j], queries)
        ks = keys[i:j]
        if j - i < batch:  # pad to one shape (one compilation)
            sl = jax.tree.map(lambda a: jnp.concatenate([a, jnp.repeat(a[:1], batch - (j - i), 0)]), sl)
            ks = jnp.concatenate([ks, jnp.repeat(ks[:1], batch - (j - i), 0)])
        return sl, ks

    data = [take(i, j) for i, j in chunks]
    jax.block_until_ready(fn(bank, *data[0]).map_id)  # compile
    t = time.perf_counter()
    outs = [fn(bank, *d) for d in data]
    jax.block_until_ready([o.map_id for o in outs])
    dt = time.perf_counter() - t
    out = jax.tree.map(lambda *a: np.concatenate([np.asarray(x)[: j - i] for x, (i, j) in zip(a, chunks)]), *outs)
    if full:
        return out.map_id, out.verification.transform, dt, out
    return out.map_id, out.verification.transform, dt


def _rot_deg(R):
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


POSE_TOLERANCE = (10.0, 1.0)  # a relocalisation is right within this rotation (deg) and translation (m)


def pose_errors(maps, revisits, ids, T, truth):
    """Rotation (deg) and first-camera translation (m) error (Q,) of each query's transform into
    its accepted map; NaN where the map is not ``truth[q]``."""
    rot, trans = np.full(len(ids), np.nan), np.full(len(ids), np.nan)
    for q, (m, Ti) in enumerate(zip(ids, T)):
        if m != truth[q] or m < 0:
            continue
        M = maps[m].prior_from_world
        gt = M @ np.linalg.inv(revisits[q].prior_from_world)
        s_gt, s_est = np.cbrt(np.linalg.det(gt[:3, :3])), np.cbrt(np.linalg.det(Ti[:3, :3]))
        rot[q] = _rot_deg((Ti[:3, :3] / s_est) @ (gt[:3, :3] / s_gt).T)
        s_map = np.cbrt(np.linalg.det(M[:3, :3]))
        trans[q] = float(np.linalg.norm(Ti[:3, 3] - gt[:3, 3]) / s_map)  # map units -> metres
    return rot, trans


def reloc_errors(maps, revisits, ids, T, truth):
    """Rotation (deg) and first-camera translation (m) errors of accepted, correct revisits."""
    rot, trans = pose_errors(maps, revisits, ids, T, truth)
    ok = ~np.isnan(rot)
    return rot[ok], trans[ok]


def right_pose(maps, revisits, ids, T, truth):
    """(Q,) bool: the query is accepted as its true map with the pose within :data:`POSE_TOLERANCE`."""
    rot, trans = pose_errors(maps, revisits, ids, T, truth)
    with np.errstate(invalid="ignore"):
        return (rot < POSE_TOLERANCE[0]) & (trans < POSE_TOLERANCE[1])


def map_update(maps, revisits, ids, T, truth, cfg, count):
    """Accuracy/Completion (m) of maps before and after merging their verified revisit."""
    from cm3d.eval.metrics import reconstruction_metrics

    update = jax.jit(lambda b, m, e, t: memory.update_map(b, m, e, t, cfg))
    one = dataclasses.replace(cfg, max_maps=1)
    rows = []
    for q in np.flatnonzero(ids == truth)[:count]:
        m = int(ids[q])
        bank = build_bank([maps[m]], one)
        after = update(bank, 0, revisits[q].entry, jnp.asarray(T[q], jnp.float32))
        gt = np.concatenate([maps[m].static_world, revisits[q].static_world])
        w = np.linalg.inv(maps[m].prior_from_world)
        res = []
        for b in (bank, after):
            p = np.asarray(b.points[0])[np.asarray(b.point_valid[0])]
            res.append(reconstruction_metrics(p @ w[:3, :3].T + w[:3, 3], gt))
        rows.append((res[0]["accuracy"], res[0]["completion"], res[1]["accuracy"], res[1]["completion"]))
    return np.array(rows)


def failure_analysis(maps, revisits, ids, truth, qs):
    """Why revisits are missed: for each test revisit q (the true map m = truth[q]) its *geometric
    overlap* (share of the query's voxels within 2 map voxels of the map's under the ground-truth
    Sim(3)) and *keypoint overlap* (distinct query keypoint clusters with a map keypoint within 2
    voxels under the same transform; the most any keypoint matching could find), accepted vs missed."""
    from scipy.spatial import cKDTree

    rows = []
    for q in qs:
        m = int(truth[q])
        gt = maps[m].prior_from_world @ np.linalg.inv(revisits[q].prior_from_world)
        e, me = revisits[q].entry, maps[m].entry
        vs = float(me.voxel_size)
        move = lambda p: p @ gt[:3, :3].T + gt[:3, 3]  # noqa: E731
        d, _ = cKDTree(np.asarray(me.points)[np.asarray(me.point_valid)]).query(
            move(np.asarray(e.points)[np.asarray(e.point_valid)]))
        kv = np.asarray(e.keypoints.valid)
        sep = CFG.cluster_separation * float(e.voxel_size)
        cluster = np.asarray(memory.keypoint_clusters(e.keypoints.points, kv, sep))
        dk, _ = cKDTree(np.asarray(me.keypoints.points)[np.asarray(me.keypoints.valid)]).query(
            move(np.asarray(e.keypoints.points)))
        rows.append((q, ids[q] == m, float(np.mean(d < 2 * vs)), len(set(cluster[kv & (dk < 2 * vs)]))))
    ok = np.array([r[1] for r in rows])
    geo, kp = np.array([r[2] for r in rows]), np.array([r[3] for r in rows])
    print(f"\nfailure analysis ({len(rows)} test revisits; ground-truth Sim(3)): geometric overlap (query voxels "
          "within 2 map voxels) and keypoint overlap (distinct query keypoints within 2 voxels of a map keypoint)")
    for name, sel in (("accepted", ok), ("missed", ~ok)):
        if sel.any():
            print(f"  {name:>8} ({sel.sum():>3}): overlap median {100 * np.median(geo[sel]):.0f}% (min "
                  f"{100 * geo[sel].min():.0f}%), keypoint overlap median {np.median(kp[sel]):.0f} "
                  f"(min {kp[sel].min()})")
    print("  missed: " + ", ".join(f"#{r[0]} {100 * r[2]:.0f}%/{r[3]}" for r in rows if not r[1]))
    out = {"overlap_median_accepted": float(np.median(geo[ok])) if ok.any() else float("nan"),
           "overlap_median_missed": float(np.median(geo[~ok])) if (~ok).any() else float("nan"),
           "kp_overlap_median_accepted": float(np.median(kp[ok])) if ok.any() else float("nan"),
           "kp_overlap_median_missed": float(np.median(kp[~ok])) if (~ok).any() else float("nan"),
           "missed_low_overlap": int(np.sum(~ok & (geo < 0.5)))}
    return out


def model_failure_analysis(maps, revisits, out, T, truth, qs, unseen_qs):
    """Each test revisit the acceptance model misses (not accepted as its map with a right pose): its
    model score (accepted when >= 0), its verified candidate and that candidate's pose error, against the
    scores of the unseen test rooms (what a lower threshold would let in)."""
    score, cand = np.asarray(out.acceptance), np.asarray(out.candidate)
    ids = np.asarray(out.map_id)
    posed = right_pose(maps, [revisits[q] for q in qs], ids[qs], T[qs], truth[qs])
    rot, trans = pose_errors(maps, revisits, cand[qs], T[qs], truth[qs])
    su = np.sort(score[unseen_qs])
    print(f"\nacceptance model scores (accept >= 0): unseen test rooms median {np.median(su):.2f}, 95th pct "
          f"{np.percentile(su, 95):.2f}, max {su[-1]:.2f}; right test revisits median "
          f"{np.median(score[qs][posed]):.2f}, min {score[qs][posed].min() if posed.any() else float('nan'):.2f}")
    feats = np.asarray(out.features)
    names = memory.ACCEPTANCE_FEATURES
    show = [names.index(k) for k in ("log_pose_inliers", "fitness", "colour_agreement", "screen_overlap")]
    for i, q in enumerate(qs):
        if posed[i]:
            continue
        pose = (f"pose {rot[i]:.0f} deg / {trans[i]:.2f} m off" if np.isfinite(rot[i]) else
                ("no candidate" if cand[q] < 0 else f"candidate {cand[q]} (not the true map)"))
        above = int(np.sum(su >= score[q]))
        print(f"  #{q}: score {score[q]:.2f} ({above} of {len(su)} unseen rooms score as high), {pose}; "
              + ", ".join(f"{names[k]} {feats[q, k]:.2f}" for k in show))
    missed = [q for i, q in enumerate(qs) if not posed[i]]
    right = np.isfinite(rot) & (np.nan_to_num(rot, nan=180.0) < POSE_TOLERANCE[0]) & (
        np.nan_to_num(trans, nan=1e9) < POSE_TOLERANCE[1])
    return {"model_missed": len(missed), "model_unseen_score_max": float(su[-1]),
            "model_missed_right_pose": int(np.sum(right & ~posed))}


THRESHOLDS = ("min_keypoint_inliers", "min_inliers", "min_fitness", "max_rmse", "min_colour_agreement")
GRID = ((4, 5, 6, 7, 8), (0, 25, 50, 75, 100), (0.0, 0.1, 0.2, 0.3, 0.4), (0.65, 0.7, 0.75, 0.8, 0.9),
        (0.5, 0.6, 0.7, 0.75, 0.8))
OPEN = dict(min_keypoint_inliers=0, min_inliers=0, min_fitness=0.0, max_rmse=float("inf"), min_colour_agreement=0.0)


def tune_thresholds(bank, queries, truth, unseen, cfg: memory.MemoryConfig, pose_ok=None, query_ids=None):
    """Verification thresholds from the tuning split only: identify every query with all
    thresholds open, then over ``GRID`` keep the settings with no false accept on the unseen
    queries and an accuracy within 1 point of the best; each threshold is the median of those
    settings (the middle of the plateau, not its edge). ``truth`` (Q,) map ids of revisits (-1 for
    unseen); ``unseen`` (Q,) bool; ``pose_ok(map_ids, transforms) -> (Q,) bool``: when given, a
    revisit only counts as recognised with a right pose (a right map with a wrong pose would
    corrupt the map on update). Returns (thresholds dict, tuning accuracy, false accepts)."""
    import itertools

    out = identify_batch(bank, queries, dataclasses.replace(cfg, **OPEN, **NO_MODEL), full=True, query_ids=query_ids)[3]
    v = out.verification
    vs = np.asarray(bank.voxel_size)[np.maximum(np.asarray(out.map_id), 0)]
    base, pick = np.asarray(v.accepted), np.asarray(out.map_id)  # the remaining checks (scale, finite)
    feats = (np.asarray(v.keypoint_inliers), np.asarray(v.inlier_count), np.asarray(v.fitness),
             np.asarray(v.inlier_rmse) / vs, np.asarray(v.colour_agreement))
    rev = ~unseen
    good = np.ones(len(pick), bool) if pose_ok is None else pose_ok(pick, np.asarray(v.transform))

    def score(th):
        ok = (base & (feats[0] >= th[0]) & (feats[1] >= th[1]) & (feats[2] >= th[2]) & (feats[3] <= th[3])
              & (feats[4] >= th[4]))
        ids = np.where(ok, pick, -1)
        return float(np.mean((ids[rev] == truth[rev]) & good[rev])), float(np.mean(ids[unseen] >= 0))

    res = [(th, *score(th)) for th in itertools.product(*GRID)]
    clean = [r for r in res if r[2] == 0.0] or [min(res, key=lambda r: r[2])]
    best = max(r[1] for r in clean)
    plateau = np.array([r[0] for r in clean if r[1] >= best - 0.01])
    th = {k: round(float(np.median(plateau[:, i])), 3) for i, k in enumerate(THRESHOLDS)}
    th["min_keypoint_inliers"] = int(round(th["min_keypoint_inliers"]))
    th["min_inliers"] = int(round(th["min_inliers"]))
    return th, *score(tuple(th[k] for k in THRESHOLDS))


NO_MODEL = dict(accept_weights=(), accept_mean=(), accept_scale=(), accept_bias=0.0)  # the thresholds decide
MAX_TUNING_FALSE_ACCEPT = 0.005  # the acceptance model's operating point: at most this share of tuning unseen rooms
ACCEPT_C = 0.1  # inverse L2 strength of the logistic regression (standardised features)
# the features the model uses (the others get weight 0): chosen by 5-fold cross-validation on the tuning split
# (3 repeats) among all 15, C in {0.03, 0.1, 1} and threshold rules: the recall margin, 3D similarity, ICP inlier
# count and both scale features did not help (held-out tuning false accepts 0.7 % with them, 0 % without)
ACCEPT_USED = ("vote_share", "log_matches", "log_triangle_inliers", "log_upright_inliers", "log_pose_inliers",
               "inlier_margin", "screen_overlap", "fitness", "rmse_voxels", "colour_agreement")


def acceptance_scores(cfg: memory.MemoryConfig, features):
    """The acceptance model's score (Q,) of features (Q, F) in NumPy (float64): the same dot product as
    :func:`cm3d.memory.acceptance_score` inside the jitted ``identify``."""
    w, mu, sd = (np.asarray(getattr(cfg, k), np.float64) for k in ("accept_weights", "accept_mean", "accept_scale"))
    return (np.asarray(features, np.float64) - mu) / sd @ w + cfg.accept_bias


def fit_acceptance(bank, queries, truth, unseen, cfg: memory.MemoryConfig, pose_ok, query_ids=None):
    """The acceptance model from the tuning split only: ``identify`` (thresholds irrelevant) gives every
    query's verified candidate and its :data:`cm3d.memory.ACCEPTANCE_FEATURES`; a scikit-learn logistic
    regression on the standardised features ``ACCEPT_USED`` (``ACCEPT_C``; the other features get weight 0)
    learns "right map with a right pose" (``pose_ok``) against everything else (unseen rooms, wrong maps,
    wrong poses); the operating threshold sits halfway between the highest score it must reject (every
    wrong candidate that passes the hard checks, but ``MAX_TUNING_FALSE_ACCEPT`` of the unseen rooms) and
    the next right revisit's score, and is folded into the bias.
    Returns (MemoryConfig fields dict, tuning accuracy, tuning false accepts), or (None, ...) when the
    split lacks one of the two classes (``--quick``). The features do not depend on the thresholds: the
    identification is the one :func:`tune_thresholds` makes (same config: one compilation)."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.preprocessing import StandardScaler

    out = identify_batch(bank, queries, dataclasses.replace(cfg, **OPEN, **NO_MODEL), full=True,
                         query_ids=query_ids)[3]
    cand, F = np.asarray(out.candidate), np.asarray(out.features, np.float64)
    v = out.verification
    y = (cand == truth) & pose_ok(cand, np.asarray(v.transform))
    scale = np.asarray(v.scale)
    has = cand >= 0
    hard = has & (scale >= cfg.scale_range[0]) & (scale <= cfg.scale_range[1]) & np.all(
        np.isfinite(np.asarray(v.transform)), (1, 2))
    if len(set(y[has])) < 2:
        return None, float("nan"), float("nan")
    used = [memory.ACCEPTANCE_FEATURES.index(k) for k in ACCEPT_USED]
    sc = StandardScaler().fit(F[has][:, used])
    lr = LogisticRegression(C=ACCEPT_C, max_iter=10_000).fit(sc.transform(F[has][:, used]), y[has])
    z = np.where(has, sc.transform(F[:, used]) @ lr.coef_[0] + lr.intercept_[0], -np.inf)
    k = int(np.floor(MAX_TUNING_FALSE_ACCEPT * np.sum(unseen)))
    wrong_rev = np.sort(z[hard & ~y & ~unseen])[::-1]
    neg_uns = np.sort(z[hard & unseen])[::-1]
    lo = max(wrong_rev[0] if len(wrong_rev) else -np.inf, neg_uns[k] if k < len(neg_uns) else -np.inf)
    pos = np.sort(z[y & (z > lo)])
    if not len(pos):
        thr = lo + 1.0
    elif not np.isfinite(lo):
        thr = pos[0] - 1.0
    else:
        thr = 0.5 * (lo + pos[0])
    nf = len(memory.ACCEPTANCE_FEATURES)
    w, mu, sd = np.zeros(nf), np.zeros(nf), np.ones(nf)
    w[used], mu[used], sd[used] = lr.coef_[0], sc.mean_, sc.scale_
    fields = dict(accept_weights=tuple(round(float(x), 5) for x in w),
                  accept_mean=tuple(round(float(x), 5) for x in mu),
                  accept_scale=tuple(round(float(x), 5) for x in sd),
                  accept_bias=round(float(lr.intercept_[0] - thr), 5))
    ok = hard & (acceptance_scores(dataclasses.replace(cfg, **fields), F) >= 0)
    rev = ~unseen
    return fields, float(np.mean((ok & y)[rev])), float(np.mean(ok[unseen]))


def config_snippet(fields) -> str:
    """The fitted model as MemoryConfig defaults (to paste into cm3d/memory/config.py)."""
    fmt = lambda v: "(" + ", ".join(f"{x:g}" for x in v) + ")"  # noqa: E731
    return "\n".join(f"    {k}: {'tuple[float, ...]' if isinstance(v, tuple) else 'float'} = "
                     f"{fmt(v) if isinstance(v, tuple) else f'{v:g}'}" for k, v in fields.items())


def _size(text: str) -> tuple[int, int]:
    """``--size HxW`` -> (H, W), both at least 16 pixels."""
    try:
        h, w = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW such as 240x320, got {text!r}") from None
    if h < 16 or w < 16:
        raise argparse.ArgumentTypeError(f"both sides must be >= 16 pixels, got {text!r}")
    return h, w


def main(argv=None):
    global WORLD, SPREAD_CELLS
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--no-cache", action="store_true")
    ap.add_argument("--no-tune", action="store_true", help="use the MemoryConfig defaults (thresholds and model)")
    ap.add_argument("--fit-acceptance", action="store_true",
                    help="only fit the acceptance model on the tuning split and print it as MemoryConfig defaults")
    ap.add_argument("--size", default=None, type=_size, metavar="HxW",
                    help=f"render size (default {WORLD.height}x{WORLD.width}; its own cache files)")
    ap.add_argument("--spread-cells", type=int, default=SPREAD_CELLS, metavar="N",
                    help=f"each frame's keypoints as a round robin over an N x N grid (default {SPREAD_CELLS}: "
                         "the product's, PipelineConfig.keypoints; 0: strongest first; its own cache files)")
    args = ap.parse_args(argv)
    SPREAD_CELLS = args.spread_cells
    if args.size:
        WORLD = dataclasses.replace(WORLD, height=args.size[0], width=args.size[1])
    quick = args.quick
    n_maps, n_unseen = (3, 2) if quick else (200, 200)
    sizes = (3,) if quick else (1, 50, 100, 200)
    map_frames, query_frames = (6, 6) if quick else (32, 12)  # quick: one shape, fewer compilations
    map_kp = QUERY_KEYPOINTS if quick else CFG.max_keypoints
    map_floor = QUERY_FLOOR_KEYPOINTS if quick else CFG.max_floor_keypoints
    use_cache = not args.no_cache and not quick

    t = time.perf_counter()
    maps = load_visits([(s, 0, map_frames, map_kp) for s in range(n_maps)], use_cache, floor=map_floor)
    revisits = load_visits([(s, 1, query_frames, QUERY_KEYPOINTS) for s in range(n_maps)], use_cache,
                           floor=QUERY_FLOOR_KEYPOINTS)
    unseen = load_visits([(UNSEEN_SEED + s, 1, query_frames, QUERY_KEYPOINTS) for s in range(n_unseen)], use_cache,
                         floor=QUERY_FLOOR_KEYPOINTS)
    t_data = time.perf_counter() - t
    prep = {k: np.mean([v.prep_s[k] for v in revisits + unseen]) for k in ("render", "features", "entry")}
    print(f"data: {n_maps} maps ({map_frames} frames), {n_maps} revisits + {n_unseen} unseen queries "
          f"({query_frames} frames), {WORLD.height}x{WORLD.width}; {t_data:.1f} s (cached: {use_cache})")
    print(f"host preparation per query (not in q/s): render {prep['render'] * 1e3:.0f} ms, image descriptors + "
          f"SIFT {prep['features'] * 1e3:.0f} ms, entry (jit) {prep['entry'] * 1e3:.0f} ms")

    rq, uq = stack(revisits), stack(unseen)
    allq = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), rq, uq)
    Q = n_maps + n_unseen
    truth = np.concatenate([np.arange(n_maps), np.full(n_unseen, -1)])
    is_unseen = truth < 0
    test = np.concatenate([np.arange(n_maps) % 2 == 1, np.arange(n_unseen) % 2 == 1])  # odd: test, even: tuning
    figures, rows = {}, []
    queries = revisits + unseen  # (unseen ones never have truth >= 0, so never a pose)
    big = dataclasses.replace(CFG, max_maps=n_maps)
    tq = np.flatnonzero(~test)
    tuning_q = jax.tree.map(lambda a: a[~test], allq)
    pose_ok = lambda ids, T: right_pose(maps, [queries[q] for q in tq], ids, T, truth[tq])  # noqa: E731

    def fit(cfg_base):
        fields, acc_m, fa_m = fit_acceptance(build_bank(maps, big), tuning_q, truth[~test], is_unseen[~test],
                                             cfg_base, pose_ok, query_ids=tq)
        if fields is None:
            print("\nacceptance model: not fitted (the tuning split lacks right or wrong candidates); defaults kept")
            return {}
        print(f"\nacceptance model fitted on the tuning split (logistic regression, C={ACCEPT_C:g}, standardised "
              f"features {', '.join(ACCEPT_USED)}; threshold above every tuning wrong candidate and all but "
              f"{100 * MAX_TUNING_FALSE_ACCEPT:g}% of the unseen rooms): tuning accuracy "
              f"(right poses) {100 * acc_m:.1f}%, false accepts {100 * fa_m:.1f}%")
        print(f"{'feature':>22} {'mean':>9} {'scale':>9} {'weight':>8}")
        for k, mu, sd, w in zip(memory.ACCEPTANCE_FEATURES, fields["accept_mean"], fields["accept_scale"],
                                fields["accept_weights"]):
            print(f"{k:>22} {mu:>9.4f} {sd:>9.4f} {w:>8.3f}")
        print(f"{'bias (threshold folded in)':>22} {fields['accept_bias']:>9.4f}")
        figures["tuning_accuracy_model"], figures["tuning_false_accept_model"] = acc_m, fa_m
        figures.update({"accept_bias": fields["accept_bias"]})
        figures.update({f"accept_weight_{k}": w for k, w in zip(memory.ACCEPTANCE_FEATURES, fields["accept_weights"])})
        return fields

    if args.fit_acceptance:
        fields = fit(big)
        if fields:
            print("\nMemoryConfig defaults (cm3d/memory/config.py):\n" + config_snippet(fields))
        if args.json:
            write_json(args.json, figures)
        return figures

    cfg = CFG
    if not args.no_tune:
        th, acc_t, fa_t = tune_thresholds(build_bank(maps, big), tuning_q, truth[~test], is_unseen[~test], big,
                                          pose_ok, query_ids=tq)
        cfg = dataclasses.replace(CFG, **th)
        print(f"\nthresholds tuned on the tuning split ({int(np.sum(~test & ~is_unseen))} revisits, "
              f"{int(np.sum(~test & is_unseen))} unseen; {n_maps} maps): "
              + ", ".join(f"{k}={v:g}" for k, v in th.items()) + f"; tuning accuracy {100 * acc_t:.1f}%, "
              f"false accepts {100 * fa_t:.1f}%")
        figures.update({f"tuned_{k}": v for k, v in th.items()})
        figures["tuning_accuracy"], figures["tuning_false_accept"] = acc_t, fa_t
        cfg = dataclasses.replace(cfg, **fit(big))
    model = bool(cfg.accept_weights)
    test_rev = np.flatnonzero(test & ~is_unseen)
    test_uns = np.flatnonzero(test & is_unseen)

    full = {}
    for n in sizes:
        cfg_n = dataclasses.replace(cfg, max_maps=n)
        if n == 1:
            singles = [q for q in test_rev if q < 100]
            hits = posed = 0
            for s in singles:
                bank = build_bank([maps[s]], cfg_n)
                ids, T1, _ = identify_batch(bank, jax.tree.map(lambda a: a[s: s + 1], rq), cfg_n, batch=1,
                                            query_ids=[s])
                hits += int(ids[0] == 0)
                posed += int(right_pose([maps[s]], [revisits[s]], ids, T1, np.zeros(1, int))[0])
            acc_map, acc = hits / len(singles), posed / len(singles)
            bank = build_bank([maps[singles[0]]], cfg_n)
            ids, _, dt = identify_batch(bank, allq, cfg_n)
            fa = float(np.mean(ids[test_uns] >= 0))
        else:
            bank = build_bank(maps[:n], cfg_n)
            ids, T, dt, out = identify_batch(bank, allq, cfg_n, full=True)
            mine = test_rev[test_rev < n]
            acc_map = float(np.mean(ids[mine] == truth[mine]))
            acc = float(np.mean(right_pose(maps, [revisits[q] for q in mine], ids[mine], T[mine], truth[mine])))
            fa = float(np.mean(ids[test_uns] >= 0))
            full = {"bank": bank, "ids": ids, "T": T, "cfg": cfg_n, "n": n, "out": out}
        qps = Q / dt
        figures[f"accuracy_{n}"], figures[f"accuracy_{n}_map"], figures[f"qps_{n}"] = acc, acc_map, qps
        rows.append((n, acc, acc_map, fa, qps))
    print(f"\nrecall, test split, {'acceptance model' if model else 'AND of thresholds'} (accuracy: test revisits "
          "accepted as the right map with a right pose; map only: right map whatever the pose; false accepts: test "
          "unseen rooms accepted; q/s over all queries)")
    print(f"{'maps':>6} {'accuracy':>9} {'map only':>9} {'false acc.':>10} {'queries/s':>10}")
    for n, acc, acc_map, fa, qps in rows:
        print(f"{n:>6} {100 * acc:>8.1f}% {100 * acc_map:>8.1f}% {100 * fa:>9.1f}% {qps:>10.1f}")

    n, bank, ids, T = full["n"], full["bank"], full["ids"], full["T"]
    mine = test_rev[test_rev < n]
    figures["false_accept"] = float(np.mean(ids[test_uns] >= 0))
    cand = np.asarray(full["out"].recall.candidates)
    k_max = cand.shape[1]
    for k in range(1, k_max + 1):
        figures[f"recall_at_{k}"] = float(np.mean(np.any(cand[mine, :k] == truth[mine, None], 1)))
    print(f"\nablation at {n} maps (test split); the 2D stage's recall@k (true map among the first k "
          "candidates): " + ", ".join(f"@{k} {100 * figures[f'recall_at_{k}']:.1f}%" for k in range(1, k_max + 1)))
    print(f"{'verification':>42} {'accuracy':>9} {'map only':>9} {'false acc.':>10} {'queries/s':>10}")
    modes = [("none", "2D only", dict(verification="none")),
             ("keypoints", "2D+3D keypoints (no ICP)", dict(verification="keypoints")),
             ("no_upright", "2D+3D+ICP, no upright pairs, thresholds", dict(upright_hypotheses=0, **NO_MODEL)),
             ("thresholds", "2D+3D+ICP + upright, AND of thresholds", NO_MODEL),
             ("full", "all + acceptance model" if model else "all (AND of thresholds)", {})]
    if not model:
        modes = [m for m in modes if m[0] != "thresholds"]
    qps_ref = {}
    for mode, name, change in ([m for m in modes if m[0] == "full"] if quick else modes):
        if mode == "full" and quick:
            ids_m, T_m, dt = ids, T, Q / figures[f"qps_{n}"]
        else:  # (full: timed again here, next to the thresholds row: the q/s ratio compares like with like)
            ids_m, T_m, dt = identify_batch(bank, allq, dataclasses.replace(full["cfg"], **change))
        posed_m = right_pose(maps, [revisits[q] for q in mine], ids_m[mine], T_m[mine], truth[mine])
        acc, fa = float(np.mean(posed_m)), float(np.mean(ids_m[test_uns] >= 0))
        acc_map = float(np.mean(ids_m[mine] == truth[mine]))
        print(f"{name:>42} {100 * acc:>8.1f}% {100 * acc_map:>8.1f}% {100 * fa:>9.1f}% {Q / dt:>10.1f}")
        figures[f"ablation_{mode}_accuracy"], figures[f"ablation_{mode}_false_accept"] = acc, fa
        figures[f"ablation_{mode}_accuracy_map"] = acc_map
        figures[f"ablation_{mode}_qps"] = qps_ref[mode] = Q / dt
    if not quick:  # the previous configuration: no floor keypoints (the bank ignores the entries'), model refitted
        prev_cfg = dataclasses.replace(full["cfg"], **PREVIOUS)
        prev_maps = maps
        fields = fit_acceptance(build_bank(prev_maps, prev_cfg), tuning_q, truth[~test], is_unseen[~test], prev_cfg,
                                pose_ok, query_ids=tq)[0]
        prev_cfg = dataclasses.replace(prev_cfg, **(fields or {}))
        ids_m, T_m, dt = identify_batch(build_bank(prev_maps, prev_cfg), allq, prev_cfg)
        posed_m = right_pose(prev_maps, [revisits[q] for q in mine], ids_m[mine], T_m[mine], truth[mine])
        acc, fa = float(np.mean(posed_m)), float(np.mean(ids_m[test_uns] >= 0))
        acc_map = float(np.mean(ids_m[mine] == truth[mine]))
        name = "previous: no floor keypoints (refitted)"
        print(f"{name:>42} {100 * acc:>8.1f}% {100 * acc_map:>8.1f}% {100 * fa:>9.1f}% {Q / dt:>10.1f}")
        figures["ablation_previous_accuracy"], figures["ablation_previous_false_accept"] = acc, fa
        figures["ablation_previous_accuracy_map"], figures["ablation_previous_qps"] = acc_map, Q / dt
        figures["qps_ratio_to_previous"] = qps_ref["full"] / (Q / dt)
        print(f"{'':>42} (q/s of the full row / this row, same process: {figures['qps_ratio_to_previous']:.2f})")
    if "thresholds" in qps_ref:
        figures["model_qps_ratio"] = qps_ref["full"] / qps_ref["thresholds"]
        print(f"(q/s of the acceptance model / the thresholds, same process: {figures['model_qps_ratio']:.2f}; "
              "accuracy counts right poses only, map only any pose)")
    if not quick:
        figures.update(failure_analysis(maps, revisits, ids, truth, mine))
        if model:
            figures.update(model_failure_analysis(maps, revisits, full["out"], T, truth, mine, test_uns))

    posed = right_pose(maps, [revisits[q] for q in mine], ids[mine], T[mine], truth[mine])
    figures[f"accuracy_{n}_right_pose"] = float(np.mean(posed))
    wrong = int(np.sum(ids[mine] == truth[mine]) - posed.sum())
    print(f"\naccuracy at {n} maps counting only right poses (rotation < {POSE_TOLERANCE[0]:g} deg, translation < "
          f"{POSE_TOLERANCE[1]:g} m): {100 * np.mean(posed):.1f}% ({wrong} test revisits accepted as the right map "
          "with a wrong pose)")
    rot, trans = reloc_errors(maps, [revisits[q] for q in mine], ids[mine], T[mine], truth[mine])
    figures["reloc_rot_deg"] = float(np.median(rot)) if len(rot) else float("nan")
    figures["reloc_trans"] = float(np.median(trans)) if len(trans) else float("nan")
    print(f"\nrelocalisation of {len(rot)} accepted test revisits (query prior frame -> map frame, Sim(3))")
    if len(rot):
        print(f"  rotation error    median {np.median(rot):.2f} deg, mean {np.mean(rot):.2f} deg, "
              f"95th pct {np.percentile(rot, 95):.2f} deg")
        print(f"  translation error median {100 * np.median(trans):.1f} cm, mean {100 * np.mean(trans):.1f} cm, "
              f"95th pct {100 * np.percentile(trans, 95):.1f} cm (first camera, metres)")

    upd = (map_update(maps, [revisits[q] for q in mine], ids[mine], T[mine], truth[mine], full["cfg"], 40)
           if not quick else [])
    if len(upd):
        a0, c0, a1, c1 = upd.mean(0)
        figures["acc_before_update"], figures["acc_after_update"] = float(a0), float(a1)
        figures["comp_before_update"], figures["comp_after_update"] = float(c0), float(c1)
        better = float(np.mean(upd[:, 3] < upd[:, 1]))
        print(f"\nmap update over {len(upd)} test maps (metres, lower is better; ground truth: static points of "
              "both visits)")
        print(f"{'':>14} {'Accuracy':>9} {'Completion':>11}")
        print(f"{'first visit':>14} {a0:>9.4f} {c0:>11.4f}")
        print(f"{'+ revisit':>14} {a1:>9.4f} {c1:>11.4f}")
        print(f"completion improved on {100 * better:.0f}% of the maps")
    figures["prep_ms_per_query"] = 1e3 * sum(prep.values())
    if args.json:
        write_json(args.json, figures)
    return figures


if __name__ == "__main__":
    main()
