"""How far the VGGT-like priors of the synthetic world are from the truth, per noise level.

    .venv/bin/python experiments/prior_noise.py [--scene 0 --visits 3 --frames 24] [--quick] [--json PATH]

Prints one row per visit and noise level (pose, depth and flow metrics of the priors) and, as headline figures, the mean over visits of each
metric per level: ``ate_prior_<level>``, ``rpe_trans_prior_<level>``, ``rpe_rot_prior_<level>``,
``abs_rel_prior_<level>``, plus ``dis_epe`` (OpenCV DIS flow error on static pixels, px).
"""

import argparse

import numpy as np

from cm3d.data import synthetic
from cm3d.outputs import write_json
from cm3d.eval import metrics


def dis_flow_epe(images: np.ndarray, gt_flow: np.ndarray, dynamic: np.ndarray) -> float:
    """Median end-point error (px) of OpenCV DIS flow against ground truth on static pixels."""
    from cm3d.ops import flow as oflow

    errs = [np.linalg.norm(oflow.compute_flow(images[i], images[i + 1]) - gt_flow[i], axis=-1)[~dynamic[i]]
            for i in range(len(images) - 1)]
    return float(np.median(np.concatenate(errs)))


def prior_rows(images, gt, visit: int, seed: int) -> list[dict]:
    """One row of prior-vs-truth metrics per noise level for one rendered visit."""
    epe = dis_flow_epe(images, gt.flow, gt.dynamic_mask)
    rows = []
    for level in synthetic.NOISE_LEVELS:
        seq = synthetic.make_priors(images, gt, level, seed=seed)
        pose = metrics.evaluate_trajectories(seq.timestamps, gt.cam_to_world, seq.timestamps, seq.cam_to_world)
        depth = metrics.depth_metrics(seq.depth, gt.depth, gt.depth > 0)
        rows.append({"visit": visit, "level": level, "prior_scale": seq.meta["prior_scale"],
                     **{k: pose[k] for k in ("ate", "ate_se3", "rpe_trans", "rpe_rot")},
                     "abs_rel": float(depth["abs_rel"]), "delta1": float(depth["delta1"]),
                     "dynamic_pct": 100.0 * float(gt.dynamic_mask.mean()), "dis_epe": epe})
    return rows


def run(scene: int, visits: int, frames: int, quick: bool) -> list[dict]:
    cfg = synthetic.WorldConfig(height=96, width=128) if quick else synthetic.WorldConfig()
    world = synthetic.make_scene(scene, cfg)
    print(f"scene {scene}: {visits} visits x {frames} frames at {cfg.height}x{cfg.width}\n")
    rows = []
    for v in range(visits):
        images, gt = synthetic.render_ground_truth(world, v, frames, cfg)
        rows += prior_rows(images, gt, v, seed=1009 * scene + v)
    cols = [("visit", "{:>5}"), ("level", "{:>9}"), ("prior_scale", "{:>11.3f}"), ("ate", "{:>9.4f}"),
            ("ate_se3", "{:>9.4f}"), ("rpe_trans", "{:>9.4f}"), ("rpe_rot", "{:>8.3f}"), ("abs_rel", "{:>8.4f}"),
            ("delta1", "{:>7.4f}"), ("dynamic_pct", "{:>11.1f}"), ("dis_epe", "{:>7.3f}")]
    head = " ".join(f"{name:>{len(fmt.format(rows[0][name]))}}" for name, fmt in cols)
    print("ATE/RPE trans (Sim3-aligned), ATE SE3 (no scale), RPE rot (deg); depth after scale & shift; "
          "DIS EPE (px, static pixels)\n")
    print("\n".join([head, "-" * len(head)] + [" ".join(fmt.format(r[n]) for n, fmt in cols) for r in rows]))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=int, default=0)
    ap.add_argument("--visits", type=int, default=3)
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--quick", action="store_true", help="small images, one short visit")
    ap.add_argument("--json", default=None, metavar="PATH")
    args = ap.parse_args()
    visits, frames = (1, 4) if args.quick else (args.visits, args.frames)
    rows = run(args.scene, visits, frames, args.quick)
    figures = {"dis_epe": float(np.mean([r["dis_epe"] for r in rows]))}
    for level in dict.fromkeys(r["level"] for r in rows):
        sel = [r for r in rows if r["level"] == level]
        for key in ("ate", "rpe_trans", "rpe_rot", "abs_rel"):
            figures[f"{key}_prior_{level}"] = float(np.mean([r[key] for r in sel]))
    print("\nmean over visits:")
    for k, v in figures.items():
        print(f"  {k:28s} {v:.5f}")
    if args.json:
        write_json(args.json, figures)


if __name__ == "__main__":
    main()
