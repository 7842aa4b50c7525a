"""Long videos: naive chunk stitching vs cm3d's Sim(3) stitching (+ factor graph) on a synthetic video.

    .venv/bin/python experiments/long_video.py [--frames 200 --chunk 40 --overlap 10] [--quick] [--json PATH]

One long camera path in synthetic scene 0 (200 frames at 96x128 by default) is rendered once and
split into chunks of 40 frames overlapping by 10 (the last chunk shorter), each with its own VGGT-like
prior (:func:`cm3d.data.synthetic.make_chunk_priors`: own unknown scale, first camera as its frame,
own depth and pose noise) at every noise level. Compared (ATE in metres, Sim(3)-aligned, evo's
protocol, :func:`cm3d.eval.metrics.evaluate_trajectories`):

* naive: each chunk placed rigidly on the previous chunk's pose of their first shared frame, scale
  ignored (:func:`cm3d.stitch.naive_stitch`);
* cm3d align: robust Sim(3) per boundary on the shared frames, chained and fused
  (:func:`cm3d.stitch.stitch_chunks` with ``refine=False``);
* cm3d refined: plus the factor graph over the whole video (tracks across boundaries), kept only
  when it passes the self-check (static mask: the synthetic ground truth's ``1 − dynamic_mask``, as
  in experiments/pose_refine.py). "graph" is the factor graph's own ATE, kept or not.

Headline JSON keys (moderate noise): ``ate_naive``, ``ate_stitch``, ``ate_stitch_refined``,
``ate_improvement`` (= 1 − refined / naive); per level ``ate_<method>_<level>``; boundary scale
errors against the true relative scales (``scale_err_max_<level>``).
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # OpenBLAS threads spin on shared cores

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from cm3d import stitch  # noqa: E402
from cm3d.data import synthetic  # noqa: E402
from cm3d.outputs import write_json  # noqa: E402
from cm3d.eval import metrics  # noqa: E402

LEVELS = tuple(synthetic.NOISE_LEVELS)


def run_level(images, gt, level, args, cfg, refine: bool):
    ts = np.arange(len(images)) / cfg.fps
    chunks = synthetic.make_chunk_priors(images, gt, args.chunk, args.overlap, level, seed=args.scene, timestamps=ts)
    ev = lambda P: metrics.evaluate_trajectories(ts, gt.cam_to_world, ts, np.asarray(P))["ate"]  # noqa: E731
    t0 = time.perf_counter()
    naive = stitch.naive_stitch(chunks)  # overlap inferred from the timestamps
    t_naive = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = stitch.stitch_chunks(chunks, static=~gt.dynamic_mask, refine=refine)
    t_stitch = time.perf_counter() - t0
    true_rel = [chunks[k - 1].meta["prior_scale"] / chunks[k].meta["prior_scale"] for k in range(1, len(chunks))]
    scale_err = [abs(b.scale / r - 1.0) for b, r in zip(res.boundaries, true_rel)]
    naive_jump = [abs(1.0 / r - 1.0) for r in true_rel]  # naive keeps scale 1 at every boundary
    row = {"level": level, "chunks": len(chunks), "ate_naive": ev(naive.sequence.cam_to_world),
           "ate_stitch": ev(res.poses_aligned), "ate_stitch_refined": ev(res.sequence.cam_to_world),
           "ate_graph": ev(res.poses_refined) if res.poses_refined is not None else float("nan"),
           "refine_ran": refine, "refine_kept": bool(res.refined),
           "scale_err_max": float(max(scale_err)), "naive_scale_err_max": float(max(naive_jump)),
           "rel_rmse_points": float(np.mean([b.rel_rmse_points for b in res.boundaries])),
           "naive_rel_rmse_points": float(np.mean([b.rel_rmse_points for b in naive.boundaries])),
           "time_naive_s": t_naive, "time_stitch_s": t_stitch}
    if refine:
        row.update({f"refine_{k}": v for k, v in res.refinement.items() if isinstance(v, (int, float, bool))})
    return row


def format_table(rows):
    head = (f"{'level':>9} | {'ATE naive':>9} {'align':>8} {'refined':>8} {'(graph)':>8} {'kept':>5} | "
            f"{'vs naive':>8} | {'scale err':>9} {'naive':>7} | {'overlap res':>11} {'naive':>7} | {'time':>6}")
    lines = [head, "-" * len(head)]
    for r in rows:
        kept = ("yes" if r["refine_kept"] else "no") if r["refine_ran"] else "-"
        gr = f"{r['ate_graph']:>8.4f}" if r["refine_ran"] else f"{'-':>8}"
        imp = 1.0 - r["ate_stitch_refined"] / r["ate_naive"] if r["ate_naive"] > 1e-12 else float("nan")
        lines.append(
            f"{r['level']:>9} | {r['ate_naive']:>9.4f} {r['ate_stitch']:>8.4f} {r['ate_stitch_refined']:>8.4f} {gr} "
            f"{kept:>5} | {100 * imp:>7.1f}% | {100 * r['scale_err_max']:>8.2f}% "
            f"{100 * r['naive_scale_err_max']:>6.1f}% | {100 * r['rel_rmse_points']:>10.2f}% "
            f"{100 * r['naive_rel_rmse_points']:>6.1f}% | {r['time_stitch_s']:>5.1f}s")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=int, default=0)
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--chunk", type=int, default=40)
    ap.add_argument("--overlap", type=int, default=10)
    ap.add_argument("--height", type=int, default=96)
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--levels", default=",".join(LEVELS), help="noise levels, comma-separated")
    ap.add_argument("--refine-levels", default="moderate",
                    help="levels that also run the factor graph (comma-separated; 'none' for no level)")
    ap.add_argument("--quick", action="store_true", help="60 frames at 48x64 in chunks of 20 (overlap 5), "
                    "moderate noise only, no factor graph")
    ap.add_argument("--json", default=None, metavar="PATH")
    args = ap.parse_args()
    levels = [lv for lv in args.levels.split(",") if lv]
    refine_levels = set(args.refine_levels.split(","))
    if args.quick:
        args.frames, args.chunk, args.overlap, args.height, args.width = 60, 20, 5, 48, 64
        levels, refine_levels = ["moderate"], set()
    for lv in levels:
        if lv not in LEVELS:
            ap.error(f"--levels: unknown level {lv!r}; choose from {', '.join(LEVELS)}")
    if "moderate" not in levels:
        ap.error("--levels: must include 'moderate' (the headline numbers)")
    cfg = synthetic.WorldConfig(height=args.height, width=args.width, supersample=1 if args.quick else 2)
    t0 = time.perf_counter()
    scene = synthetic.make_scene(args.scene, cfg)
    images, gt = synthetic.render_ground_truth(scene, 0, args.frames, cfg)
    t_render = time.perf_counter() - t0
    ranges = synthetic.chunk_ranges(args.frames, args.chunk, args.overlap)
    print(f"scene {args.scene}: {args.frames} frames at {cfg.height}x{cfg.width} (rendered in {t_render:.1f} s), "
          f"{len(ranges)} chunks of {args.chunk} frames overlapping by {args.overlap} "
          f"(last chunk {ranges[-1][1] - ranges[-1][0]} frames); each chunk its own VGGT-like prior")
    rows = [run_level(images, gt, lv, args, cfg, lv in refine_levels) for lv in levels]
    print("\nATE in metres (Sim(3)-aligned); 'vs naive' = 1 - refined / naive; scale err: worst boundary's "
          "relative scale error (naive: the scale jump it ignores); overlap res: shared-pixel residual "
          "after alignment / depth\n")
    print(format_table(rows))
    mod = next(r for r in rows if r["level"] == "moderate")
    out = {"ate_naive": mod["ate_naive"], "ate_stitch": mod["ate_stitch"],
           "ate_stitch_refined": mod["ate_stitch_refined"],
           "ate_improvement": 1.0 - mod["ate_stitch_refined"] / mod["ate_naive"],
           "ate_improvement_align": 1.0 - mod["ate_stitch"] / mod["ate_naive"],
           "frames": args.frames, "chunk": args.chunk, "overlap": args.overlap, "chunks": mod["chunks"],
           "height": cfg.height, "width": cfg.width, "render_s": t_render}
    for r in rows:
        for k, v in r.items():
            if k != "level" and isinstance(v, (int, float, bool)) and v == v:  # no NaN (not run)
                out[f"{k}_{r['level']}"] = v
    print(f"\nmoderate: cm3d {out['ate_stitch_refined']:.4f} m vs naive {out['ate_naive']:.4f} m: "
          f"{100 * out['ate_improvement']:.1f} % lower (target >= 50 %)")
    if args.json:
        write_json(args.json, out)


if __name__ == "__main__":
    main()
