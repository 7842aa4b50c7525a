"""Static-map reconstruction with and without memory (the paper's Table 3).

    .venv/bin/python experiments/reconstruction.py [--scenes 3 --frames 40] [--quick] [--json PATH]

Each scene is visited twice at *moderate* prior noise (as ``experiments/camera_pose.py``): visit 1
fills the memory bank, and the reconstruction of the revisit (visit 2) is compared with the
ground-truth scene surface, three ways:

* ``no_memory``: the revisit's static map (static, confident pixels lifted with the prior depth
  and the refined poses, voxel-averaged: :func:`cm3d.outputs.static_map`), the pipeline run with
  the memory off (``use_memory=False``);
* ``memory``: the revisit's static map from the run with visit 1's bank, plus the recalled map
  (visit 1's map as the bank held it *before* the revisit) moved into the revisit's frame by the
  verified Sim(3) of the recall; when no window recalled a map of visit 1, the static map alone;
* ``update``: the recalled map *after* the revisit was merged into it (the bank's map after
  :func:`cm3d.memory.update_map`), moved into the revisit's frame the same way (no recall: the map
  the revisit wrote).

Ground truth: the static surface either visit saw (ground-truth depth of both visits, static
pixels, metric world frame). Estimated clouds live in the prior's frame and scale: each run's
clouds are mapped to the world by one Sim(3), Umeyama on per-pixel correspondences between the
revisit's static pixels lifted with the prior depth and the run's refined poses and the same
pixels' true world points (a global alignment: pose errors between frames still count). Camera
centres alone are not used: on short paths they leave a rotation free, and they ignore the depth's
scale. Every cloud (ground truth
too) is then voxel-downsampled to the same metric voxel, so that the bank's capacity-bound maps and
the dense static maps are compared at one density, and normals are PCA normals of 16 neighbours
(:func:`cm3d.eval.metrics.estimate_normals`). Metrics (:func:`cm3d.eval.metrics.reconstruction_metrics`,
7-Scenes / NICE-SLAM protocol): Acc (m, mean distance of the map to the truth), Comp (m, truth to
the map), NC (normal consistency, both directions averaged).

JSON keys (means over scenes): ``acc_<v>``, ``comp_<v>``, ``nc_<v>`` for ``v`` in no_memory, memory,
update, plus ``recalled``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # OpenBLAS threads spin on shared cores

import time  # noqa: E402

import numpy as np  # noqa: E402

from cm3d import memory  # noqa: E402
from camera_pose import LEVEL, mean_figures, parse_args, recalled_cell, revisit_runs, write_figures  # noqa: E402

VARIANTS = ("no_memory", "memory", "update")


def voxel_mean(points: np.ndarray, voxel: float) -> np.ndarray:
    """Points (N, 3) averaged per voxel of size ``voxel``."""
    keys = np.floor(points / voxel).astype(np.int64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    return np.stack([np.bincount(inv, points[:, k]) for k in range(3)], -1) / counts[:, None]


def lift(seq, poses, stride: int) -> np.ndarray:
    """World points (S, h, w, 3) of every ``stride``-th pixel: prior depth, camera ``poses``."""
    d = np.asarray(seq.depth, np.float64)[:, ::stride, ::stride]
    h, w = d.shape[1:]
    v, u = np.mgrid[0:h, 0:w].astype(np.float64) * stride
    rays = np.einsum("sij,hwj->shwi", np.linalg.inv(np.asarray(seq.intrinsic, np.float64)),
                     np.stack([u, v, np.ones_like(u)], -1))
    P = np.asarray(poses, np.float64)
    return np.einsum("sij,shwj->shwi", P[:, :3, :3], rays * d[..., None]) + P[:, None, None, :3, 3]


def world_alignment(seq, poses, masks, stride: int):
    """The Sim(3) (s, R, t) taking a run's point map into the world: Umeyama on per-pixel
    correspondences, each static pixel lifted with the prior depth and the run's ``poses`` against
    the same pixel's ground-truth world point (the point-map protocol of DUSt3R-style evaluations;
    the trajectory alone would leave the depth's scale and the rotation about a short path free)."""
    import jax

    from cm3d.eval.metrics import umeyama

    gt = seq.gt
    ok = (~np.asarray(masks, bool) & (gt.depth > 0) & (np.asarray(seq.depth) > 0))[:, ::stride, ::stride]
    src, dst = lift(seq, poses, stride)[ok], gt.world_points(stride)[ok]
    keep = np.random.default_rng(0).permutation(len(src))[:200_000]
    with jax.enable_x64(True):
        s, R, t = umeyama(src[keep], dst[keep])
    return float(s), np.asarray(R, np.float64), np.asarray(t, np.float64)


def to_world(points: np.ndarray, sim3) -> np.ndarray:
    s, R, t = sim3
    return s * np.asarray(points, np.float64) @ R.T + t


