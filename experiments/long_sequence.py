"""One long sequence through cm3d (issue 26): does the windows' refinement add up over many windows?

    .venv/bin/python experiments/long_sequence.py [--frames 120 --height 288 --width 384]
                                                  [--worlds own,held_out] [--level moderate] [--quick] [--json PATH]
                                                  [--kitchen-camera folder|colour]

One camera path per world (cm3d's own synthetic scene 0 visit 0, the held-out world's hall 0
visit 0, :mod:`cm3d.data.held_out_world`, and the real 7-Scenes kitchen of ``../shared/data``: all
its 390 frames at ``--resize`` 0.5, 320x240, whatever ``--frames``), VGGT-like priors at ``--level`` (jitter + random-walk
drift), given to :func:`cm3d.pipeline.run` as ONE sequence (default config for the image size).
Rows follow the paper's Table 9: the prior, cm3d without memory, cm3d with memory. For each cm3d row
two trajectories: ``chained`` (the windows' refinements chained anchor to anchor, what cm3d gave
before issue 26) and the final result (``cm3d``: the global pose graph of
:mod:`cm3d.pipeline.global_graph`, after the run's photometric check). ATE (Sim(3)-aligned), RPE
trans / rot on the whole trajectory, and the mean ATE of 40-frame segments each aligned on its own.

Chunked (``--chunks``, default 4 x 40 frames overlapping by 10, so 130 frames; off with ``--chunks 0``):
the same world renders one longer path once (the kitchen: all its frames); it is given (a) as one
sequence with one prior and (b) as VGGT-like chunks, each with its own prior (own unknown scale and
frame: :func:`cm3d.data.priors.segment_priors`), run by :func:`cm3d.long_video.stitch_with_memory`
(what ``cm3d run c0.npz c1.npz ...`` runs: the pipeline per chunk, the chunks' refined poses
stitched on their overlaps, the Sim(3) pose graph with recalled loops, loop closures measured in the
images, the whole-trajectory refinement), with and without memory. ``stitched chunk priors``: the
baseline, the chunks' priors stitched on their overlaps; ``refined chunks stitched``: cm3d before the
loops in the images and the whole-trajectory refinement.

JSON keys per world ``W`` (own, held_out, kitchen): ``W_ate_prior``, ``W_ate_chained_nomem``, ``W_ate_nomem``,
``W_ate_chained``, ``W_ate`` (with memory), ``W_ratio`` (= ate / ate_prior, target <= 0.5),
``W_seg_ate_prior``, ``W_seg_ate_chained``, ``W_seg_ate``, ``W_rpe_trans_*``, ``W_rpe_rot_*``,
``W_windows_dropped``, ``W_global_kept``; chunked: ``W_chunk_ate_stitched_prior``,
``W_chunk_ate_stitched`` / ``W_chunk_ate_stitched_nomem`` (the refined chunks stitched),
``W_chunk_ate_one_sequence`` (b's video as one sequence), ``W_chunk_ate`` / ``W_chunk_ate_nomem``,
``W_chunk_image_loops`` / ``W_chunk_image_loops_nomem`` (image loops in the kept frame-level graph, 0
when none), ``W_chunk_ratio`` (= chunk_ate / chunk_ate_stitched_prior, target <= 0.5), ``W_chunk_vs_one`` (=
chunk_ate / chunk_ate_one_sequence, target <= 1.3); ``seconds``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # OpenBLAS threads spin on shared cores

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from cm3d import pipeline  # noqa: E402
from cm3d.data import held_out_world, priors, synthetic  # noqa: E402
from cm3d.eval import metrics  # noqa: E402
from cm3d.outputs import write_json  # noqa: E402

SEGMENT = 40


KITCHEN = Path(__file__).resolve().parents[2] / "shared" / "data" / "sevenscenes_redkitchen"


def kitchen(resize: float, camera: str = "folder"):
    """Every frame of the shared 7-Scenes redkitchen (390: every 2nd of 100-398 and 460-938, so one
    jump of 62 frames) at ``resize``, with ground truth, seen by ``camera``: "folder" (the folder's one K)
    or "colour" (the Kinect colour camera, :data:`cm3d.data.sevenscenes.KINECT_COLOUR`)."""
    from cm3d.data import sevenscenes

    folder = Path(os.environ.get("CM3D_SHARED_DATA", KITCHEN.parent)) / KITCHEN.name
    colour = sevenscenes.KINECT_COLOUR if camera == "colour" else None
    return sevenscenes.load_sevenscenes(folder, resize=resize, colour=colour)


def make_world(name: str, frames: int, height: int, width: int, level: str, resize: float = 0.5,
               camera: str = "folder"):
    if name == "kitchen":
        return priors.priors_for(kitchen(resize, camera), level, seed=0)  # all its frames, whatever --frames
    if name == "own":
        cfg = synthetic.WorldConfig(height=height, width=width)
        return synthetic.generate(0, 0, frames, level, cfg)
    if name == "held_out":
        return held_out_world.generate(0, 0, frames, level, held_out_world.HeldOutConfig(height=height, width=width))
    raise ValueError(f"unknown world {name!r}")


def render(name: str, frames: int, height: int, width: int, resize: float = 0.5, camera: str = "folder"):
    """(images, ground truth, timestamps) of visit 0 of the world's scene 0 (one render for both
    uses); the kitchen: its frames (all of them)."""
    if name == "kitchen":
        seq = kitchen(resize, camera)
        return np.asarray(seq.images), seq.gt, np.asarray(seq.timestamps, np.float64)
    if name == "own":
        cfg = synthetic.WorldConfig(height=height, width=width)
        return (*synthetic.render_ground_truth(synthetic.make_scene(0, cfg), 0, frames, cfg), np.arange(frames) / cfg.fps)
    cfg = held_out_world.HeldOutConfig(height=height, width=width)
    return (*held_out_world.render_visit(held_out_world.make_hall(0), 0, frames, cfg), np.arange(frames) / cfg.fps)


def run_chunked(name: str, args) -> tuple[dict, list]:
    """The chunked comparison of the module docstring for one world."""
    from cm3d import long_video

    n = args.chunk + (args.chunks - 1) * (args.chunk - args.overlap)
    images, gt, ts = render(name, n, args.height, args.width, args.resize, args.kitchen_camera)
    n = len(images)  # the kitchen: all its frames
    ranges = synthetic.chunk_ranges(n, args.chunk, args.overlap)
    chunks = priors.segment_priors(images, gt, ranges, args.level, seed=1, timestamps=ts)
    whole = priors.make_priors(images, gt, args.level, seed=2, timestamps=ts)
    ate = lambda P: float(metrics.ate(np.asarray(P, np.float64), gt.cam_to_world))  # noqa: E731
    H, W = whole.image_size
    _, (one,) = pipeline.run(whole, pipeline.config_for(H, W))
    out, rows = {}, []
    for mem in (True,) if args.quick else (False, True):
        cfg = long_video.memory_config_for_chunks(H, W, [c.num_frames for c in chunks], use_memory=mem)
        t0 = time.perf_counter()
        res = long_video.stitch_with_memory(chunks, args.overlap, pipeline_config=cfg)
        dt = time.perf_counter() - t0
        tag = "" if mem else "_nomem"
        out[f"{name}_chunk_ate{tag}"] = ate(res.sequence.cam_to_world)
        out[f"{name}_chunk_ate_stitched{tag}"] = ate(res.refinement["poses_stitched"])
        out[f"{name}_chunk_seconds{tag}"] = dt
        il = res.refinement["image_loops"]
        out[f"{name}_chunk_image_loops{tag}"] = int(il.get("loops_used", 0)) if il["kept"] else 0
        if mem:
            out[f"{name}_chunk_ate_stitched_prior"] = ate(res.refinement["poses_stitched_prior"])
            out[f"{name}_chunk_recalls"] = int(res.refinement["recalls"])
    out[f"{name}_chunk_ate_one_prior"] = ate(whole.cam_to_world)
    out[f"{name}_chunk_ate_one_sequence"] = ate(one.poses)
    out[f"{name}_chunk_ratio"] = out[f"{name}_chunk_ate"] / out[f"{name}_chunk_ate_stitched_prior"]
    out[f"{name}_chunk_vs_one"] = out[f"{name}_chunk_ate"] / out[f"{name}_chunk_ate_one_sequence"]
    for label, key in (("stitched chunk priors", "chunk_ate_stitched_prior"),
                       ("refined chunks stitched, no memory", "chunk_ate_stitched_nomem"),
                       ("cm3d chunks without memory", "chunk_ate_nomem"),
                       ("refined chunks stitched, memory", "chunk_ate_stitched"), ("cm3d chunks with memory", "chunk_ate"),
                       ("one prior for the whole video", "chunk_ate_one_prior"),
                       ("cm3d on the video as one sequence", "chunk_ate_one_sequence")):
        if f"{name}_{key}" in out:
            rows.append((name, label, out[f"{name}_{key}"]))
    return out, rows


def trajectory_figures(seq, P, segment: int) -> dict:
    ts, gt = seq.timestamps, seq.gt.cam_to_world
    m = metrics.evaluate_trajectories(ts, gt, ts, P)
    segs = [float(metrics.ate(P[a:a + segment], gt[a:a + segment])) for a in range(0, len(P) - 2, segment)
            if len(P[a:a + segment]) >= 3]
    return {"ate": m["ate"], "rpe_trans": m["rpe_trans"], "rpe_rot": m["rpe_rot"], "seg_ate": float(np.mean(segs))}


def run_world(name: str, args) -> tuple[dict, list]:
    seq = make_world(name, args.frames, args.height, args.width, args.level, args.resize, args.kitchen_camera)
    H, W = seq.image_size
    out, rows = {}, []
    prior = trajectory_figures(seq, np.asarray(seq.cam_to_world, np.float64), args.segment)
    rows.append((name, "prior", prior, None))
    for mem in (True,) if args.quick else (False, True):
        cfg = pipeline.config_for(H, W, use_memory=mem)
        t0 = time.perf_counter()
        _, (res,) = pipeline.run(seq, cfg)
        dt = time.perf_counter() - t0
        tag = "" if mem else "_nomem"
        ch = trajectory_figures(seq, res.chained, args.segment)
        fin = trajectory_figures(seq, res.poses, args.segment)
        label = "cm3d with memory" if mem else "cm3d without memory"
        rows.append((name, label + " (chained windows)", ch, None))
        rows.append((name, label, fin, dt))
        g = res.global_graph or {}
        for k, v in (("ate_chained", ch["ate"]), ("ate", fin["ate"]), ("seg_ate_chained", ch["seg_ate"]),
                     ("seg_ate", fin["seg_ate"]), ("rpe_trans", fin["rpe_trans"]), ("rpe_rot", fin["rpe_rot"]),
                     ("rpe_trans_chained", ch["rpe_trans"]), ("rpe_rot_chained", ch["rpe_rot"]),
                     ("windows_dropped", g.get("windows_dropped", -1)), ("global_kept", bool(g.get("kept", False))),
                     ("refinement_kept", bool(res.report.refinement_kept)), ("seconds", dt)):
            out[f"{name}_{k}{tag}"] = v
    out[f"{name}_ate_prior"] = prior["ate"]
    out[f"{name}_seg_ate_prior"] = prior["seg_ate"]
    out[f"{name}_rpe_trans_prior"], out[f"{name}_rpe_rot_prior"] = prior["rpe_trans"], prior["rpe_rot"]
    out[f"{name}_ratio"] = out[f"{name}_ate"] / prior["ate"]
    if f"{name}_ate_nomem" in out:
        out[f"{name}_ratio_nomem"] = out[f"{name}_ate_nomem"] / prior["ate"]
    return out, rows


def format_table(rows, segment: int) -> str:
    head = f"{'world':>9} | {'trajectory':<40} | {'ATE':>8} {'RPE tr':>8} {'RPE rot':>8} | {f'ATE/{segment}f':>9} | {'time':>6}"
    lines = [head, "-" * len(head)]
    for name, label, f, dt in rows:
        t = f"{dt:5.0f}s" if dt is not None else f"{'':>6}"
        lines.append(f"{name:>9} | {label:<40} | {f['ate']:8.4f} {f['rpe_trans']:8.4f} {f['rpe_rot']:8.3f} | "
                     f"{f['seg_ate']:9.4f} | {t}")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--height", type=int, default=288)
    ap.add_argument("--width", type=int, default=384)
    ap.add_argument("--segment", type=int, default=SEGMENT)
    ap.add_argument("--worlds", default="own,held_out,kitchen")
    ap.add_argument("--resize", type=float, default=0.5, help="the kitchen's image scale (0.5: 320x240)")
    ap.add_argument("--level", default="moderate", choices=list(priors.NOISE_LEVELS))
    ap.add_argument("--chunks", type=int, default=4, help="chunks of the chunked comparison (0: none)")
    ap.add_argument("--chunk", type=int, default=40)
    ap.add_argument("--overlap", type=int, default=10)
    ap.add_argument("--quick", action="store_true", help="30 frames at 48x64, own world only; 2 chunks of 8")
    ap.add_argument("--kitchen-camera", choices=("colour", "folder"), default="folder",
                    help="folder: the folder's K (the depth camera's) for both images (default); colour: the "
                         "Kinect colour camera's K and place, the depth registered into it (docs/real_data.md)")
    ap.add_argument("--json", default=None, metavar="PATH")
    args = ap.parse_args()
    worlds = [w for w in args.worlds.split(",") if w]
    if args.quick:
        args.frames, args.height, args.width, args.segment = 30, 48, 64, 10
        # chunks of 8: memory_config_for_chunks then gives config_for's own small config, so the
        # chunks reuse the program the single sequence compiled
        args.chunks, args.chunk, args.overlap = min(args.chunks, 2), 8, 2
        worlds = ["own"]
    for w in worlds:
        if w not in ("own", "held_out", "kitchen"):
            ap.error(f"--worlds: unknown world {w!r} (own, held_out, kitchen)")
    if args.frames < 3 or args.segment < 3:
        ap.error("--frames and --segment must be >= 3")
    if args.chunks < 0 or args.chunks == 1 or (args.chunks and not 0 < args.overlap < args.chunk):
        ap.error("--chunks: 0 or >= 2, with 0 < --overlap < --chunk")
    t0 = time.perf_counter()
    out, rows = {"frames": args.frames, "height": args.height, "width": args.width, "level": args.level}, []
    for w in worlds:
        o, r = run_world(w, args)
        out.update(o)
        rows += r
    chunk_rows = []
    if args.chunks:
        for w in worlds:
            o, r = run_chunked(w, args)
            out.update(o)
            chunk_rows += r
    out["seconds"] = time.perf_counter() - t0
    print(f"{args.frames} frames at {args.height}x{args.width}, {args.level} prior noise, one sequence each; "
          f"ATE Sim(3)-aligned; ATE/{args.segment}f: mean over {args.segment}-frame segments aligned on their own\n")
    print(format_table(rows, args.segment))
    for w in worlds:
        nomem = f", {out[f'{w}_ratio_nomem']:.3f} without" if f"{w}_ratio_nomem" in out else ""
        print(f"\n{w}: cm3d / prior ATE = {out[f'{w}_ratio']:.3f} with memory{nomem} (target <= 0.5); "
              f"windows dropped by the global graph {out[f'{w}_windows_dropped']}")
    if chunk_rows:
        n = args.chunk + (args.chunks - 1) * (args.chunk - args.overlap)
        print(f"\nchunked: chunks of {args.chunk} frames overlapping by {args.overlap} ({args.chunks} chunks, {n} "
              "frames; the kitchen: all its frames), each with its own prior (scale, frame, noise); ATE Sim(3)-aligned\n")
        head = f"{'world':>9} | {'trajectory':<36} | {'ATE':>8}"
        print(head + "\n" + "-" * len(head))
        for name, label, v in chunk_rows:
            print(f"{name:>9} | {label:<36} | {v:8.4f}")
        for w in worlds:
            print(f"\n{w}: chunked cm3d / stitched priors = {out[f'{w}_chunk_ratio']:.3f} (target <= 0.5), "
                  f"chunked / one sequence = {out[f'{w}_chunk_vs_one']:.3f} (target <= 1.3)")
    if args.json:
        write_json(args.json, out)


if __name__ == "__main__":
    main()
