"""Handcrafted vs learned (PointNet++) 3D scene descriptor in the memory bank (issue #9's column).

    .venv/bin/python experiments/descriptor_3d.py [--quick] [--json PATH] [--no-cache]

The setup is ``experiments/memory_recall.py``'s, imported from it (same worlds, visits, prepared
entries and cache ``~/.cache/cm3d/memory_recall``): 200 rooms stored from a 32-frame visit, queried
by a 12-frame revisit of each and by 200 rooms never stored (seeds from 10000). None of these
scenes is used to train the PointNet++ weights (training seeds from 100000, validation from
200000, ``experiments/train_pointnet2.py``). For each descriptor the bank is built with
``MemoryConfig(descriptor_3d=...)``: the entries' 3D descriptors are recomputed from their stored
voxel clouds by :func:`cm3d.memory.cloud_descriptor` (exactly what :func:`cm3d.memory.build_entry`
computes), everything else is shared.

Figures per descriptor:
- ``top1_3d``: 3D-only retrieval: share of revisits whose most similar stored descriptor (cosine)
  is their own room's, among 200;
- ``recall_top1``: share of revisits whose first recall candidate (2D votes + ``w_cloud`` x 3D
  similarity, before verification) is the right map: where the 3D descriptor acts in the bank;
- ``accuracy_200`` / ``false_accept`` / ``qps_200``: the full pipeline (2D recall, 3D re-ranking,
  keypoint RANSAC, ICP verification) at 200 maps, as in memory_recall.py;
- ``accuracy_200_2d3d`` / ``false_accept_2d3d``: without geometric verification (``verification=
  "none"``: the best re-ranked candidate is accepted), where the re-ranking decides alone;
- ``describe_ms``: descriptor time per cloud (batched, compile excluded; part of the host
  preparation of a query, not of q/s).

``--quick``: 3 stored rooms, 2 unseen, 6-frame visits, not cached, no 2D+3D row (checks that the
script runs; its time is mostly rendering and compilation).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # OpenBLAS threads spin on shared cores

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import memory_recall as mr  # noqa: E402  (the recall experiment's setup, imported without side effects)

from cm3d import memory  # noqa: E402
from cm3d.outputs import write_json  # noqa: E402

DESCRIPTORS = ("handcrafted", "pointnet2")


def describe(entries: memory.MapEntry, cfg: memory.MemoryConfig, chunk: int = 50):
    """3D descriptors (Q, D) of stacked entries' stored clouds per ``cfg.descriptor_3d`` and the
    time per cloud (s, compile excluded)."""
    fn = jax.jit(jax.vmap(lambda p, v: memory.cloud_descriptor(p, v, cfg)))
    pts, val = np.asarray(entries.points), np.asarray(entries.point_valid)
    Q = len(pts)
    chunk = min(chunk, Q)
    pad = (-Q) % chunk
    pts = np.concatenate([pts, np.repeat(pts[:1], pad, 0)])
    val = np.concatenate([val, np.repeat(val[:1], pad, 0)])
    jax.block_until_ready(fn(jnp.asarray(pts[:chunk]), jnp.asarray(val[:chunk])))  # compile
    t = time.perf_counter()
    out = [fn(jnp.asarray(pts[i:i + chunk]), jnp.asarray(val[i:i + chunk])) for i in range(0, len(pts), chunk)]
    out = np.concatenate([np.asarray(o) for o in out])[:Q]
    return out, (time.perf_counter() - t) / Q


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--no-cache", action="store_true")
    args = ap.parse_args(argv)
    quick = args.quick
    n_maps, n_unseen = (3, 2) if quick else (200, 200)
    map_frames, query_frames = (6, 6) if quick else (32, 12)
    map_kp = mr.QUERY_KEYPOINTS if quick else mr.CFG.max_keypoints
    use_cache = not args.no_cache and not quick

    t = time.perf_counter()
    map_floor = mr.QUERY_FLOOR_KEYPOINTS if quick else mr.CFG.max_floor_keypoints  # (memory_recall's entries)
    maps = mr.load_visits([(s, 0, map_frames, map_kp) for s in range(n_maps)], use_cache, floor=map_floor)
    revisits = mr.load_visits([(s, 1, query_frames, mr.QUERY_KEYPOINTS) for s in range(n_maps)], use_cache,
                              floor=mr.QUERY_FLOOR_KEYPOINTS)
    unseen = mr.load_visits([(mr.UNSEEN_SEED + s, 1, query_frames, mr.QUERY_KEYPOINTS) for s in range(n_unseen)],
                            use_cache, floor=mr.QUERY_FLOOR_KEYPOINTS)
    print(f"data: {n_maps} maps, {n_maps} revisits + {n_unseen} unseen queries (memory_recall.py's visits); "
          f"{time.perf_counter() - t:.1f} s (cached: {use_cache})")
    map_e, rq, uq = mr.stack(maps), mr.stack(revisits), mr.stack(unseen)
    truth = np.arange(n_maps)

    figures, rows = {}, []
    for name in DESCRIPTORS:
        cfg = dataclasses.replace(mr.CFG, max_maps=n_maps, descriptor_3d=name, cloud_dim=None)
        dm, ms = describe(map_e, cfg)
        dr, _ = describe(rq, cfg)
        du, _ = describe(uq, cfg)
        stored = [dataclasses.replace(v, entry=v.entry.replace(cloud_desc=d)) for v, d in zip(maps, dm)]
        allq = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), rq.replace(cloud_desc=jnp.asarray(dr)),
                            uq.replace(cloud_desc=jnp.asarray(du)))
        bank = mr.build_bank(stored, cfg)
        top1_3d = float(np.mean(np.argmax(dr @ dm.T, axis=1) == truth))
        ids, _, dt = mr.identify_batch(bank, allq, cfg)
        acc, fa, qps = float(np.mean(ids[:n_maps] == truth)), float(np.mean(ids[n_maps:] >= 0)), len(ids) / dt
        rec = jax.jit(jax.vmap(lambda e: memory.recall(bank, e.kf_desc, e.kf_valid, e.cloud_desc, cfg).candidates[0]))
        recall_top1 = float(np.mean(np.asarray(rec(allq))[:n_maps] == truth))
        acc0 = fa0 = float("nan")
        if not quick:  # (one compilation less in the smoke test)
            ids0, _, _ = mr.identify_batch(bank, allq, dataclasses.replace(cfg, verification="none"))
            acc0, fa0 = float(np.mean(ids0[:n_maps] == truth)), float(np.mean(ids0[n_maps:] >= 0))
        sims = dr @ dm.T
        pos = float(np.mean(np.diag(sims)))
        neg = float((sims.sum() - np.trace(sims)) / max(sims.size - n_maps, 1))
        n = n_maps
        figures |= {f"accuracy_{n}_{name}": acc, f"false_accept_{name}": fa, f"qps_{n}_{name}": qps,
                    f"top1_3d_{name}": top1_3d, f"recall_top1_{name}": recall_top1,
                    f"describe_ms_{name}": 1e3 * ms, f"cos_same_{name}": pos, f"cos_other_{name}": neg}
        if not quick:
            figures |= {f"accuracy_{n}_2d3d_{name}": acc0, f"false_accept_2d3d_{name}": fa0}
        rows.append((name, top1_3d, recall_top1, acc0, fa0, acc, fa, qps, 1e3 * ms, pos, neg))

    print(f"\n3D descriptor in the memory bank: {n_maps} stored rooms, {n_maps} revisits, {n_unseen} unseen rooms "
          "(none seen in training)")
    print(f"{'descriptor':>12} {'3D top-1':>9} {'recall@1':>9} {'acc 2D+3D':>10} {'FA 2D+3D':>9} "
          f"{'accuracy':>9} {'false acc.':>10} {'queries/s':>10} {'ms/cloud':>9} {'cos same/other':>15}")
    def pct(x, w):
        return f"{'-':>{w}}" if np.isnan(x) else f"{100 * x:>{w - 1}.1f}%"

    for name, t1, r1, a0, f0, a, f, q, ms, pos, neg in rows:
        print(f"{name:>12} {pct(t1, 9)} {pct(r1, 9)} {pct(a0, 10)} {pct(f0, 9)} "
              f"{pct(a, 9)} {pct(f, 10)} {q:>10.1f} {ms:>9.2f} {pos:>7.3f}/{neg:.3f}")
    print("(3D top-1: 3D descriptor alone; recall@1: first candidate of 2D votes + 3D re-ranking; "
          "2D+3D: accepted without geometric verification; accuracy / false acc. / queries/s: full pipeline)")
    if args.json:
        write_json(args.json, figures)
    return figures


if __name__ == "__main__":
    main()
