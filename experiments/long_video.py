"""Long videos: naive chunk stitching vs cm3d's Sim(3) stitching (+ factor graph) on a synthetic video.

    .venv/bin/python experiments/long_video.py [--frames 200 --chunk 40 --overlap 10] [--quick] [--json PATH]

One long camera path in synthetic scene 0 (200 frames at 96x128 by default) is rendered once and
split into chunks of 40 frames overlapping by 10 (the last chunk shorter), each with its own VGGT-like
prior (:func:`cm3d.data.synthetic.make_chunk_priors`: own unknown scale, first camera as its frame,
own depth and pose noise) at every noise level. Compared (ATE in metres, Sim(3)-aligned, evo's
protocol, :func:`cm3d.eval.metrics.evaluate_trajectories`):

* naive: each chunk placed rigidly on the previous chunk's pose of their first shared frame, scale
  ignored (:func:`cm3d.long_video.naive_stitch`);
* cm3d align: robust Sim(3) per boundary on the shared frames, chained and fused
  (:func:`cm3d.long_video.stitch_chunks` with ``refine=False``);
* cm3d refined: plus the whole-trajectory refinement (:func:`cm3d.long_video.refine_frames`): one pose
  graph over every frame, a prior per frame at the stitched pose and a relative-motion factor per
  consecutive frame pair measured from the images (optical flow + both frames' depth, robust
  Sim(3)), across chunk boundaries alike, noise levels by variance component estimation, solved by
  the factor graph's LM, kept only when it passes its self-check. No ground truth and no mask is
  used.

Headline JSON keys (moderate noise): ``ate_naive``, ``ate_stitch`` (the stitched priors),
``ate_stitch_refined`` (the refined whole trajectory), ``ate_improvement`` (= 1 − refined / naive),
``ate_refine_gain`` (= 1 − refined / stitched); per level ``ate_<method>_<level>``; boundary scale
errors against the true relative scales (``scale_err_max_<level>``).

Loop variant (``--loop-level``, default moderate; not in ``--quick``): the same scene, a camera path
that comes back to its start (``synthetic.generate_long_video(loop=True)``), the same chunking.
Compared: naive stitching, overlap stitching (Sim(3) alignment, as above), and
:func:`cm3d.long_video.stitch_with_memory`: every chunk through the pipeline threading one memory bank,
each recall of a map the previous chunk did not write a Sim(3) loop constraint, and a Sim(3) pose
graph over the chunk transforms (overlap + loop constraints), then the whole-trajectory
refinement; it stitches the chunks' refined poses, where ``stitch_chunks`` stitches the priors.
Keys: ``ate_loop_naive``, ``ate_loop_stitch``, ``ate_loop_chained`` (the chain of the refined
chunks' overlap alignments before the pose graph), ``ate_loop`` (+ the loop as the memory registered it),
``ate_loop_refined`` (its whole-trajectory refinement), ``ate_loop_stitch_refined`` (overlap stitching
+ refinement, no loop),
``loops_recalled``, ``loops_kept``, ``loop_improvement`` (= 1 − ate_loop / ate_loop_stitch),
``loop_improvement_refined`` (= 1 − ate_loop_refined / ate_loop_stitch_refined), ``loop_pipeline_s``,
``image_loops`` (loops measured in the images in the kept frame-level graph; 0 when none).
The drifting loop variant (``--loop-drift``, default 3: the priors' random-walk drift x 3, chosen
before measuring) repeats it with ``ate_loopdrift_*`` keys. And what limits it:
``ate_loop_true_transforms`` (every chunk placed by its ground-truth Sim(3): the floor of any chunk
placement, loop or not), ``ate_loop_forced`` (the recalled loops forced in at σ × 2, as accurate as
an overlap, no consistency check), ``ate_loop_true_constraint`` (the same with the loop at its
ground-truth value), and the widest loop's Sim(3) errors against the truth,
``loop_err_{rot_deg,log_scale,centre_m}_{memory,prior_frames,chain}`` (the memory's transform
between the windows' refined frames, the same re-expressed between the chunks' prior frames as the
pose graph uses it, and the chain of overlap alignments); the straight
video through the same memory stitching: ``ate_straight_memory`` (vs ``ate_straight_chained``),
``loops_recalled_straight``, ``loops_kept_straight``.
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # OpenBLAS threads spin on shared cores

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from cm3d import long_video as stitch  # noqa: E402
from cm3d.data import synthetic  # noqa: E402
from cm3d.outputs import write_json  # noqa: E402
from cm3d.eval import metrics  # noqa: E402
from cm3d.ops import sim3  # noqa: E402

LEVELS = tuple(synthetic.NOISE_LEVELS)


def run_level(images, gt, level, args, cfg, refine: bool):
    ts = np.arange(len(images)) / cfg.fps
    chunks = synthetic.make_chunk_priors(images, gt, args.chunk, args.overlap, level, seed=args.scene, timestamps=ts)
    ev = lambda P: metrics.evaluate_trajectories(ts, gt.cam_to_world, ts, np.asarray(P))["ate"]  # noqa: E731
    t0 = time.perf_counter()
    naive = stitch.naive_stitch(chunks)  # overlap inferred from the timestamps
    t_naive = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = stitch.stitch_chunks(chunks, refine=refine)  # no mask, no ground truth
    t_stitch = time.perf_counter() - t0
    true_rel = [chunks[k - 1].meta["prior_scale"] / chunks[k].meta["prior_scale"] for k in range(1, len(chunks))]
    scale_err = [abs(b.scale / r - 1.0) for b, r in zip(res.boundaries, true_rel)]
    naive_jump = [abs(1.0 / r - 1.0) for r in true_rel]  # naive keeps scale 1 at every boundary
    row = {"level": level, "chunks": len(chunks), "ate_naive": ev(naive.sequence.cam_to_world),
           "ate_stitch": ev(res.poses_aligned), "ate_stitch_refined": ev(res.sequence.cam_to_world),
           "refine_ran": refine, "refine_kept": bool(res.refined),
           "scale_err_max": float(max(scale_err)), "naive_scale_err_max": float(max(naive_jump)),
           "rel_rmse_points": float(np.mean([b.rel_rmse_points for b in res.boundaries])),
           "naive_rel_rmse_points": float(np.mean([b.rel_rmse_points for b in naive.boundaries])),
           "time_naive_s": t_naive, "time_stitch_s": t_stitch}
    if refine:
        row.update({f"refine_{k}": v for k, v in res.refinement.items() if isinstance(v, (int, float, bool))})
    return row


def true_chunk_transforms(chunks):
    """Ground-truth Sim(3) chunk k -> chunk 0's prior frame: a chunk's prior frame is its first
    ground-truth camera scaled by its ``prior_scale`` (:func:`cm3d.data.synthetic.make_priors`)."""
    def to_world(c):
        s = c.meta["prior_scale"]
        return c.gt.cam_to_world[0] @ np.diag([1 / s, 1 / s, 1 / s, 1.0])

    W0 = np.linalg.inv(to_world(chunks[0]))
    return np.stack([W0 @ to_world(c) for c in chunks])


def sim3_errors(T, truth, poses, unit):
    """Errors of a Sim(3) chunk b -> chunk a against the truth: rotation (deg), log-scale, and the
    mean centre error (metres: ``unit`` chunk-a units per metre) of chunk b's ``poses`` placed by each."""
    from scipy.spatial.transform import Rotation

    sT, sG = float(sim3.scale(np.asarray(T, np.float64))), float(sim3.scale(np.asarray(truth, np.float64)))
    rot = float(np.rad2deg(Rotation.from_matrix((T[:3, :3] / sT).T @ (truth[:3, :3] / sG)).magnitude()))
    ca, cb = poses[:, :3, 3] @ T[:3, :3].T + T[:3, 3], poses[:, :3, 3] @ truth[:3, :3].T + truth[:3, 3]
    return {"rot_deg": rot, "log_scale": float(np.log(sT / sG)),
            "centre_m": float(np.mean(np.linalg.norm(ca - cb, axis=1)) / unit)}


