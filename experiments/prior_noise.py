"""How far the VGGT-like priors of the synthetic world are from the truth, per noise level.

    .venv/bin/python experiments/prior_noise.py [--scene 0 --visits 3 --frames 24] [--quick] [--json PATH]

Prints the per-visit table of ``cm3d demo`` and, as headline figures, the mean over visits of each
metric per level: ``ate_prior_<level>``, ``rpe_trans_prior_<level>``, ``rpe_rot_prior_<level>``,
``abs_rel_prior_<level>``, plus ``dis_epe`` (OpenCV DIS flow error on static pixels, px).
"""

import argparse
import json

import numpy as np

from cm3d.data.atomic import atomic_write
from cm3d.demo import run_demo


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=int, default=0)
    ap.add_argument("--visits", type=int, default=3)
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--quick", action="store_true", help="small images, one short visit")
    ap.add_argument("--json", default=None, metavar="PATH")
    args = ap.parse_args()
    visits, frames = (1, 4) if args.quick else (args.visits, args.frames)
    rows = run_demo(args.scene, visits, frames, quick=args.quick)
    figures = {"dis_epe": float(np.mean([r["dis_epe"] for r in rows]))}
    for level in dict.fromkeys(r["level"] for r in rows):
        sel = [r for r in rows if r["level"] == level]
        for key in ("ate", "rpe_trans", "rpe_rot", "abs_rel"):
            figures[f"{key}_prior_{level}"] = float(np.mean([r[key] for r in sel]))
    print("\nmean over visits:")
    for k, v in figures.items():
        print(f"  {k:28s} {v:.5f}")
    if args.json:
        with atomic_write(args.json, "w") as f:
            json.dump(figures, f, indent=1)


if __name__ == "__main__":
    main()
