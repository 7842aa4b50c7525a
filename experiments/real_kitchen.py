"""Real 7-Scenes RGB-D frames (the redkitchen): pose refinement, static maps, false-dynamic pixels
and memory recall on real revisits, with VGGT-like priors made from the ground truth.

    .venv/bin/python experiments/real_kitchen.py [--data DIR] [--segments 160,640,...]
                                                 [--frames 30] [--resize 1.0] [--level moderate]
                                                 [--all-pairs] [--camera folder|colour] [--quick] [--json PATH]

The folder (default ``../shared/data/sevenscenes_redkitchen``, or under ``$CM3D_SHARED_DATA``) is read with
:func:`cm3d.data.sevenscenes.load_sevenscenes`. A *segment* is ``--frames`` (30) consecutive
listed frames, named by its first frame number (the folder holds every 2nd frame of 100-398 and
460-938: 13 segments of 30). Each segment gets its own VGGT-like prior
(:func:`cm3d.data.priors.make_priors`, level ``--level``, seed = its first frame number): first
camera at the origin, unknown scale, pose noise + drift, depth jitter, sensor holes kept (depth 0,
confidence 0). Images are resized by ``--resize`` (default 1: the sensor's 640x480, the back end
at 320x240; 0.5: 320x240, 3.5x faster). ``--camera colour`` reads the colour frames with the Kinect
colour camera (its K and place, the depth registered into it; docs/real_data.md) instead of the
folder's one K (the depth camera's).

Per segment (the pipeline alone on it, a fresh memory bank), against the ground truth:

* ATE / RPE (trans, rot) of the prior and of cm3d (Sim(3)-aligned, evo's protocol);
* static-map accuracy / completion (median, metres) of the prior map (prior depth at the prior
  poses) and of cm3d's (prior depth at the refined poses, its dynamic pixels removed;
  :func:`cm3d.outputs.static_map`) against the ground-truth cloud (sensor depth lifted with the true
  poses). The map goes to the world with its *known* scale (``prior_scale``) and a rotation fitted
  to all camera orientations (a centres-only Umeyama fit on a 30-frame path leaves ~10° free),
  then the mean camera-centre offset;
* the fraction of pixels called dynamic (the kitchen is static: every one is a false positive), by
  cm3d and by the MonST3R-style fixed-threshold baseline on the same inputs
  (:func:`cm3d.baselines.monst3r_masks`);
* wall time of the pipeline on the segment (flow, SIFT and back end; compilation excluded).

Memory: for each pair (A, B) of ``REVISITS`` (views of the same place, from the folder's README)
and ``DISTINCT`` (segments whose ground-truth overlap is 0 %), B runs with the bank A's run
left (one bank: A stored, B queries). A revisit counts as recalled when a window of B is accepted
with A's map; any accepted window of a distinct pair is a false recall. Relocalisation error of an
accepted window: its Sim(3) (B's prior frame -> A's) against the true one, rotation (°),
translation of B's first camera after undoing A's known scale (m), scale error (%); beside it the
*window's own cameras* placed in A's map (B's output poses of the window's frames moved by its Sim(3)
against their true poses in A's frame, :func:`camera_reloc_error`: B's drift between its first frame
and the window does not enter). True overlap: the fraction of B's ground-truth points within 5 cm of A's.

``--all-pairs`` (issue 22's bars) also runs every pair (A, B) of the run's segments with B at least one
segment after A: each *window* of B accepted with A's map counts, on the pairs with >= 30 % true
overlap (recall) and those under 10 % (false recalls); relocalisation medians over the recalled
windows.

JSON keys: ate_prior, ate_cm3d, rpe_trans_prior, rpe_trans_cm3d, map_acc_median_prior,
map_acc_median_cm3d, map_comp_median_prior, map_comp_median_cm3d, false_dynamic_frac,
false_dynamic_frac_monst3r, false_dynamic_frac_untuned (without the ``TUNED_ON`` segments) (means over
segments), revisits_recalled, revisits_total, false_recalls, distinct_total, reloc_rot_deg_median,
reloc_trans_m_median, reloc_scale_err_pct_median, camera_reloc_rot_deg_median, camera_reloc_trans_m_median
(null when nothing was recalled), segments,
seconds_per_segment; one ``overlap_A_B`` per pair; with ``--all-pairs``: window_recall_frac_overlap30,
windows_overlap30, pairs_overlap30, pairs_overlap30_recalled, false_recalls_overlap10, pairs_overlap10,
window_reloc_rot_deg_median, window_reloc_trans_m_median, window_reloc_scale_err_pct_median,
window_camera_reloc_rot_deg_median, window_camera_reloc_trans_m_median,
window_reloc_abs_scale_err_pct_median, merge_acc_ratio_median, merge_comp_ratio_median, merge_acc_worse10_pairs,
merge_comp_improved_pairs, merge_pairs. Map update (the revisit pairs B recalled): merge_acc_before, merge_acc_after,
merge_comp_before, merge_comp_after (means; A's stored map before / after B's windows merged into it, in the world
by A's own alignment, against the ground truth of both visits).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # OpenBLAS threads spin on shared cores

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from cm3d import baselines, memory, outputs, pipeline  # noqa: E402
from cm3d.data import priors, sevenscenes  # noqa: E402
from cm3d.eval import metrics  # noqa: E402
from cm3d.outputs import write_json  # noqa: E402

SHARED = Path(os.environ.get("CM3D_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
DEFAULT_DATA = SHARED / "sevenscenes_redkitchen"
# (first segment, revisiting segment), by first frame number: the folder's README lists 160-218 vs
# 640-698 and 280-338 vs 520-578 as views of the same part of the kitchen.
REVISITS = ((160, 640), (280, 520))
# pairs with 0 % ground-truth overlap (100-158 vs 820-878 is the README's; the others are the only
# other pairs of the 13 segments under 2 %, by :func:`overlap` on the ground truth alone: this small
# kitchen's segments mostly overlap, 5-98 %).
DISTINCT = ((100, 820), (100, 880), (640, 820))
QUICK_REVISITS, QUICK_DISTINCT = ((160, 640),), ((100, 820),)
# segments a motion-cue constant was chosen on (the appearance check's quantile, docs/motion.md):
# the false-dynamic share is also reported over the other segments
TUNED_ON = (160, 340)


def segment_starts(folder, frames: int) -> list[int]:
    """First frame numbers of the folder's segments of ``frames`` consecutive listed frames (a gap
    in the numbering, like 398 -> 460, starts a new run)."""
    nums = sevenscenes.frame_numbers(folder)
    steps = np.diff(nums)
    step = int(np.median(steps))
    starts, run = [], [nums[0]]
    for n, d in zip(nums[1:], steps):
        if d != step:
            starts += run[::frames][: len(run) // frames]
            run = [n]
        else:
            run.append(n)
    starts += run[::frames][: len(run) // frames]
    return starts


CAMERAS = {"colour": sevenscenes.KINECT_COLOUR, "folder": None}


def load_segment(folder, start: int, frames: int, resize: float, level: str, camera: str = "folder"):
    """Frames ``start, start + step, ...`` (``frames`` of them) with their VGGT-like prior; ``camera``:
    "folder" (the folder's one K for both images) or "colour" (the Kinect colour camera,
    :data:`cm3d.data.sevenscenes.KINECT_COLOUR`: its K, the depth registered into it, its poses)."""
    nums = sevenscenes.frame_numbers(folder)
    i = nums.index(start)
    if i + frames > len(nums):
        raise ValueError(f"segment {start}: fewer than {frames} frames left")
    seq = sevenscenes.load_sevenscenes(folder, f"{start}:{nums[i + frames - 1] + 1}", resize=resize,
                                       colour=CAMERAS[camera])
    if seq.num_frames != frames:
        raise ValueError(f"segment {start}: {seq.num_frames} frames, expected {frames}")
    return priors.priors_for(seq, level, seed=start)


def gt_cloud(seq, stride: int = 2, voxel: float = 0.01) -> np.ndarray:
    """Ground-truth cloud (N, 3): sensor depth lifted with the true poses, one point per ``voxel``."""
    pts = seq.gt.static_points(stride)
    keys = np.floor(pts / voxel).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return pts[np.sort(first)]


def map_to_world(points: np.ndarray, est_c2w: np.ndarray, gt_c2w: np.ndarray, scale: float) -> np.ndarray:
    """Map points of the prior frame (N, 3) in the world: the known ``scale``, the rotation that best
    maps every estimated camera orientation onto the true one (SVD of sum R_gt R_est^T), then the
    mean camera-centre offset."""
    M = np.einsum("sij,skj->ik", gt_c2w[:, :3, :3], est_c2w[:, :3, :3])
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    t = np.mean(gt_c2w[:, :3, 3] - (est_c2w[:, :3, 3] / scale) @ R.T, axis=0)
    return (points / scale) @ R.T + t


def map_errors(seq, poses, masks, cloud) -> dict:
    pts, _ = outputs.static_map(seq, poses, masks)
    world = map_to_world(pts, poses, seq.gt.cam_to_world, seq.meta["prior_scale"])
    m = metrics.reconstruction_metrics(world, cloud)
    return {"acc": m["accuracy_median"], "comp": m["completion_median"]}


def true_sim3(seq_a, seq_b) -> np.ndarray:
    """The Sim(3) (4, 4) from B's prior frame to A's: ``x_A = s_A T_A0^-1 T_B0 x_B / s_B``."""
    rel = np.linalg.inv(seq_a.gt.cam_to_world[0]) @ seq_b.gt.cam_to_world[0]
    sa, sb = seq_a.meta["prior_scale"], seq_b.meta["prior_scale"]
    out = np.eye(4)
    out[:3, :3] = rel[:3, :3] * (sa / sb)
    out[:3, 3] = rel[:3, 3] * sa
    return out


def rotation_deg(R: np.ndarray) -> float:
    """The angle (°) of a rotation matrix."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def reloc_error(est: np.ndarray, true: np.ndarray, scale_a: float) -> dict:
    """Rotation (°), translation of B's first camera (m, A's scale undone) and scale (%) errors."""
    se, st = np.cbrt(np.linalg.det(est[:3, :3])), np.cbrt(np.linalg.det(true[:3, :3]))
    return {"rot_deg": rotation_deg((est[:3, :3] / se).T @ (true[:3, :3] / st)),
            "trans_m": float(np.linalg.norm(est[:3, 3] - true[:3, 3]) / scale_a),
            "scale_err_pct": float(100 * (se / st - 1))}


