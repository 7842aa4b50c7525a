"""The held-out world (:mod:`cm3d.data.held_out_world`): dynamic masks, pose refinement and memory
recall on a world cm3d was not built against. A baseline to move; never tune on it.

    .venv/bin/python experiments/held_out_world.py [--scenes 4 --frames 30] [--height 240 --width 320]
                                                   [--level moderate] [--quick] [--json PATH]

Every hall (scene seeds 0..N-1) is visited twice: visit 0 a lateral dolly (strong parallax),
visit 1 a near-pure rotation over the same area under another light. All visits run through the
library path of ``cm3d run VISIT --memory BANK`` (:func:`cm3d.pipeline.run`, the default
:func:`cm3d.pipeline.config_for` configuration, one bank threaded through every visit in the order
hall 0 visit 0, hall 0 visit 1, hall 1 visit 0, ...), with VGGT-like priors at ``--level``
(:func:`cm3d.data.priors.make_priors`).

Per visit: mask IoU / precision / recall (pooled over the visit's pixels) against the ground-truth
dynamic mask, the share of false-positive pixels within 2 px of a depth discontinuity, the IoU of
the MonST3R-style fixed-threshold baseline on the same inputs (:func:`cm3d.baselines.monst3r_masks`),
ATE of the prior and of cm3d (Sim(3)-aligned). Memory: a revisit (visit 1) is recalled when one of its windows
is accepted with the map its hall's visit 0 stored; any window accepted with another hall's map is
a false recall.

JSON keys: mask_iou, mask_precision, mask_recall, fp_edge_share, mask_iou_monst3r, ate_prior,
ate_cm3d (means over visits), revisits_recalled, revisits_total, false_recalls, visits, seconds.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # OpenBLAS threads spin on shared cores

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from cm3d import baselines, outputs, pipeline  # noqa: E402
from cm3d.data import held_out_world, priors  # noqa: E402
from cm3d.eval.metrics import mask_metrics  # noqa: E402
from cm3d.outputs import write_json  # noqa: E402


def depth_edges(depth: np.ndarray, radius: int = 2, jump: float = 0.05) -> np.ndarray:
    """Pixels (S, H, W) within ``radius`` px of a relative depth jump above ``jump``."""
    import cv2

    logd = np.log(np.maximum(depth, 1e-6))
    e = np.zeros(depth.shape, bool)
    e[:, :, 1:] |= np.abs(np.diff(logd, axis=2)) > jump
    e[:, 1:, :] |= np.abs(np.diff(logd, axis=1)) > jump
    k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    return np.stack([cv2.dilate(x.astype(np.uint8), k) > 0 for x in e])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--level", default="moderate", choices=list(priors.NOISE_LEVELS))
    ap.add_argument("--quick", action="store_true", help="1 hall, 2 visits of 8 frames at 48x64")
    ap.add_argument("--json", default=None, metavar="PATH")
    args = ap.parse_args()
    scenes, frames, (H, W) = (1, 8, (48, 64)) if args.quick else (args.scenes, args.frames, (args.height, args.width))
    wcfg = held_out_world.HeldOutConfig(height=H, width=W)
    cfg = pipeline.config_for(H, W)
    t_start = time.perf_counter()
    print(f"held-out world: {scenes} halls x 2 visits x {frames} frames at {W}x{H}, priors '{args.level}'")
    t0 = time.perf_counter()
    seqs = [held_out_world.generate(s, v, frames, args.level, wcfg) for s in range(scenes) for v in (0, 1)]
    render_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    kept = {}
    _, results = pipeline.run(seqs, cfg, observe=lambda i, inputs, *_: kept.__setitem__(i, inputs))
    run_s = time.perf_counter() - t0

    owner, rows = {}, []
    recalled, false_recalls = 0, 0
    head = (f"{'hall':>4s} {'visit':>5s} {'path':>8s} {'dyn %':>6s} {'IoU':>6s} {'prec':>6s} {'recall':>6s} "
            f"{'FP@edge':>7s} {'MonST3R':>7s} {'ATE prior':>9s} {'ATE cm3d':>9s}  memory")
    print("\n" + head + "\n" + "-" * len(head))
    for i, (seq, res) in enumerate(zip(seqs, results)):
        s, v = seq.meta["scene"], seq.meta["visit"]
        gt = seq.gt.dynamic_mask
        mm = {k: float(x) for k, x in mask_metrics(res.masks, gt).items()}
        base = (np.zeros_like(res.masks) if kept.get(i) is None
                else baselines.monst3r_masks(kept[i], seq.num_frames, gt.shape[1:], cfg))
        base_iou = float(mask_metrics(base, gt)["iou"])
        fp = res.masks & ~gt
        fp_edge = float((fp & depth_edges(seq.gt.depth)).sum() / max(fp.sum(), 1))
        m = outputs.sequence_metrics(res)
        accepted = [w.recalled_map for w in res.windows if w.accepted]
        right = [mid for mid in accepted if owner.get(mid) == (s, 0)] if v == 1 else []
        wrong = [mid for mid in accepted if mid in owner and owner[mid][0] != s]
        for w in res.windows:
            if w.created_map:
                owner[w.map_id] = (s, v)
        if v == 1:
            recalled += bool(right)
        false_recalls += bool(wrong)
        mem = ("recalled" if right else ("FALSE recall" if wrong else "no recall")) if (v == 1 or wrong) else "stored"
        row = {"iou": mm["iou"], "precision": mm["precision"], "recall": mm["recall"], "fp_edge": fp_edge,
               "iou_monst3r": base_iou,
               "ate_prior": m["prior"]["ate"], "ate_cm3d": m["refined"]["ate"]}
        rows.append(row)
        print(f"{s:4d} {v:5d} {seq.meta['path']:>8s} {100 * gt.mean():6.2f} {row['iou']:6.3f} {row['precision']:6.3f} "
              f"{row['recall']:6.3f} {row['fp_edge']:7.2f} {base_iou:7.3f} {row['ate_prior']:9.4f} "
              f"{row['ate_cm3d']:9.4f}  {mem}")
    mean = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
    print("-" * len(head))
    print(f"{'mean':>10s} {'':>8s} {'':>6s} {mean['iou']:6.3f} {mean['precision']:6.3f} {mean['recall']:6.3f} "
          f"{mean['fp_edge']:7.2f} {mean['iou_monst3r']:7.3f} {mean['ate_prior']:9.4f} {mean['ate_cm3d']:9.4f}")
    print(f"\nrevisits recalled {recalled}/{scenes}, false recalls {false_recalls}; render {render_s:.0f} s, "
          f"pipeline {run_s:.0f} s (compilation included), wall {time.perf_counter() - t_start:.0f} s")
    figures = {"mask_iou": mean["iou"], "mask_precision": mean["precision"], "mask_recall": mean["recall"],
               "fp_edge_share": mean["fp_edge"], "mask_iou_monst3r": mean["iou_monst3r"],
               "ate_prior": mean["ate_prior"], "ate_cm3d": mean["ate_cm3d"],
               "revisits_recalled": recalled, "revisits_total": scenes, "false_recalls": false_recalls,
               "visits": len(rows), "frames_per_visit": frames, "seconds": time.perf_counter() - t_start}
    if args.json:
        write_json(args.json, figures)


if __name__ == "__main__":
    main()