def run_loop(args, level, drift: float = 1.0):
    """The loop variant: naive vs overlap stitching vs overlap + loop closure (the memory's
    registration) vs + the whole-trajectory refinement, with the loop constraint measured against
    the ground truth."""
    cfg = synthetic.WorldConfig(height=args.height, width=args.width)
    t0 = time.perf_counter()
    chunks, images, gt = synthetic.generate_long_video(args.scene, 0, args.frames, args.chunk, args.overlap, level,
                                                       cfg, loop=True, drift=drift)
    t_render = time.perf_counter() - t0
    ts = np.arange(args.frames) / cfg.fps
    ev = lambda P: metrics.evaluate_trajectories(ts, gt.cam_to_world, ts, np.asarray(P))["ate"]  # noqa: E731
    naive = stitch.naive_stitch(chunks)
    aligned = stitch.stitch_chunks(chunks, refine=False)
    t0 = time.perf_counter()
    mem = stitch.stitch_with_memory(chunks)  # the memory's loops, then the whole-trajectory refinement
    t_mem = time.perf_counter() - t0
    # overlap stitching + the same refinement (the same static masks: the pipeline's), no loop
    static = ~stitch.memory_sequence_result(mem, chunks).masks
    aligned_refined = stitch.stitch_chunks(chunks, static=static, refine=True)
    f = mem.refinement
    G0, Gt = f["chained_transforms"], true_chunk_transforms(chunks)
    out = {"ate_loop_naive": ev(naive.sequence.cam_to_world), "ate_loop_stitch": ev(aligned.sequence.cam_to_world),
           "ate_loop_stitch_refined": ev(aligned_refined.sequence.cam_to_world),
           "ate_loop_chained": ev(mem.poses_aligned), "ate_loop": ev(f["poses_stitched"]),
           "ate_loop_refined": ev(mem.sequence.cam_to_world),
           "loop_refine_kept": bool(mem.refined),
           # the floor of any chunk placement: every chunk placed by its ground-truth Sim(3)
           "ate_loop_true_transforms": ev(stitch.place_chunks(chunks, Gt).cam_to_world),
           "loops_recalled": len(mem.loops), "loops_kept": f["loops_kept"],
           "loop_discrepancy_max": f["loop_discrepancy_max"], "loop_limit": f["loop_limit"],
           "loop_recalls": f["recalls"], "loop_windows": f["windows"], "loop_pipeline_s": f["pipeline_s"],
           "loop_time_s": t_mem, "loop_render_s": t_render, "loop_drift": drift,
           "loop_end_to_start_m": float(np.linalg.norm(gt.cam_to_world[-1, :3, 3] - gt.cam_to_world[0, :3, 3])),
           "loop_pairs": [f"{lc.chunk}->{lc.other}" for lc in mem.loops], "loop_level": level,
           # loop closures measured in the images (long_video.loops), in the kept frame-level graph
           "image_loops": int(f["image_loops"].get("loops_used", 0)) if f["image_loops"]["kept"] else 0}
    if mem.loops:  # the loop across the most chunks (the camera back at its start)
        i = max(range(len(mem.loops)), key=lambda n: (mem.loops[n].chunk - mem.loops[n].other, -n))
        lc = mem.loops[i]
        a, b = lc.other, lc.chunk
        truth = np.linalg.inv(Gt[a]) @ Gt[b]
        poses = chunks[b].cam_to_world[lc.frames[0]:lc.frames[1] + 1]
        unit = chunks[a].meta["prior_scale"]
        for name, T in (("memory", lc.measured), ("prior_frames", lc.transform),
                        ("chain", np.linalg.inv(G0[a]) @ G0[b])):
            for k, v in sim3_errors(T, truth, poses, unit).items():
                out[f"loop_err_{k}_{name}"] = v
        # every loop forced in (no consistency check) at σ x 2, as if as accurate as an overlap
        A = np.stack([np.eye(4)] + [np.linalg.inv(G0[k - 1]) @ G0[k] for k in range(1, len(chunks))])
        forced = stitch.PoseGraphConfig(loop_quantile=1.0, loop_factor=2.0)
        G, _ = stitch.sim3_pose_graph(G0, A, mem.loops, forced)
        out["ate_loop_forced"] = ev(stitch.place_chunks(chunks, G).cam_to_world)
        truth_loops = [dataclasses.replace(x, transform=np.linalg.inv(Gt[x.other]) @ Gt[x.chunk]) for x in mem.loops]
        G, _ = stitch.sim3_pose_graph(G0, A, truth_loops, forced)
        out["ate_loop_true_constraint"] = ev(stitch.place_chunks(chunks, G).cam_to_world)
    out["loop_improvement"] = 1.0 - out["ate_loop"] / out["ate_loop_stitch"]
    out["loop_improvement_refined"] = 1.0 - out["ate_loop_refined"] / out["ate_loop_stitch_refined"]
    return out


