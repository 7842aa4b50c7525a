"""Video depth from multi-view fusion with the refined poses vs the prior's depth (the paper's Table 1), and fps.

    .venv/bin/python experiments/video_depth.py [--scenes 3 --frames 40] [--quick] [--json PATH]

Each scene is visited twice at *moderate* prior noise and both visits run through the pipeline
with one memory bank (as ``experiments/camera_pose.py``). For every visit:

* ``prior``: the foundation model's per-frame depth as given;
* ``refined``: every frame's depth re-estimated from its 8 nearest frames (``t +- 1 .. 4``) with *the
  refined poses* (:func:`cm3d.eval.fusion.fuse_depths`: each neighbour's prior depth is
  reprojected into the frame at full resolution, kept where it agrees with the frame's own depth
  (occlusion test, 5 %, and a 1 px round trip), and averaged with the frame's own depth; two
  passes; pixels no neighbour agrees with keep the prior). Static pixels only: the pipeline's
  dynamic masks;
* ``prior poses`` (a control): the same fusion with the *prior* poses: what the refinement
  contributes;
* ``true poses`` (an oracle): the same fusion with the ground-truth poses (in the prior's frame and
  scale): the best the fusion of these prior depths can do.

Metrics: Abs Rel and δ<1.25 after per-sequence median scale alignment
(:func:`cm3d.eval.metrics.depth_metrics_median`) against the ground-truth depth, on every pixel with
ground truth > 0 that is not on a moving object. ``fused`` is the share of those pixels where at
least one neighbour agreed (refined poses). The prior's depth error model is reported beside:
``frame scale`` is the spread (std) of the prior's per-frame scale against the ground truth (what a
per-sequence median alignment leaves), ``frame-scaled`` the prior's Abs Rel after an oracle
*per-frame* median alignment (what is left once that per-frame scale is gone), ``image bias`` the
mean relative error the prior makes *at the same pixel in every frame* (the per-pixel median over
frames of prior / ground truth after the per-frame scale): neighbours that see a point at nearly
the same pixel share it, so fusion cannot average it away.

``fps_pipeline`` is the frames per second of :func:`cm3d.pipeline.run` on the revisit, compiled,
memory holding visit 1: flow and keypoints, the back end, the global graph and the checks (until stop
46 the back end alone, ``fps_backend``; ``experiments/bench_backend.py`` measures that).

JSON keys (means over visits): ``absrel_prior``, ``delta1_prior``, ``absrel_refined``,
``delta1_refined``, ``fps_pipeline``, plus ``absrel_prior_poses``, ``delta1_prior_poses``,
``absrel_true_poses``, ``delta1_true_poses``, ``fused_share``, ``absrel_prior_frame_scaled``,
``prior_frame_scale_std``, ``prior_image_bias``, ``fusion_s`` (seconds per fusion of one visit, compiled).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # OpenBLAS threads spin on shared cores

import time  # noqa: E402
import warnings  # noqa: E402

import numpy as np  # noqa: E402

from camera_pose import LEVEL, mean_figures, parse_args, revisit_runs, write_figures  # noqa: E402

VARIANTS = ("prior", "prior_poses", "refined", "true_poses")
OFFSETS = (-4, -3, -2, -1, 1, 2, 3, 4)


def true_poses_in_prior_frame(seq) -> np.ndarray:
    """Ground-truth cam_to_world (S, 4, 4) expressed like the prior: first camera at the origin,
    translations times the prior's scale (the oracle for the fusion)."""
    gt = np.asarray(seq.gt.cam_to_world, np.float64)
    rel = np.linalg.inv(gt[0]) @ gt
    rel[:, :3, 3] *= float(seq.meta["prior_scale"])
    return rel


def prior_error_model(seq, valid) -> dict:
    """How much of the prior's depth error is a per-frame scale: the std of the per-frame median
    ratio prior / ground truth (relative to its median), and the prior's Abs Rel after an oracle
    per-frame median alignment."""
    from cm3d.eval import metrics

    gt = np.asarray(seq.gt.depth, np.float64)
    d = np.asarray(seq.depth, np.float64)
    ratio = np.where(valid & (gt > 0) & (d > 0), d / np.where(gt > 0, gt, 1.0), np.nan)
    per_frame = np.nanmedian(ratio.reshape(len(d), -1), axis=1)
    scaled = d / per_frame[:, None, None]
    m = metrics.depth_metrics_median(scaled.astype(np.float32), seq.gt.depth, valid)
    # an error fixed in image coordinates (the same in every frame): the per-pixel median over frames
    with warnings.catch_warnings():  # pixels that are never valid (e.g. always on a moving object)
        warnings.simplefilter("ignore", RuntimeWarning)
        fixed = np.nanmedian(ratio / per_frame[:, None, None], axis=0)
    fixed_err = np.abs(np.broadcast_to(fixed, ratio.shape) - 1.0)[np.isfinite(ratio)]
    return {"prior_frame_scale_std": float(np.std(per_frame / np.median(per_frame))),
            "absrel_prior_frame_scaled": float(m["abs_rel"]), "prior_image_bias": float(np.nanmean(fixed_err))}


