"""Sensor holes: does a sequence with 20 % of its depth missing still refine like the hole-free one?

Synthetic visits (moderate prior noise) run through ``cm3d.pipeline.run`` three times: as rendered,
with 20 % of the pixels of every frame turned into holes (depth 0, confidence 0) at random pixels,
and with 20 % in smooth random blobs (what a depth sensor loses: dark, shiny, far or grazing
surfaces). Printed per variant: the mean and median ATE change of the refinement over the scenes,
and the mask IoU against the ground truth.

    .venv/bin/python experiments/sensor_holes.py                  # 192x256, 30 frames, scenes 0-3
    .venv/bin/python experiments/sensor_holes.py --size 96 128 --scenes 6
    .venv/bin/python experiments/sensor_holes.py --quick          # 48x64, 8 frames, scene 5
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def with_holes(seq, share: float, kind: str, seed: int):
    """``seq`` with holes (depth 0, confidence 0) at ``share`` of each frame's pixels: ``pixels``
    (independent) or ``blobs`` (the top ``share`` of a Gaussian-blurred noise field)."""
    import cv2

    rng = np.random.default_rng(seed)
    S, h, w = seq.depth.shape
    if kind == "pixels":
        m = rng.random((S, h, w)) < share
    else:
        m = np.zeros((S, h, w), bool)
        for t in range(S):
            field = cv2.GaussianBlur(rng.normal(size=(h, w)).astype(np.float32), (0, 0), max(1.0, h / 24))
            m[t] = field > np.quantile(field, 1 - share)
    return seq.replace(depth=np.where(m, 0, seq.depth).astype(np.float32),
                       depth_conf=np.where(m, 0, seq.depth_conf).astype(np.float32))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, nargs=2, default=(192, 256), metavar=("H", "W"))
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--scenes", type=int, default=4, help="scenes 0 .. N-1")
    ap.add_argument("--share", type=float, default=0.2, help="share of pixels that are holes")
    ap.add_argument("--quick", action="store_true", help="48x64, 8 frames, scene 5 only")
    ap.add_argument("--json", default=None, metavar="PATH", help="also write the headline figures (flat JSON)")
    args = ap.parse_args()
    from cm3d import outputs, pipeline
    from cm3d.data import synthetic
    from cm3d.eval import metrics

    (H, W), S, scenes = (48, 64), 8, [5]
    if not args.quick:
        (H, W), S, scenes = args.size, args.frames, list(range(args.scenes))
    world = synthetic.WorldConfig(height=H, width=W, supersample=1 if H < 100 else 2)
    cfg = pipeline.config_for(H, W, use_memory=False)
    rows = {"clean": [], "pixels": [], "blobs": []}
    for scene in scenes:
        seq = synthetic.generate(scene, 0, S, "moderate", world)
        variants = {"clean": seq, "pixels": with_holes(seq, args.share, "pixels", scene),
                    "blobs": with_holes(seq, args.share, "blobs", scene)}
        _, results = pipeline.run(list(variants.values()), cfg)
        for (name, _), res in zip(variants.items(), results):
            m = outputs.sequence_metrics(res)
            iou = float(metrics.mask_metrics(res.masks, seq.gt.dynamic_mask)["iou"])
            rows[name].append((-m["ate_reduction_pct"], iou, res.report.refinement_kept))
            print(f"scene {scene} {name:6s}: ATE {m['prior']['ate']:.5f} -> {m['refined']['ate']:.5f} "
                  f"({-m['ate_reduction_pct']:+.1f} %), mask IoU {iou:.3f}", flush=True)
    print(f"\n{H}x{W}, {S} frames, scenes {scenes}, {100 * args.share:g} % holes")
    print(f"{'variant':8s} {'mean ATE change':>16s} {'median':>8s} {'mask IoU':>9s} {'refinement kept':>16s}")
    figures = {"height": H, "width": W, "frames": S, "scenes": len(scenes), "hole_share": args.share}
    for name, v in rows.items():
        a = np.array([r[:2] for r in v])
        kept = sum(r[2] for r in v)
        print(f"{name:8s} {a[:, 0].mean():>+14.1f} % {np.median(a[:, 0]):>+6.1f} % {a[:, 1].mean():>9.3f} "
              f"{kept:>11d} of {len(v)}")
        figures.update({f"{name}_ate_change_pct_mean": round(float(a[:, 0].mean()), 2),
                        f"{name}_ate_change_pct_median": round(float(np.median(a[:, 0])), 2),
                        f"{name}_mask_iou": round(float(a[:, 1].mean()), 4)})
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=1) + "\n")


if __name__ == "__main__":
    main()
