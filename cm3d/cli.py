"""The ``cm3d`` command: parse arguments, call the library, print. No logic lives here."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def _generate(args) -> int:
    from cm3d.data import io, synthetic

    cfg = synthetic.WorldConfig(height=args.height, width=args.width)
    out = Path(args.out)
    for v in range(args.visits):
        seq = synthetic.generate(args.scene, v, args.frames, args.level, cfg)
        path = out / f"scene{args.scene:03d}_visit{v:02d}.npz"
        io.save_sequence(path, seq)
        io.write_tum(path.with_suffix(".gt.txt"), seq.timestamps, seq.gt.cam_to_world)
        io.write_tum(path.with_suffix(".prior.txt"), seq.timestamps, seq.cam_to_world)
        print(f"wrote {path} ({seq.num_frames} frames, {seq.image_size[0]}x{seq.image_size[1]}, "
              f"level {args.level}) and its .gt.txt / .prior.txt trajectories")
    return 0


def _eval(args) -> int:
    from cm3d.eval.metrics import evaluate_trajectory_files

    m = evaluate_trajectory_files(args.gt, args.est, max_diff=args.max_diff)
    if args.json:
        print(json.dumps(m))
    else:
        print(f"pairs      {m['pairs']}")
        print(f"ATE (Sim3) {m['ate']:.6f}")
        print(f"ATE (SE3)  {m['ate_se3']:.6f}")
        print(f"RPE trans  {m['rpe_trans']:.6f}")
        print(f"RPE rot    {m['rpe_rot']:.6f} deg")
    return 0


def _demo(args) -> int:
    from cm3d.demo import run_demo

    run_demo(scene=args.scene, visits=args.visits, frames=args.frames, quick=args.quick,
             json_path=args.json)
    return 0


def _memory(args) -> int:
    import numpy as np

    from cm3d import memory

    bank, cfg = memory.load(args.bank)
    valid = np.asarray(bank.map_valid)
    if args.action == "ls":
        print(f"{args.bank}: {int(valid.sum())} of {cfg.max_maps} maps "
              f"(capacity {cfg.max_points} points, {cfg.max_keyframes} keyframes each)")
        for m in np.flatnonzero(valid):
            print(f"  map {m:3d}: {int(np.asarray(bank.point_valid[m]).sum()):6d} points, "
                  f"{int(np.asarray(bank.kf_valid[m]).sum()):3d} keyframes, {int(bank.visits[m])} visits")
        return 0
    if args.map_id is None or not (0 <= args.map_id < cfg.max_maps) or not valid[args.map_id]:
        raise ValueError(f"map id: {args.map_id} is not a stored map (valid: {np.flatnonzero(valid).tolist()})")
    m = args.map_id
    if args.action == "show":
        pts = np.asarray(bank.points[m])[np.asarray(bank.point_valid[m])]
        lo, hi = (pts.min(0), pts.max(0)) if len(pts) else (np.zeros(3), np.zeros(3))
        print(json.dumps({"map_id": int(m), "points": int(len(pts)), "keyframes": int(np.asarray(bank.kf_valid[m]).sum()),
                          "visits": int(bank.visits[m]), "bounds_min": lo.round(4).tolist(),
                          "bounds_max": hi.round(4).tolist()}, indent=1))
        return 0
    memory.save(memory.remove_map(bank, m), args.bank, cfg)
    print(f"removed map {m} from {args.bank}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="cm3d", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    g = sub.add_parser("generate", help="write synthetic multi-visit sequences (.npz + TUM trajectories)")
    g.add_argument("--out", default="out/synthetic", help="output folder")
    g.add_argument("--scene", type=int, default=0, help="scene seed")
    g.add_argument("--visits", type=int, default=2)
    g.add_argument("--frames", type=int, default=30)
    g.add_argument("--level", default="moderate", help="prior noise: none, slight, moderate, severe")
    g.add_argument("--height", type=int, default=384)
    g.add_argument("--width", type=int, default=512)
    g.set_defaults(func=_generate)

    e = sub.add_parser("eval", help="ATE/RPE of an estimated TUM trajectory against ground truth")
    e.add_argument("--gt", required=True, help="reference trajectory, TUM format")
    e.add_argument("--est", required=True, help="estimated trajectory, TUM format")
    e.add_argument("--max-diff", type=float, default=0.01, help="timestamp association tolerance (s)")
    e.add_argument("--json", action="store_true", help="print one JSON object")
    e.set_defaults(func=_eval)

    d = sub.add_parser("demo", help="metrics of noisy priors vs ground truth on a synthetic world")
    d.add_argument("--scene", type=int, default=0)
    d.add_argument("--visits", type=int, default=3)
    d.add_argument("--frames", type=int, default=24)
    d.add_argument("--quick", action="store_true", help="tiny images, for smoke tests")
    d.add_argument("--json", default=None, metavar="PATH", help="also write the table as JSON")
    d.set_defaults(func=_demo)

    m = sub.add_parser("memory", help="list, show or remove maps of a memory bank file")
    m.add_argument("action", choices=["ls", "show", "rm"])
    m.add_argument("bank", help="memory bank file (.cm3d)")
    m.add_argument("map_id", nargs="?", type=int, help="map id, for show and rm")
    m.set_defaults(func=_memory)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    t0 = time.perf_counter()
    try:
        rc = args.func(args)
    except (ValueError, FileNotFoundError) as err:
        print(f"cm3d {args.command}: error: {err}", file=sys.stderr)
        return 2
    if args.command not in ("eval", "memory"):
        print(f"done in {time.perf_counter() - t0:.1f} s")
    return rc


if __name__ == "__main__":
    sys.exit(main())
