"""``cm3d demo``: a multi-visit synthetic world, and how far its VGGT-like priors are from the truth.

Until the pipeline lands this is the main job on the embedded default: it renders several visits
of one scene, derives priors at every noise level, and prints pose, depth and flow metrics of the
priors against ground truth (the numbers the later stages must beat).
"""

from __future__ import annotations

import json

import numpy as np

from cm3d.data import synthetic
from cm3d.data.atomic import atomic_write
from cm3d.eval import metrics


def dis_flow_epe(images: np.ndarray, gt_flow: np.ndarray, dynamic: np.ndarray) -> float:
    """Median end-point error (px) of OpenCV DIS flow against ground truth on static pixels."""
    import cv2

    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    errs = []
    for i in range(len(images) - 1):
        g0, g1 = (cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in (images[i], images[i + 1]))
        err = np.linalg.norm(dis.calc(g0, g1, None) - gt_flow[i], axis=-1)
        errs.append(err[~dynamic[i]])
    return float(np.median(np.concatenate(errs)))


def prior_rows(images, gt, visit: int, seed: int) -> list[dict]:
    """One row of prior-vs-truth metrics per noise level for one rendered visit."""
    epe = dis_flow_epe(images, gt.flow, gt.dynamic_mask)
    rows = []
    for level in synthetic.NOISE_LEVELS:
        seq = synthetic.make_priors(images, gt, level, seed=seed)
        pose = metrics.evaluate_trajectories(seq.timestamps, gt.cam_to_world, seq.timestamps, seq.cam_to_world)
        depth = metrics.depth_metrics(seq.depth, gt.depth, gt.depth > 0)
        rows.append({
            "visit": visit, "level": level, "frames": seq.num_frames,
            "prior_scale": seq.meta["prior_scale"], **{k: pose[k] for k in ("ate", "ate_se3", "rpe_trans", "rpe_rot")},
            "abs_rel": float(depth["abs_rel"]), "delta1": float(depth["delta1"]),
            "dynamic_pct": 100.0 * float(gt.dynamic_mask.mean()), "dis_epe": epe,
        })
    return rows


def format_table(rows: list[dict]) -> str:
    cols = [("visit", "{:>5}"), ("level", "{:>9}"), ("frames", "{:>6}"), ("prior_scale", "{:>11.3f}"),
            ("ate", "{:>9.4f}"), ("ate_se3", "{:>9.4f}"), ("rpe_trans", "{:>9.4f}"), ("rpe_rot", "{:>8.3f}"),
            ("abs_rel", "{:>8.4f}"), ("delta1", "{:>7.4f}"), ("dynamic_pct", "{:>11.1f}"), ("dis_epe", "{:>7.3f}")]
    head = " ".join(f"{name:>{len(fmt.format(rows[0][name]))}}" for name, fmt in cols)
    lines = [head, "-" * len(head)]
    lines += [" ".join(fmt.format(r[name]) for name, fmt in cols) for r in rows]
    return "\n".join(lines)


def run_demo(scene: int = 0, visits: int = 3, frames: int = 24, quick: bool = False,
             json_path: str | None = None) -> list[dict]:
    cfg = synthetic.WorldConfig(height=96, width=128) if quick else synthetic.WorldConfig()
    world = synthetic.make_scene(scene, cfg)
    print(f"scene {scene}: room {2 * world.room_half.round(2)} m, {visits} visits x {frames} frames "
          f"at {cfg.height}x{cfg.width}")
    rows = []
    for v in range(visits):
        images, gt = synthetic.render_ground_truth(world, v, frames, cfg)
        rows += prior_rows(images, gt, v, seed=1009 * scene + v)
    print("\nVGGT-like priors vs ground truth (ATE/RPE trans in metres after Sim3 alignment, ATE SE3 "
          "without scale;\nRPE rot in degrees; depth after per-sequence scale & shift; DIS EPE in px on "
          "static pixels)\n")
    print(format_table(rows))
    if json_path:
        with atomic_write(json_path, "w") as f:
            json.dump(rows, f, indent=1)
    return rows
