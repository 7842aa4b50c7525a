"""Dynamic masks per motion-cue stage on the seeded synthetic benchmark, against ground truth.

    .venv/bin/python experiments/motion_masks.py [--sequences 8 --frames 8 --moving 4 --level moderate]
                                                 [--quick] [--json PATH]

Each sequence is scene ``i``, visit ``--visit`` (1) of the synthetic world with ``--moving`` moving objects and
VGGT-like priors at ``--level`` noise. Per stage (flow GMM / geometry residual + Otsu / robust
keypoint-verified regions / refined + tracked) and for the MonST3R-style baseline (fixed residual
threshold) it prints IoU, precision and recall (pooled over the pixels of a sequence, then averaged
over sequences) on frames 0..S-2 (those with a forward flow), and each stage's own throughput in
frames per second (its share of the work: OpenCV DIS flow and SIFT matching included where the
stage needs them; JAX stages timed after compilation, vmapped over the frames of a sequence).
The masks are the pipeline step's cues (:func:`cm3d.motion.sequence_motion_cues` with the reverse
flows): every pair's forward-backward occlusion check and, for frames t >= 1, the previous frame as
a second partner (``MotionConfig.two_pairs``; before stop 53 this script judged each pair alone,
without the occlusion check). The geo and robust stages' fps time the pair (t, t+1) alone (the geo
stage's include the reverse DIS flows it needs).
Headline JSON keys: iou_flow, iou_geo, iou_robust, iou_refined, iou_monst3r (+ precision, recall,
fps per stage).
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from cm3d import motion, refine
from cm3d.data import synthetic
from cm3d.outputs import write_json
from cm3d.eval.metrics import mask_metrics
from cm3d.ops import flow as flow_ops
from cm3d.ops import keypoints

STAGES = ("flow", "geo", "robust", "refined", "monst3r")


def _vm(f):
    return jax.jit(jax.vmap(f, in_axes=(0, 0, 0, 0, None)), static_argnums=4)


def _flow_stage(a, b, flow, matches, cfg):
    return motion.flow_motion_cue(flow, cfg)[0]


def _geo_stage(a, b, flow, matches, cfg):
    return motion.geometry_motion_cue(a, b, flow, cfg)


def _robust_stage(a, b, geo, matches, cfg):
    # geo = (flow_mask, geo_mask, valid, rel): the robust stage's own work given the earlier cues
    flow_mask, geo_mask, valid, rel = geo
    cand, labels = motion.candidate_regions(flow_mask, geo_mask, valid, cfg)
    disp, ray, ok = motion.keypoint_displacements(a, b, matches, rel, cfg)
    dyn = motion.dynamic_keypoints(disp, ray, ok, cfg, motion.static_reference(labels, matches, ok, cfg))
    return motion.robust_motion_cue(labels, matches, dyn, ok, cfg)[0]


def _baseline_stage(a, b, flow, matches, cfg):
    return motion.baseline_motion_cue(a, b, flow, motion.relative_pose(a, b), cfg)


FLOW_J, GEO_J, ROBUST_J, BASE_J = map(_vm, (_flow_stage, _geo_stage, _robust_stage, _baseline_stage))


def _timed(f, *args):
    t = time.perf_counter()
    out = jax.block_until_ready(f(*args))
    return out, time.perf_counter() - t


def run_sequence(seq, cfg: motion.MotionConfig, refiner, track_cfg: refine.TrackConfig, warm: bool):
    """All stages on one sequence -> (masks per stage (T, H, W), seconds per stage, extra facts)."""
    S = seq.num_frames
    T = S - 1
    priors = motion.FramePrior.from_sequence(seq)
    a = jax.tree.map(lambda x: x[:-1], priors)
    b = jax.tree.map(lambda x: x[1:], priors)
    secs = {}
    t0 = time.perf_counter()
    flows = flow_ops.sequence_flow(seq.images)
    secs["dis"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    # the reverse flows (t+1 -> t): the occlusion check and the second partner, as in the pipeline's step
    flows_rev = flow_ops.sequence_flow(seq.images[::-1])[::-1]
    secs["dis_rev"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    matches = keypoints.sequence_matches(seq.images)
    secs["sift"] = time.perf_counter() - t0
    flows_j = jnp.asarray(flows)
    if warm:  # compile every stage once on this shape, outside the timings
        jax.block_until_ready(motion.sequence_motion_cues(priors, flows_j, matches, cfg, flows_rev))
        for f, x in ((FLOW_J, flows_j), (GEO_J, flows_j), (BASE_J, flows_j)):
            jax.block_until_ready(f(a, b, x, matches, cfg))
    flow_mask, secs["gmm"] = _timed(FLOW_J, a, b, flows_j, matches, cfg)
    geo, secs["geo"] = _timed(GEO_J, a, b, flows_j, matches, cfg)
    geo_in = (flow_mask, geo.mask, geo.valid, geo.rel_pose)
    if warm:
        jax.block_until_ready(ROBUST_J(a, b, geo_in, matches, cfg))
    robust, secs["robust"] = _timed(ROBUST_J, a, b, geo_in, matches, cfg)
    base_prior, secs["baseline"] = _timed(BASE_J, a, b, flows_j, matches, cfg)
    cues, secs["all_cues"] = _timed(motion.sequence_motion_cues, priors, flows_j, matches, cfg, flows_rev)

    cues_np = jax.tree.map(np.asarray, cues)
    t0 = time.perf_counter()
    refined, detected = refine.refine_and_track(
        seq.images, flows, cues_np.candidates, lambda t: cues_np.robust_mask[t], refiner,
        depth=seq.depth, residual=cues_np.residual, cfg=track_cfg)
    secs["refine"] = time.perf_counter() - t0
    masks = {"flow": cues_np.flow_mask, "geo": cues_np.geo_mask, "robust": cues_np.robust_mask,
             "refined": refined, "monst3r": cues_np.baseline_mask, "monst3r_prior_pose": np.asarray(base_prior)}
    facts = {"detections": int(detected.sum()), "frames": T, "geo_threshold": float(np.mean(cues_np.geo_threshold)),
             "kp_dynamic": float(cues_np.kp_dynamic.sum(1).mean())}
    return masks, secs, facts


def stage_fps(secs, T):
    """Frames per second of each stage's own work (host OpenCV work included where it is needed)."""
    per = {
        "flow": secs["dis"] + secs["gmm"],
        "geo": secs["dis_rev"] + secs["geo"],
        "robust": secs["sift"] + secs["robust"],
        "refined": secs["refine"],
        "monst3r": secs["baseline"],
    }
    return {k: T / max(v, 1e-9) for k, v in per.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", type=int, default=8)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--moving", type=int, default=4)
    ap.add_argument("--visit", type=int, default=1, help="visit of each scene (another visit: held-out check)")
    ap.add_argument("--level", default="moderate", choices=list(synthetic.NOISE_LEVELS))
    ap.add_argument("--refiner", default="grabcut", choices=["grabcut", "watershed"])
    ap.add_argument("--quick", action="store_true", help="2 short sequences at 96x128")
    ap.add_argument("--json", default=None, metavar="PATH")
    args = ap.parse_args()
    n_seq, frames = (2, 4) if args.quick else (args.sequences, args.frames)
    size = (96, 128) if args.quick else (384, 512)
    wcfg = synthetic.WorldConfig(height=size[0], width=size[1], num_moving=args.moving)
    cfg = motion.MotionConfig()
    refiner = refine.GrabCutRefiner() if args.refiner == "grabcut" else refine.WatershedRefiner()
    print(f"{n_seq} sequences (scenes 0..{n_seq - 1}, visit {args.visit}) x {frames} frames at {size[0]}x{size[1]}, "
          f"{args.moving} moving objects, "
          f"priors '{args.level}', refiner {args.refiner}")
    per_seq = {k: [] for k in (*STAGES, "monst3r_prior_pose")}
    secs_tot, T_tot, detections, dyn_frac = {}, 0, 0, []
    t_start = time.perf_counter()
    for i in range(n_seq):
        seq = synthetic.generate(scene_seed=i, visit=args.visit, num_frames=frames, level=args.level, cfg=wcfg)
        masks, secs, facts = run_sequence(seq, cfg, refiner, refine.TrackConfig(), warm=(i == 0))
        gt = seq.gt.dynamic_mask[: frames - 1]
        dyn_frac.append(gt.mean())
        row = []
        for k, m in masks.items():
            met = {q: float(v) for q, v in mask_metrics(m, gt).items()}
            per_seq[k].append(met)
            row.append(f"{k} {met['iou']:.3f}")
        for k, v in secs.items():
            secs_tot[k] = secs_tot.get(k, 0.0) + v
        T_tot += facts["frames"]
        detections += facts["detections"]
        print(f"  seq {i}: dynamic {100 * gt.mean():4.1f}%  thr {facts['geo_threshold']:.2f}px  "
              f"kp_dyn {facts['kp_dynamic']:.1f}  det {facts['detections']}/{facts['frames']}  IoU " + ", ".join(row))
    fps = stage_fps(secs_tot, T_tot)
    names = {"flow": "flow (GMM on DIS flow)", "geo": "geo (residual + Otsu)", "robust": "robust (keypoint-verified)",
             "refined": "refined + tracked", "monst3r": "MonST3R-style baseline",
             "monst3r_prior_pose": "  same, prior poses"}
    print(f"\nmean over {n_seq} sequences ({T_tot} frames, {100 * np.mean(dyn_frac):.1f}% dynamic pixels):\n")
    head = f"{'stage':30s} {'IoU':>6s} {'prec':>6s} {'recall':>6s} {'fps':>8s}"
    print(head)
    print("-" * len(head))
    figures = {}
    for k, rows in per_seq.items():
        mean = {q: float(np.mean([r[q] for r in rows])) for q in ("iou", "precision", "recall")}
        f = fps.get(k)
        print(f"{names[k]:30s} {mean['iou']:6.3f} {mean['precision']:6.3f} {mean['recall']:6.3f} "
              + (f"{f:8.1f}" if f is not None else f"{'':>8s}"))
        if k in STAGES:
            figures[f"iou_{k}"] = mean["iou"]
            figures[f"precision_{k}"] = mean["precision"]
            figures[f"recall_{k}"] = mean["recall"]
            figures[f"fps_{k}"] = f
        else:
            figures[f"iou_{k}"] = mean["iou"]
    all_fps = T_tot / max(secs_tot["dis"] + secs_tot["dis_rev"] + secs_tot["sift"] + secs_tot["all_cues"]
                          + secs_tot["refine"], 1e-9)
    print(f"\nwhole stage 1 (DIS + SIFT + motion_cues + refine/track): {all_fps:.1f} fps; "
          f"detection re-run on {detections}/{T_tot} frames; wall {time.perf_counter() - t_start:.0f} s")
    figures["fps_all"] = all_fps
    figures["iou_refined_minus_monst3r"] = figures["iou_refined"] - figures["iou_monst3r"]
    if args.json:
        write_json(args.json, figures)


if __name__ == "__main__":
    main()