def bank_map(bank, result, earlier_only: bool):
    """Points (N, 3) of the map a sequence recalled, in the sequence's frame (inverse of the
    recall's Sim(3) query -> map), and whether it is a map of an earlier visit. ``earlier_only``:
    only a recall of a map this sequence did not create counts; without one, (None, False).
    Otherwise falls back to the map the sequence wrote last (its own frame)."""
    created = {w.map_id for w in result.windows if w.created_map}
    acc = [w for w in result.windows if w.accepted and w.recalled_map >= 0 and w.recalled_map not in created]
    if acc:
        w = acc[-1]
        m, T = w.recalled_map, np.asarray(w.transform, np.float64)
    elif earlier_only:
        return None, False
    else:
        written = [w for w in result.windows if w.map_id >= 0]
        if not written:
            return None, False
        w = written[-1]
        m = w.map_id
        T = np.eye(4) if w.created_map else np.asarray(w.transform, np.float64)
    cloud = memory.map_cloud(bank, m)
    pts = np.asarray(cloud.points, np.float64)[np.asarray(cloud.valid)]
    return (pts - T[:3, 3]) @ np.linalg.inv(T[:3, :3]).T, bool(acc)


def scene_rows(scene: int, frames: int, wcfg, quick: bool, use_cache: bool = False) -> dict:
    # --quick: the memory program on an empty bank stands in for the memory-off one (one compilation
    # fewer; camera_pose.py's smoke run does the same, and a smoke run's figures mean nothing)
    return reconstruction_row(scene, revisit_runs(scene, frames, wcfg, use_cache=use_cache,
                                                  empty_bank_baseline=quick), quick)


def reconstruction_row(scene: int, run: dict, quick: bool) -> dict:
    """Acc / Comp / NC of the three variants for one scene's runs (:func:`revisit_runs`)."""
    from cm3d.eval import metrics
    from cm3d.outputs import static_map

    seq = run["seqs"][1]
    mem, nomem = run["res_mem"][1], run["res_nomem"]
    stride = 2 if quick else 4
    voxel = 0.08 if quick else 0.04  # metres
    gt_pts = np.concatenate([s.gt.static_points(stride) for s in run["seqs"]])

    clouds = {}
    pts_nm, _ = static_map(seq, nomem.poses, nomem.masks, stride=stride)
    clouds["no_memory"] = to_world(pts_nm, world_alignment(seq, nomem.poses, nomem.masks, stride))
    pts_mem, _ = static_map(seq, mem.poses, mem.masks, stride=stride)
    recalled_pts, recalled = bank_map(run["bank0"], mem, earlier_only=True)
    both = pts_mem if recalled_pts is None else np.concatenate([pts_mem, recalled_pts])
    to_gt = world_alignment(seq, mem.poses, mem.masks, stride)
    clouds["memory"] = to_world(both, to_gt)
    upd, _ = bank_map(run["bank1"], mem, earlier_only=False)
    clouds["update"] = to_world(upd if upd is not None else pts_mem, to_gt)

    gt = voxel_mean(gt_pts, voxel)
    gt_n = metrics.estimate_normals(gt)
    row = {"scene": scene, "recalled": recalled, "gt_points": len(gt)}
    for name, pts in clouds.items():
        p = voxel_mean(pts, voxel)
        r = metrics.reconstruction_metrics(p, gt, metrics.estimate_normals(p), gt_n)
        row |= {f"acc_{name}": r["accuracy"], f"comp_{name}": r["completion"],
                f"nc_{name}": r["normal_consistency"], f"points_{name}": len(p)}
    return row


def format_table(rows) -> str:
    head = (f"{'scene':>5} | {'Acc no mem':>10} {'memory':>8} {'update':>8} | {'Comp no mem':>11} {'memory':>8} "
            f"{'update':>8} | {'NC no mem':>9} {'memory':>7} {'update':>7} | {'points no mem':>13} {'memory':>7} "
            f"{'update':>7} | recalled")
    lines = [head, "-" * len(head)]
    for r in rows:
        rec = recalled_cell(r["recalled"])
        lines.append(
            f"{r['scene']:>5} | {r['acc_no_memory']:>10.4f} {r['acc_memory']:>8.4f} {r['acc_update']:>8.4f} | "
            f"{r['comp_no_memory']:>11.4f} {r['comp_memory']:>8.4f} {r['comp_update']:>8.4f} | "
            f"{r['nc_no_memory']:>9.4f} {r['nc_memory']:>7.4f} {r['nc_update']:>7.4f} | "
            f"{r['points_no_memory']:>13.0f} {r['points_memory']:>7.0f} {r['points_update']:>7.0f} | {rec}")
    return "\n".join(lines)


def main() -> None:
    args, use_cache, wcfg, scenes, frames = parse_args(__doc__)
    print(f"{scenes} scene(s) x 2 visits x {frames} frames at {wcfg.height}x{wcfg.width}, {LEVEL} prior noise; "
          f"visit 1 fills the memory, the table is about the revisit's map")
    t0 = time.perf_counter()
    rows = []
    for s in range(scenes):
        rows.append(scene_rows(s, frames, wcfg, args.quick, use_cache))
        print(f"  scene {s} done ({time.perf_counter() - t0:.0f} s)", flush=True)
    figures = mean_figures(rows, [f"{k}_{v}" for v in VARIANTS for k in ("acc", "comp", "nc")] + ["recalled"])
    mean = {"scene": "mean", **figures, **mean_figures(rows, [f"points_{v}" for v in VARIANTS])}
    print("\nAcc / Comp in metres (lower is better), NC (higher is better), after each run's per-pixel Sim(3) "
          "alignment and a common voxel downsampling; ground truth: the static surface both visits saw\n")
    print(format_table(rows + [mean]))
    write_figures(args, figures, scenes, frames, wcfg)


if __name__ == "__main__":
    main()