def run_straight_memory(images, gt, level, args, cfg):
    """The straight (non-loop) video through :func:`cm3d.long_video.stitch_with_memory`: what loop
    closures from memory recall do where the camera does not come back."""
    ts = np.arange(len(images)) / cfg.fps
    chunks = synthetic.make_chunk_priors(images, gt, args.chunk, args.overlap, level, seed=args.scene, timestamps=ts)
    ev = lambda P: metrics.evaluate_trajectories(ts, gt.cam_to_world, ts, np.asarray(P))["ate"]  # noqa: E731
    mem = stitch.stitch_with_memory(chunks)
    return {"ate_straight_memory": ev(mem.refinement["poses_stitched"]), "ate_straight_chained": ev(mem.poses_aligned),
            "ate_straight_memory_refined": ev(mem.sequence.cam_to_world),
            "loops_recalled_straight": len(mem.loops), "loops_kept_straight": mem.refinement["loops_kept"]}


def print_loop(lp, title="loop variant"):
    print(f"\n{title} ({lp['loop_level']} noise, prior drift x{lp['loop_drift']:g}; the camera ends "
          f"{lp['loop_end_to_start_m']:.2f} m from its start): {lp['loops_recalled']} loop closures recalled across "
          f"chunks {lp['loop_pairs']} (kept by the consistency check: {lp['loops_kept']}; worst "
          f"discrepancy {lp['loop_discrepancy_max']:.1f} vs chi2 limit {lp['loop_limit']:.1f}; {lp['loop_recalls']} "
          f"recalls in {lp['loop_windows']} windows; pipeline {lp['loop_pipeline_s']:.0f} s); loop closures measured "
          f"in the images in loop+refine: {lp['image_loops']}\n")
    head = (f"{'ATE naive':>10} {'overlap':>9} {'+ loop (memory)':>16} | {'vs overlap':>10} "
            f"|| {'overlap+refine':>14} {'loop+refine':>12} | {'vs':>7} || {'forced σx2':>11} {'true loop':>10} "
            f"{'true chunks':>11}")
    print(head + "\n" + "-" * len(head))
    na = lambda k: f"{lp[k]:.4f}" if k in lp else "-"  # noqa: E731
    print(f"{lp['ate_loop_naive']:>10.4f} {lp['ate_loop_stitch']:>9.4f} {lp['ate_loop']:>16.4f} "
          f"| {100 * lp['loop_improvement']:>9.1f}% || "
          f"{lp['ate_loop_stitch_refined']:>14.4f} "
          f"{lp['ate_loop_refined']:>12.4f} | {100 * lp['loop_improvement_refined']:>6.1f}% || "
          f"{na('ate_loop_forced'):>11} {na('ate_loop_true_constraint'):>10} {lp['ate_loop_true_transforms']:>11.4f}")
    if "loop_err_rot_deg_chain" in lp:
        print("\nthe widest loop's Sim(3) against the ground truth (rotation, log-scale, mean centre error of the "
              "recalling window's cameras):")
        for name, label in (("memory", "memory recall (refined window frames)"),
                            ("prior_frames", "memory recall in the chunks' prior frames"),
                            ("chain", "chain of overlap alignments")):
            print(f"  {label:<44} {lp[f'loop_err_rot_deg_{name}']:6.2f} deg  {lp[f'loop_err_log_scale_{name}']:+.4f}  "
                  f"{lp[f'loop_err_centre_m_{name}']:.4f} m")


