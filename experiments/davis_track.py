"""Real DAVIS 2016 videos: the DAVIS region measure J of the mask refinement + tracking stage
(prompted from the first frame's ground-truth mask) and of the flow-only GMM motion cue.

    .venv/bin/python experiments/davis_track.py [--data DIR] [--sequences blackswan,camel,...]
                                                [--resize 1.0] [--max-frames N] [--quick] [--json PATH]

``DIR`` (default ``../shared/data/davis2016``, or under ``$CM3D_SHARED_DATA``) holds DAVIS-layout
folders ``SEQ/images/*.jpg`` and ``SEQ/masks/*.png`` (binary foreground mask of every frame;
:func:`cm3d.data.davis.load_davis`). The videos have no depth and no poses, so only the two
stages that need neither are measured:

* ``track``: :func:`cm3d.refine.refine_and_track` (GrabCut refinement, flow-warped tracking) with
  frame 0's *ground-truth* mask as its detection and nothing detected afterwards: DAVIS's
  semi-supervised protocol, which SAM2 is scored with (~0.9 J; the classical 2016 propagation
  methods 0.6-0.7). Without geometry every pixel is a candidate (the tracked mask is not cut by a
  motion cue) and the mask does not grow into candidate regions; pixels GrabCut adds outside the
  tracked mask are dropped when they move like the background (``TrackConfig.check_added``: colour and
  motion are all the evidence here). J over frames 1..S-2 (frame 0 is the prompt; the last frame has
  no forward flow);
* ``flow``: :func:`cm3d.motion.flow_motion_cue` (a GMM on the DIS flow, moving = outside the
  slowest component), no prompt, frames 0..S-2.

J of a sequence = mean over its frames of the IoU with the ground truth (an empty prediction on
an empty ground truth counts 1, DAVIS's convention); the headline is the mean over sequences.
Frames are resized by ``--resize`` (default 1: DAVIS's 854x480; 0.5: 427x240, 3x faster) before
both stages and the masks compared at that size (nearest-neighbour resized ground truth).

JSON keys: j_track_mean, j_flow_mean, one ``j_track_<seq>`` and ``j_flow_<seq>`` per sequence,
sequences, frames, seconds.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # OpenBLAS threads spin on shared cores

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

SHARED = Path(os.environ.get("CM3D_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
DEFAULT_DATA = SHARED / "davis2016"


def region_j(pred: np.ndarray, gt: np.ndarray) -> float:
    """DAVIS J: mean over frames of IoU (1 for an empty prediction on an empty ground truth)."""
    inter = (pred & gt).sum((1, 2))
    union = (pred | gt).sum((1, 2))
    return float(np.mean(np.where(union > 0, inter / np.maximum(union, 1), 1.0)))


def track_masks(images, flows, first_mask, refiner):
    """The refinement + tracking stage prompted by ``first_mask`` (frames 0..S-2)."""
    from cm3d import refine

    T = len(flows)
    H, W = first_mask.shape
    candidates = np.ones((T, H, W), bool)  # no geometry: every pixel may move
    empty = np.zeros((H, W), bool)
    # never re-detect; without geometry, pixels GrabCut adds by colour must not move like the background
    cfg = refine.TrackConfig(grow=False, new_region_frac=2.0, check_added=True)
    masks, _ = refine.refine_and_track(images, flows, candidates, lambda t: first_mask if t == 0 else empty,
                                       refiner, cfg=cfg)
    return masks


def main() -> None:
    import jax

    from cm3d import motion, refine
    from cm3d.data.davis import load_davis
    from cm3d.ops import flow as flow_ops
    from cm3d.outputs import write_json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(DEFAULT_DATA), help="folder of DAVIS-layout sequences")
    ap.add_argument("--sequences", default=None, help="comma-separated names (default: every folder in --data)")
    ap.add_argument("--resize", type=float, default=1.0, help="image scale (0.5: 427x240)")
    ap.add_argument("--max-frames", type=int, default=None, help="first N frames of each video")
    ap.add_argument("--quick", action="store_true", help="2 sequences, 6 frames at 1/8 size")
    ap.add_argument("--json", default=None, metavar="PATH")
    args = ap.parse_args()
    data = Path(args.data)
    if not data.is_dir():
        raise SystemExit(f"--data {data}: no such folder")
    names = args.sequences.split(",") if args.sequences else sorted(p.name for p in data.iterdir()
                                                                     if (p / "images").is_dir())
    resize, max_frames = args.resize, args.max_frames
    if args.quick:
        names, resize, max_frames = names[:2], 0.125, 6
    cfg = motion.MotionConfig()
    flow_cue = jax.jit(jax.vmap(lambda f: motion.flow_motion_cue(f, cfg)[0]))
    refiner = refine.GrabCutRefiner()
    t_start = time.perf_counter()
    figures, jt, jf, n_frames = {}, [], [], 0
    print(f"{len(names)} DAVIS sequences at {resize:g}x size"
          + (f", first {max_frames} frames" if max_frames else ""))
    head = f"{'sequence':16s} {'frames':>6s} {'size':>9s} {'fg %':>6s} {'J track':>8s} {'J flow':>7s} {'s':>6s}"
    print("\n" + head + "\n" + "-" * len(head))
    for name in names:
        t0 = time.perf_counter()
        images, gt = load_davis(data / name, resize, max_frames)
        S, H, W = gt.shape
        flows = flow_ops.sequence_flow(images)
        tracked = track_masks(images, flows, gt[0], refiner)
        j_track = region_j(tracked[1:], gt[1:S - 1])
        j_flow = region_j(np.asarray(flow_cue(flows), bool), gt[:S - 1])
        secs = time.perf_counter() - t0
        jt.append(j_track), jf.append(j_flow)
        n_frames += S
        figures[f"j_track_{name}"], figures[f"j_flow_{name}"] = j_track, j_flow
        print(f"{name:16s} {S:6d} {W:4d}x{H:<4d} {100 * gt.mean():6.1f} {j_track:8.3f} {j_flow:7.3f} {secs:6.1f}")
    print("-" * len(head))
    print(f"{'mean':16s} {n_frames:6d} {'':9s} {'':6s} {np.mean(jt):8.3f} {np.mean(jf):7.3f}")
    print("\nreference J (DAVIS 2016 val, semi-supervised): SAM2 ~0.9; classical 2016 propagation 0.6-0.7")
    figures |= {"j_track_mean": float(np.mean(jt)), "j_flow_mean": float(np.mean(jf)), "sequences": len(names),
                "frames": n_frames, "resize": resize, "seconds": time.perf_counter() - t_start}
    print(f"wall {figures['seconds']:.0f} s")
    if args.json:
        write_json(args.json, figures)


if __name__ == "__main__":
    main()