def camera_reloc_error(est: np.ndarray, seq_a, seq_b, poses_b: np.ndarray, frames) -> dict:
    """Where the window's own cameras land in A's map: B's output poses ``poses_b`` (its prior frame) of the
    window's frames (first, last) moved by the window's Sim(3) ``est`` (B -> A) against their true poses in
    A's frame (``G_A0^-1 G_Bi``, A's scale undone); medians over the window's frames of the rotation (°) and
    camera-centre (m) errors. Unlike :func:`reloc_error` (B's *first* camera, which the window may not
    see), B's own drift between its first frame and the window does not enter; A's drift at the place
    (the map's geometry) does."""
    s = np.cbrt(np.linalg.det(est[:3, :3]))
    R, t = est[:3, :3] / s, est[:3, 3]
    sa = seq_a.meta["prior_scale"]
    g0 = np.linalg.inv(seq_a.gt.cam_to_world[0])
    rot, trans = [], []
    for i in range(frames[0], frames[1] + 1):
        true = g0 @ seq_b.gt.cam_to_world[i]
        r_est = R @ poses_b[i][:3, :3]
        c_est = s * R @ poses_b[i][:3, 3] + t
        rot.append(rotation_deg(r_est.T @ true[:3, :3]))
        trans.append(np.linalg.norm(c_est / sa - true[:3, 3]))
    return {"rot_deg": float(np.median(rot)), "trans_m": float(np.median(trans))}


