"""Video depth from the refined static map vs the prior's depth (the paper's Table 1), and fps.

    .venv/bin/python experiments/video_depth.py [--scenes 3 --frames 40] [--quick] [--json PATH]

Each scene is visited twice at *moderate* prior noise and both visits run through the pipeline
with one memory bank (as ``experiments/camera_pose.py``). For every visit:

* ``prior``: the foundation model's per-frame depth as given;
* ``refined``: depth re-rendered from the refined static map: the static (``~`` the pipeline's
  dynamic masks), confident pixels of every ``stride``-th column and row are lifted with the prior
  depth and *the refined poses*, fused (voxel-averaged, :func:`cm3d.outputs.static_map`), then
  projected into each refined camera with a soft z-buffer (:func:`cm3d.eval.render.render_depths`:
  one pixel per point, square splats only to fill the pixels no point hit);
* ``prior_map`` (a control): the same map and rendering with the *prior* poses, which shows what
  the refinement contributes to a fused map.

Metrics: Abs Rel and δ<1.25 after per-sequence median scale alignment
(:func:`cm3d.eval.metrics.depth_metrics_median`), against the ground-truth depth, on the pixels
where all three depths exist: ground truth > 0, not on a moving object (a static map has no
moving objects) and covered by both renderings; ``coverage`` is that pixel share. ``fps_backend``
is the frames per second of the whole back end (:func:`cm3d.pipeline.run_sequence`: motion cues,
landmarks, memory, factor graph) on the revisit, compiled, memory holding visit 1; flow and
keypoints (host front end) excluded, as in ``experiments/bench_backend.py``.

JSON keys (means over visits): ``absrel_prior``, ``delta1_prior``, ``absrel_refined``,
``delta1_refined``, ``fps_backend``, plus ``absrel_prior_map``, ``delta1_prior_map``, ``coverage``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # OpenBLAS threads spin on shared cores

import time  # noqa: E402

import numpy as np  # noqa: E402

from camera_pose import LEVEL, mean_figures, parse_args, revisit_runs, write_figures  # noqa: E402

VARIANTS = ("prior", "prior_map", "refined")


def map_depth(seq, poses, masks, stride: int, voxel_ratio: float, radius: int, tolerance: float = 0.02):
    """Depth (S, H, W) and coverage of the fused static map (lifted with ``poses``) rendered in the
    cameras ``poses``, and the map's size. Two z-buffered passes with a soft z-buffer (writes within
    ``tolerance`` of the nearest are averaged): one pixel per point, then ``radius`` splats only
    for the pixels the first pass left empty (so splats fill holes without blurring hit pixels)."""
    from cm3d.eval import render
    from cm3d.outputs import static_map

    pts, _ = static_map(seq, poses, masks, stride=stride, voxel_ratio=voxel_ratio)
    P, valid = render.pad_points(pts.astype(np.float32))
    H, W = seq.depth.shape[1:]
    cams, K = np.asarray(poses, np.float32), np.asarray(seq.intrinsic, np.float32)
    hit, c_hit = render.render_depths(P, valid, cams, K, height=H, width=W, radius=0, tolerance=tolerance)
    splat, c_splat = render.render_depths(P, valid, cams, K, height=H, width=W, radius=radius, tolerance=tolerance)
    c_hit = np.asarray(c_hit)
    return np.where(c_hit, np.asarray(hit), np.asarray(splat)), np.asarray(c_splat), len(pts)


def visit_row(scene, visit, seq, result, opts) -> dict:
    from cm3d.eval import metrics

    gt = seq.gt
    d_ref, c_ref, n_ref = map_depth(seq, result.poses, result.masks, **opts)
    d_pri, c_pri, _ = map_depth(seq, seq.cam_to_world, result.masks, **opts)
    valid = (gt.depth > 0) & ~gt.dynamic_mask & c_ref & c_pri
    row = {"scene": scene, "visit": visit, "coverage": float(valid.mean()), "map_points": n_ref}
    for name, pred in (("prior", seq.depth), ("prior_map", d_pri), ("refined", d_ref)):
        m = metrics.depth_metrics_median(pred, gt.depth, valid)
        row |= {f"absrel_{name}": float(m["abs_rel"]), f"delta1_{name}": float(m["delta1"])}
    return row


def format_table(rows) -> str:
    head = (f"{'scene':>5} {'visit':>5} | {'AbsRel prior':>12} {'prior map':>9} {'refined':>8} | "
            f"{'δ<1.25 prior':>12} {'prior map':>9} {'refined':>8} | {'coverage':>8} {'map pts':>8}")
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r['scene']:>5} {r['visit']:>5} | {r['absrel_prior']:>12.4f} {r['absrel_prior_map']:>9.4f} "
                     f"{r['absrel_refined']:>8.4f} | {r['delta1_prior']:>12.4f} {r['delta1_prior_map']:>9.4f} "
                     f"{r['delta1_refined']:>8.4f} | {r['coverage']:>8.3f} {r['map_points']:>8.0f}")
    return "\n".join(lines)


def main() -> None:
    args, use_cache, wcfg, scenes, frames = parse_args(__doc__)
    # map: every 2nd pixel (every pixel at 48x64), voxels of extent / 400 (/ 200), 3x3 fill splats
    opts = dict(stride=1, voxel_ratio=200.0, radius=1) if args.quick else dict(stride=2, voxel_ratio=400.0, radius=1)
    print(f"{scenes} scene(s) x 2 visits x {frames} frames at {wcfg.height}x{wcfg.width}, {LEVEL} prior noise; "
          f"map from every {opts['stride']}. pixel, voxel = extent / {opts['voxel_ratio']:.0f}, "
          f"splat {2 * opts['radius'] + 1}x{2 * opts['radius'] + 1} px")
    rows, fps = [], []
    t0 = time.perf_counter()
    for s in range(scenes):
        run = revisit_runs(s, frames, wcfg, no_memory=False, use_cache=use_cache)
        fps.append(frames / run["backend_s"])
        for v, (seq, res) in enumerate(zip(run["seqs"], run["res_mem"])):
            rows.append(visit_row(s, v + 1, seq, res, opts))
        print(f"  scene {s} done ({time.perf_counter() - t0:.0f} s)", flush=True)
    figures = mean_figures(rows, [f"{k}_{name}" for name in VARIANTS for k in ("absrel", "delta1")] + ["coverage"])
    figures["fps_backend"] = float(np.median(fps))
    print("\nAbs Rel / δ<1.25 after per-sequence median scaling, on ground-truth static pixels covered by the "
          "map renders; prior map: the same map fused with the prior poses\n")
    print(format_table(rows + [{"scene": "mean", "visit": "", "map_points": np.mean([r["map_points"] for r in rows]),
                                **figures}]))
    print(f"\nback end: {figures['fps_backend']:.1f} frames/s at {wcfg.height}x{wcfg.width} (revisit, compiled; "
          f"per scene: {', '.join(f'{f:.1f}' for f in fps)})")
    write_figures(args, figures, scenes, frames, wcfg)


if __name__ == "__main__":
    main()