def format_table(rows):
    head = (f"{'level':>9} | {'ATE naive':>9} {'stitched':>9} {'refined':>8} {'kept':>5} | "
            f"{'vs naive':>8} {'vs stitched':>11} | {'scale err':>9} {'naive':>7} | {'overlap res':>11} "
            f"{'naive':>7} | {'time':>6}")
    lines = [head, "-" * len(head)]
    for r in rows:
        kept = ("yes" if r["refine_kept"] else "no") if r["refine_ran"] else "-"
        imp = 1.0 - r["ate_stitch_refined"] / r["ate_naive"] if r["ate_naive"] > 1e-12 else float("nan")
        gain = (f"{100 * (1.0 - r['ate_stitch_refined'] / r['ate_stitch']):>10.1f}%"
                if r["refine_ran"] and r["ate_stitch"] > 1e-12 else f"{'-':>11}")
        lines.append(
            f"{r['level']:>9} | {r['ate_naive']:>9.4f} {r['ate_stitch']:>9.4f} {r['ate_stitch_refined']:>8.4f} "
            f"{kept:>5} | {100 * imp:>7.1f}% {gain} | {100 * r['scale_err_max']:>8.2f}% "
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
    ap.add_argument("--refine-levels", default="slight,moderate,severe",
                    help="levels that also run the whole-trajectory refinement (comma-separated; '' for none)")
    ap.add_argument("--loop-level", default="moderate",
                    help="noise level of the loop variants (memory recall across chunks); 'off' to skip")
    ap.add_argument("--loop-drift", type=float, default=3.0,
                    help="the drifting loop variant's prior drift factor (synthetic.make_priors(drift=...)); "
                    "0 to skip it")
    ap.add_argument("--quick", action="store_true", help="60 frames at 48x64 in chunks of 20 (overlap 5), "
                    "moderate noise only, no loop variants")
    ap.add_argument("--json", default=None, metavar="PATH")
    args = ap.parse_args()
    levels = [lv for lv in args.levels.split(",") if lv]
    refine_levels = set(args.refine_levels.split(","))
    if args.quick:
        args.frames, args.chunk, args.overlap, args.height, args.width = 60, 20, 5, 48, 64
        levels, refine_levels = ["moderate"], {"moderate"}
        args.loop_level = "off"
    for lv in levels:
        if lv not in LEVELS:
            ap.error(f"--levels: unknown level {lv!r}; choose from {', '.join(LEVELS)}")
    if "moderate" not in levels:
        ap.error("--levels: must include 'moderate' (the headline numbers)")
    if args.loop_level != "off" and args.loop_level not in LEVELS:
        ap.error(f"--loop-level: unknown level {args.loop_level!r}; choose from {', '.join(LEVELS)} or off")
    if not args.loop_drift >= 0:
        ap.error(f"--loop-drift: must be >= 0, got {args.loop_drift}")
    t_all = time.perf_counter()
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
    print("\nATE in metres (Sim(3)-aligned); stitched: the priors aligned by Sim(3) on the overlaps; refined: + the "
          "whole-trajectory pose graph; 'vs naive' = 1 - refined / naive; scale err: worst boundary's relative "
          "scale error (naive: the scale jump it ignores); overlap res: shared-pixel residual after alignment / "
          "depth\n")
    print(format_table(rows))
    mod = next(r for r in rows if r["level"] == "moderate")
    out = {"ate_naive": mod["ate_naive"], "ate_stitch": mod["ate_stitch"],
           "ate_stitch_refined": mod["ate_stitch_refined"],
           "ate_improvement": 1.0 - mod["ate_stitch_refined"] / mod["ate_naive"],
           "ate_improvement_align": 1.0 - mod["ate_stitch"] / mod["ate_naive"],
           "ate_refine_gain": 1.0 - mod["ate_stitch_refined"] / mod["ate_stitch"],
           "frames": args.frames, "chunk": args.chunk, "overlap": args.overlap, "chunks": mod["chunks"],
           "height": cfg.height, "width": cfg.width, "render_s": t_render}
    for r in rows:
        for k, v in r.items():
            if k != "level" and isinstance(v, (int, float, bool)) and v == v:  # no NaN (not run)
                out[f"{k}_{r['level']}"] = v
    print(f"\nmoderate: stitched priors {out['ate_stitch']:.4f} m, refined {out['ate_stitch_refined']:.4f} m "
          f"({100 * out['ate_refine_gain']:.1f} % lower) vs naive {out['ate_naive']:.4f} m: "
          f"{100 * out['ate_improvement']:.1f} % lower than naive (target >= 50 %)")
    if args.loop_level != "off":
        lp = run_loop(args, args.loop_level)
        print_loop(lp)
        out.update({k: v for k, v in lp.items() if isinstance(v, (int, float)) and not isinstance(v, bool)})
        if args.loop_drift > 0:
            ld = run_loop(args, args.loop_level, args.loop_drift)
            print_loop(ld, "drifting loop variant")
            def ren(k):
                return k.replace("ate_loop", "ate_loopdrift", 1) if k.startswith("ate_loop") else "drift_" + k

            out.update({ren(k): v for k, v in ld.items() if isinstance(v, (int, float)) and not isinstance(v, bool)})
        sm = run_straight_memory(images, gt, args.loop_level, args, cfg)
        print(f"\nstraight video through the same memory stitching ({args.loop_level}): "
              f"{sm['loops_recalled_straight']} loop closures recalled, {sm['loops_kept_straight']} kept; "
              f"ATE {sm['ate_straight_chained']:.4f} (chained) -> {sm['ate_straight_memory']:.4f} (pose graph) -> "
              f"{sm['ate_straight_memory_refined']:.4f} (refined)")
        out.update(sm)
    out["total_s"] = time.perf_counter() - t_all
    print(f"\ntotal {out['total_s']:.0f} s")
    if args.json:
        write_json(args.json, out)


if __name__ == "__main__":
    main()