def visit_row(scene, visit, seq, result, cfg) -> dict:
    from cm3d.eval import fusion, metrics

    gt = seq.gt
    depth = np.asarray(seq.depth, np.float32)
    usable = ~np.asarray(result.masks, bool) & (depth > 0)
    K = np.asarray(seq.intrinsic, np.float32)
    nb = fusion.neighbour_frames(len(depth), OFFSETS)
    fused, times = {}, []
    for name, poses in (("prior_poses", seq.cam_to_world), ("refined", result.poses),
                        ("true_poses", true_poses_in_prior_frame(seq))):
        t0 = time.perf_counter()
        out = fusion.fuse_depths(depth, usable, np.asarray(poses, np.float32), K, nb, cfg=cfg)
        fused[name] = (np.asarray(out.depth), np.asarray(out.support))
        times.append(time.perf_counter() - t0)
    valid = (gt.depth > 0) & ~gt.dynamic_mask
    row = {"scene": scene, "visit": visit, "fused_share": float(np.mean(fused["refined"][1][valid] > 0)),
           "fusion_s": float(np.median(times[1:])), **prior_error_model(seq, valid)}
    for name in VARIANTS:
        pred = depth if name == "prior" else fused[name][0]
        m = metrics.depth_metrics_median(pred, gt.depth, valid)
        row |= {f"absrel_{name}": float(m["abs_rel"]), f"delta1_{name}": float(m["delta1"])}
    return row


def format_table(rows) -> str:
    head = (f"{'scene':>5} {'visit':>5} | {'AbsRel prior':>12} {'prior poses':>11} {'refined':>8} {'true poses':>10} | "
            f"{'δ<1.25 prior':>12} {'prior poses':>11} {'refined':>8} {'true poses':>10} | {'fused':>6} | "
            f"{'frame scale':>11} {'frame-scaled':>12} {'image bias':>10}")
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(f"{r['scene']:>5} {r['visit']:>5} | {r['absrel_prior']:>12.4f} {r['absrel_prior_poses']:>11.4f} "
                     f"{r['absrel_refined']:>8.4f} {r['absrel_true_poses']:>10.4f} | {r['delta1_prior']:>12.4f} "
                     f"{r['delta1_prior_poses']:>11.4f} {r['delta1_refined']:>8.4f} {r['delta1_true_poses']:>10.4f} | "
                     f"{r['fused_share']:>6.3f} | {r['prior_frame_scale_std']:>11.4f} "
                     f"{r['absrel_prior_frame_scaled']:>12.4f} {r['prior_image_bias']:>10.4f}")
    return "\n".join(lines)


def main() -> None:
    from cm3d.eval import fusion

    args, use_cache, wcfg, scenes, frames = parse_args(__doc__)
    cfg = fusion.FusionConfig()
    print(f"{scenes} scene(s) x 2 visits x {frames} frames at {wcfg.height}x{wcfg.width}, {LEVEL} prior noise; "
          f"fusion of the frames t{OFFSETS[0]:+d} .. t{OFFSETS[-1]:+d}, agreement {100 * cfg.rel_tol:.0f} % / "
          f"{cfg.px_tol:g} px, {cfg.iterations} passes")
    rows, fps = [], []
    t0 = time.perf_counter()
    for s in range(scenes):
        run = revisit_runs(s, frames, wcfg, no_memory=False, use_cache=use_cache)
        fps.append(frames / run["run_s"])
        for v, (seq, res) in enumerate(zip(run["seqs"], run["res_mem"])):
            rows.append(visit_row(s, v + 1, seq, res, cfg))
        print(f"  scene {s} done ({time.perf_counter() - t0:.0f} s)", flush=True)
    keys = ([f"{k}_{name}" for name in VARIANTS for k in ("absrel", "delta1")]
            + ["fused_share", "fusion_s", "absrel_prior_frame_scaled", "prior_frame_scale_std", "prior_image_bias"])
    figures = mean_figures(rows, keys)
    figures["fps_pipeline"] = float(np.median(fps))
    print("\nAbs Rel / δ<1.25 after per-sequence median scaling, on ground-truth static pixels; prior poses / "
          "refined / true poses: the prior depths of 9 frames fused with those poses; fused: share of pixels a "
          "neighbour agreed with (refined); frame scale: std of the prior's per-frame depth scale, frame-scaled: "
          "the prior's Abs Rel after an oracle per-frame scale; image bias: mean relative error of the prior "
          "that is fixed in image coordinates (the same in every frame), which fusing frames cannot average\n")
    print(format_table(rows + [{"scene": "mean", "visit": "", **figures}]))
    a = figures["absrel_prior"]
    print("\nAbs Rel vs prior: " + ", ".join(f"{n.replace('_', ' ')} {100 * (figures['absrel_' + n] - a) / a:+.1f} %"
                                             for n in VARIANTS[1:]))
    print(f"fusion: {figures['fusion_s']:.1f} s per visit ({frames} frames, compiled)")
    print(f"pipeline.run: {figures['fps_pipeline']:.1f} frames/s at {wcfg.height}x{wcfg.width} (revisit, compiled; "
          f"per scene: {', '.join(f'{f:.1f}' for f in fps)})")
    write_figures(args, figures, scenes, frames, wcfg)


if __name__ == "__main__":
    main()