def map_points(bank, map_ids) -> np.ndarray:
    """The stored points (N, 3) of the maps ``map_ids`` of ``bank`` (their frame: the sequence that created them)."""
    clouds = [memory.map_cloud(bank, m) for m in sorted(map_ids)]
    pts = [np.asarray(c.points, np.float64)[np.asarray(c.valid)] for c in clouds]
    return np.concatenate(pts) if pts else np.zeros((0, 3))


def merge_quality(seq_a, res_a, before: np.ndarray, after: np.ndarray, cloud: np.ndarray) -> dict:
    """A's stored map before and after a revisit merged into it (points in A's prior frame), in the world
    by A's own alignment (:func:`map_to_world` with A's refined poses), against the ground-truth ``cloud``
    of both visits: accuracy / completion medians (m) and the point counts."""
    out = {}
    for name, pts in (("before", before), ("after", after)):
        world = map_to_world(pts, res_a.poses, seq_a.gt.cam_to_world, seq_a.meta["prior_scale"])
        m = metrics.reconstruction_metrics(world, cloud)
        out |= {f"acc_{name}": m["accuracy_median"], f"comp_{name}": m["completion_median"],
                f"points_{name}": len(pts)}
    return out


def run_segment(seq, cfg, bank=None, baseline: bool = False):
    """(bank, result, seconds, MonST3R-style baseline masks (S, H, W) of the same inputs, or None)."""
    t0 = time.perf_counter()
    kept = {}
    bank, (res,) = pipeline.run([seq], cfg, bank, observe=lambda i, inputs, *_: kept.setdefault("inputs", inputs))
    secs = time.perf_counter() - t0
    base = None
    if baseline:
        base = (np.zeros(res.masks.shape, bool) if kept.get("inputs") is None
                else baselines.monst3r_masks(kept["inputs"], seq.num_frames, res.masks.shape[1:], cfg))
    return bank, res, secs, base


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(DEFAULT_DATA), help="a 7-Scenes folder (default: the shared redkitchen)")
    ap.add_argument("--segments", default=None,
                    help="comma-separated first frame numbers (default: every segment of the folder)")
    ap.add_argument("--frames", type=int, default=30, help="frames per segment")
    ap.add_argument("--resize", type=float, default=1.0, help="image scale (0.5: 320x240)")
    ap.add_argument("--level", default="moderate", choices=list(priors.NOISE_LEVELS))
    ap.add_argument("--quick", action="store_true", help="8-frame segments at 64x48, 1 revisit + 1 distinct pair")
    ap.add_argument("--all-pairs", action="store_true",
                    help="also every pair of segments at least one segment apart: window recall at >= 30 %% "
                         "overlap, false recalls under 10 %%")
    ap.add_argument("--camera", choices=sorted(CAMERAS), default="folder",
                    help="folder: the folder's K (the depth camera's) for both images (default); colour: the "
                         "Kinect colour camera's K and place, the depth registered into it (docs/real_data.md)")
    ap.add_argument("--json", default=None, metavar="PATH")
    args = ap.parse_args()
    folder = Path(args.data)
    frames, resize = (8, 0.1) if args.quick else (args.frames, args.resize)
    revisits, distinct = (QUICK_REVISITS, QUICK_DISTINCT) if args.quick else (REVISITS, DISTINCT)
    all_starts = segment_starts(folder, frames)
    pair_starts = sorted({s for p in (*revisits, *distinct) for s in p})
    if args.segments:
        starts = [int(s) for s in args.segments.split(",")]
    elif args.quick:
        starts = pair_starts
    else:
        starts = all_starts
    listed = sevenscenes.frame_numbers(folder)
    missing = [s for s in (*starts, *pair_starts) if s not in listed]
    if missing:
        raise SystemExit(f"--segments: {missing} are not frames of {folder} (segment starts: {all_starts})")
    t_start = time.perf_counter()
    seqs = {s: load_segment(folder, s, frames, resize, args.level, args.camera) for s in sorted({*starts, *pair_starts})}
    H, W = next(iter(seqs.values())).image_size
    cfg = pipeline.config_for(H, W)
    print(f"{folder.name}: {len(starts)} segments x {frames} frames at {W}x{H}, priors '{args.level}'; "
          f"{len(revisits)} revisit pairs, {len(distinct)} distinct pairs")
    # compile once outside the timings (the first segment's shapes are every segment's)
    run_segment(seqs[starts[0]], cfg)

    clouds = {s: gt_cloud(q) for s, q in seqs.items()}
    rows, banks, results = [], {}, {}
    head = (f"{'segment':>9s} {'ATE prior':>9s} {'ATE cm3d':>9s} {'RPE prior':>9s} {'RPE cm3d':>9s} "
            f"{'acc prior':>9s} {'acc cm3d':>9s} {'comp pr':>8s} {'comp cm3d':>9s} {'dynamic':>8s} {'MonST3R':>8s} "
            f"{'s':>6s}")
    print("\nper segment (ATE / RPE trans in m, Sim(3)-aligned; map accuracy / completion: medians, m)\n")
    print(head)
    print("-" * len(head))
    for s in sorted(seqs):
        seq = seqs[s]
        bank, res, secs, base = run_segment(seq, cfg, baseline=s in starts)
        banks[s], results[s] = bank, res
        if s not in starts:
            continue
        m = outputs.sequence_metrics(res)
        mp = map_errors(seq, res.prior, np.zeros_like(res.masks), clouds[s])
        mc = map_errors(seq, res.poses, res.masks, clouds[s])
        row = {"segment": s, "ate_prior": m["prior"]["ate"], "ate_cm3d": m["refined"]["ate"],
               "rpe_prior": m["prior"]["rpe_trans"], "rpe_cm3d": m["refined"]["rpe_trans"],
               "rpe_rot_prior": m["prior"]["rpe_rot"], "rpe_rot_cm3d": m["refined"]["rpe_rot"],
               "acc_prior": mp["acc"], "acc_cm3d": mc["acc"], "comp_prior": mp["comp"], "comp_cm3d": mc["comp"],
               "dynamic": float(res.masks.mean()), "dynamic_monst3r": float(base.mean()), "seconds": secs}
        rows.append(row)
        n1 = seq.meta["frames"][-1]
        print(f"{s:4d}-{n1:<4d} {row['ate_prior']:9.4f} {row['ate_cm3d']:9.4f} {row['rpe_prior']:9.4f} "
              f"{row['rpe_cm3d']:9.4f} {row['acc_prior']:9.4f} {row['acc_cm3d']:9.4f} {row['comp_prior']:8.4f} "
              f"{row['comp_cm3d']:9.4f} {100 * row['dynamic']:7.2f}% {100 * row['dynamic_monst3r']:7.2f}% {secs:6.1f}")
    mean = {k: float(np.mean([r[k] for r in rows])) for k in rows[0] if k != "segment"}
    print("-" * len(head))
    print(f"{'mean':>9s} {mean['ate_prior']:9.4f} {mean['ate_cm3d']:9.4f} {mean['rpe_prior']:9.4f} "
          f"{mean['rpe_cm3d']:9.4f} {mean['acc_prior']:9.4f} {mean['acc_cm3d']:9.4f} {mean['comp_prior']:8.4f} "
          f"{mean['comp_cm3d']:9.4f} {100 * mean['dynamic']:7.2f}% {100 * mean['dynamic_monst3r']:7.2f}% "
          f"{mean['seconds']:6.1f}")
    untuned = [r["dynamic"] for r in rows if r["segment"] not in TUNED_ON]
    untuned_frac = float(np.mean(untuned)) if untuned else None
    if untuned:
        print(f"dynamic pixels over the {len(untuned)} segments no constant was chosen on: {100 * untuned_frac:.2f} %")
    print(f"ATE {100 * (mean['ate_cm3d'] / mean['ate_prior'] - 1):+.1f} %, RPE rot {mean['rpe_rot_prior']:.3f}° -> "
          f"{mean['rpe_rot_cm3d']:.3f}°")

    figures = {"ate_prior": mean["ate_prior"], "ate_cm3d": mean["ate_cm3d"],
               "rpe_trans_prior": mean["rpe_prior"], "rpe_trans_cm3d": mean["rpe_cm3d"],
               "rpe_rot_prior": mean["rpe_rot_prior"], "rpe_rot_cm3d": mean["rpe_rot_cm3d"],
               "map_acc_median_prior": mean["acc_prior"], "map_acc_median_cm3d": mean["acc_cm3d"],
               "map_comp_median_prior": mean["comp_prior"], "map_comp_median_cm3d": mean["comp_cm3d"],
               "false_dynamic_frac": mean["dynamic"], "false_dynamic_frac_monst3r": mean["dynamic_monst3r"],
               "false_dynamic_frac_untuned": untuned_frac,
               "segments": len(rows), "frames_per_segment": frames,
               "seconds_per_segment": mean["seconds"]}

    if len(clouds) > 2:
        print("\nground-truth overlap (%): column B's points within 5 cm of row A's\n")
        print("      " + " ".join(f"{b:5d}" for b in sorted(clouds)))
        for a in sorted(clouds):
            print(f"{a:5d} " + " ".join(f"{100 * metrics.cloud_overlap(clouds[a], clouds[b]):5.0f}"
                                        for b in sorted(clouds)))

    print("\nmemory: B runs with the bank A's run left (reloc error of an accepted window vs the true Sim(3))\n")
    head = f"{'pair':>11s} {'kind':>8s} {'overlap':>7s} {'recalled':>8s} {'windows':>7s} {'top cand.':>9s} " \
           f"{'kp inl.':>7s} {'rot °':>6s} {'trans m':>7s} {'scale %':>7s}"
    print(head)
    print("-" * len(head))
    memo = {}

    def pair_run(a, b):
        """B's windows with the bank A's run left: (overlap, [(window, accepted with A's map)], best window)."""
        if (a, b) not in memo:
            maps_a = {w.map_id for w in results[a].windows if w.created_map}
            bank_b, res_b, *_ = run_segment(seqs[b], cfg, banks[a])
            wins = [(w, bool(w.accepted and w.recalled_map in maps_a)) for w in res_b.windows]
            best = max(res_b.windows, key=lambda w: max(w.keypoint_inliers or [0]))
            top = "A" if best.candidates and best.candidates[0] in maps_a else "-"
            merged = None
            if any(ok for _, ok in wins):  # A's map before and after B's recalled windows merged into it
                merged = merge_quality(seqs[a], results[a], map_points(banks[a], maps_a), map_points(bank_b, maps_a),
                                       np.concatenate([clouds[a], clouds[b]]))
            cams = [camera_reloc_error(np.asarray(w.transform, np.float64), seqs[a], seqs[b],
                                       np.asarray(res_b.poses, np.float64), w.frames) for w, ok in wins if ok]
            memo[(a, b)] = (metrics.cloud_overlap(clouds[a], clouds[b]), wins, best, top, merged, cams)
        return memo[(a, b)]

    def window_errors(a, b, wins):
        return [reloc_error(np.asarray(w.transform), true_sim3(seqs[a], seqs[b]), seqs[a].meta["prior_scale"])
                for w, ok in wins if ok]

    def show(a, b, kind):
        ov, wins, best, top, merged, cams = pair_run(a, b)
        errs = window_errors(a, b, wins)
        e = errs[0] if errs else {"rot_deg": float("nan"), "trans_m": float("nan"), "scale_err_pct": float("nan")}
        n_ok = sum(ok for _, ok in wins)
        print(f"{a:4d}/{b:<4d}  {kind:>8s} {100 * ov:6.1f}% {('yes' if n_ok else 'no'):>8s} {n_ok:3d}/{len(wins):<3d} "
              f"{top:>9s} {max(best.keypoint_inliers or [0]):7d} {e['rot_deg']:6.2f} {e['trans_m']:7.3f} "
              f"{e['scale_err_pct']:7.2f}")
        return ov, wins, errs, merged, cams

    recalled, false_recalls, reloc, cam_reloc, merges = 0, 0, [], [], {}
    for kind, pairs in (("revisit", revisits), ("distinct", distinct)):
        for a, b in pairs:
            ov, wins, errs, merged, cams = show(a, b, kind)
            figures[f"overlap_{a}_{b}"] = ov
            if kind == "revisit":
                recalled += any(ok for _, ok in wins)
                reloc += errs[:1]
                cam_reloc += cams[:1]
                if merged is not None:
                    merges[(a, b)] = merged
            else:
                false_recalls += any(ok for _, ok in wins)
    med = lambda rows, k: float(np.median([r[k] for r in rows])) if rows else None  # noqa: E731
    figures |= {"revisits_recalled": recalled, "revisits_total": len(revisits), "false_recalls": false_recalls,
                "distinct_total": len(distinct), "reloc_rot_deg_median": med(reloc, "rot_deg"),
                "reloc_trans_m_median": med(reloc, "trans_m"),
                "reloc_scale_err_pct_median": med(reloc, "scale_err_pct"),
                "camera_reloc_rot_deg_median": med(cam_reloc, "rot_deg"),
                "camera_reloc_trans_m_median": med(cam_reloc, "trans_m")}
    print(f"\nrevisits recalled {recalled}/{len(revisits)}, false recalls {false_recalls}/{len(distinct)}")
    if cam_reloc:
        print(f"relocalisation, median: B's first camera {med(reloc, 'rot_deg'):.2f}° / "
              f"{med(reloc, 'trans_m'):.3f} m; "
              f"the window's own cameras {med(cam_reloc, 'rot_deg'):.2f}° / {med(cam_reloc, 'trans_m'):.3f} m")
    if merges:
        print("\nmap update: A's stored map before / after B's recalled windows merged into it, against the "
              "ground truth of both visits (medians, m; A's alignment)\n")
        print(f"{'pair':>11s} {'acc before':>10s} {'acc after':>9s} {'comp before':>11s} {'comp after':>10s} "
              f"{'points':>13s}")
        for (a, b), q in merges.items():
            print(f"{a:4d}/{b:<4d}  {q['acc_before']:10.4f} {q['acc_after']:9.4f} {q['comp_before']:11.4f} "
                  f"{q['comp_after']:10.4f} {q['points_before']:6d}/{q['points_after']:<6d}")
        for k in ("acc_before", "acc_after", "comp_before", "comp_after"):
            figures[f"merge_{k}"] = float(np.mean([q[k] for q in merges.values()]))

    if args.all_pairs:
        # every pair (A, B) of the run's segments with B at least one segment after A (not B continuing A's
        # path): windows of pairs with >= 30 % true overlap should recall A's map, none of a pair under 10 %
        segs = sorted(s for s in starts if s in results)
        pos = {s: all_starts.index(s) for s in segs}
        pairs = [(a, b) for a in segs for b in segs if pos[b] >= pos[a] + 2]
        print(f"\nall {len(pairs)} pairs of segments at least one segment apart (windows: accepted with A's map / "
              f"windows of B)\n")
        print(head)
        print("-" * len(head))
        win_ok = win_n = 0
        errs_all, cams_all, false_pairs, low_pairs, high_pairs, high_recalled, merged_all = [], [], 0, 0, 0, 0, []
        for a, b in pairs:
            ov = metrics.cloud_overlap(clouds[a], clouds[b])
            kind = "revisit" if ov >= 0.3 else ("distinct" if ov < 0.1 else "partial")
            ov, wins, errs, merged, cams = show(a, b, kind)
            if kind == "revisit":
                high_pairs += 1
                high_recalled += any(ok for _, ok in wins)
                win_ok += sum(ok for _, ok in wins)
                win_n += len(wins)
                errs_all += errs
                cams_all += cams
                if merged is not None:
                    merged_all.append(merged)
            elif kind == "distinct":
                low_pairs += 1
                false_pairs += any(ok for _, ok in wins)
        figures |= {"window_recall_frac_overlap30": win_ok / win_n if win_n else None, "windows_overlap30": win_n,
                    "pairs_overlap30": high_pairs, "pairs_overlap30_recalled": high_recalled,
                    "false_recalls_overlap10": false_pairs, "pairs_overlap10": low_pairs,
                    "window_reloc_rot_deg_median": med(errs_all, "rot_deg"),
                    "window_reloc_trans_m_median": med(errs_all, "trans_m"),
                    "window_reloc_scale_err_pct_median": med(errs_all, "scale_err_pct"),
                    "window_camera_reloc_rot_deg_median": med(cams_all, "rot_deg"),
                    "window_camera_reloc_trans_m_median": med(cams_all, "trans_m")}
        if win_n:
            print(f"\nwindows of the {high_pairs} pairs with >= 30 % overlap recalled: {win_ok}/{win_n} "
                  f"({100 * win_ok / win_n:.1f} %; pairs {high_recalled}/{high_pairs}); false recalls on the "
                  f"{low_pairs} pairs under 10 %: {false_pairs}")
        if errs_all:
            print(f"relocalisation of the recalled windows, median: {med(errs_all, 'rot_deg'):.2f}° / "
                  f"{med(errs_all, 'trans_m'):.3f} m / {med(errs_all, 'scale_err_pct'):+.2f} % scale "
                  f"(|scale| {float(np.median([abs(r['scale_err_pct']) for r in errs_all])):.2f} %)")
            print(f"... the windows' own cameras in A's map (median over windows of each window's median): "
                  f"{med(cams_all, 'rot_deg'):.2f}° / {med(cams_all, 'trans_m'):.3f} m")
            figures["window_reloc_abs_scale_err_pct_median"] = float(np.median([abs(r["scale_err_pct"])
                                                                               for r in errs_all]))
        if merged_all:
            ratio = lambda k: np.array([q[f"{k}_after"] / q[f"{k}_before"] for q in merged_all])  # noqa: E731
            acc, comp = ratio("acc"), ratio("comp")
            print(f"map update of the {len(merged_all)} recalled pairs with >= 30 % overlap (after / before): accuracy "
                  f"median x{np.median(acc):.3f} (worse by > 10 % in {int(np.sum(acc > 1.1))}), completion median "
                  f"x{np.median(comp):.3f} (improved in {int(np.sum(comp < 1))})")
            figures |= {"merge_acc_ratio_median": float(np.median(acc)),
                        "merge_comp_ratio_median": float(np.median(comp)),
                        "merge_acc_worse10_pairs": int(np.sum(acc > 1.1)),
                        "merge_comp_improved_pairs": int(np.sum(comp < 1)), "merge_pairs": len(merged_all)}
    print(f"wall {time.perf_counter() - t_start:.0f} s")
    if args.json:
        write_json(args.json, figures)


if __name__ == "__main__":
    main()
