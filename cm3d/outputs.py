"""Writers for what a user looks at in ``--out DIR`` (trajectories, masks, point clouds, JSON) and the
one-line window report. Every writer is atomic: an interrupted run never leaves a half-written file."""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import jax
import numpy as np

from cm3d import programs
from cm3d.data.atomic import atomic_write, check_writable_folder
from cm3d.data.tum import write_tum
from cm3d.ops import camera, sim3

__all__ = ["write_json", "write_masks", "write_ply", "write_tum", "static_map", "sequence_metrics",
           "memory_points", "window_line", "headline", "commit_line", "check_output_folder", "write_results"]


def _plain(obj):
    """JSON-serialisable copy: numpy/jax arrays and scalars become lists and Python numbers."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if hasattr(obj, "tolist"):
        return obj.tolist()
    return obj


def write_json(path, obj, indent: int = 1) -> None:
    """Write ``obj`` (arrays allowed) as JSON, atomically."""
    with atomic_write(path, "w") as f:
        json.dump(_plain(obj), f, indent=indent)
        f.write("\n")


def write_masks(folder, masks: np.ndarray, start: int = 0) -> list[Path]:
    """Per-frame masks (S, H, W) bool as ``folder/NNNNNN.png`` (0 / 255, 8-bit)."""
    import cv2

    masks = np.asarray(masks)
    if masks.ndim != 3:
        raise ValueError(f"masks: expected (S, H, W), got {masks.shape}")
    folder = Path(folder)
    paths = []
    for i, m in enumerate(masks):
        ok, buf = cv2.imencode(".png", np.where(m, 255, 0).astype(np.uint8))
        if not ok:
            raise ValueError(f"masks: frame {i} could not be encoded as PNG")
        path = folder / f"{start + i:06d}.png"
        with atomic_write(path) as f:
            f.write(buf.tobytes())
        paths.append(path)
    return paths


def write_ply(path, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Binary little-endian PLY of points (N, 3) with optional uint8 colours (N, 3)."""
    pts = np.asarray(points, np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points: expected (N, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError(f"points: {int(np.sum(~np.isfinite(pts)))} non-finite values")
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(pts)}",
              "property float x", "property float y", "property float z"]
    if colors is not None:
        cols = np.asarray(colors)
        if cols.shape != pts.shape:
            raise ValueError(f"colors: expected {pts.shape}, got {cols.shape}")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    rec = np.empty(len(pts), dtype=fields)
    rec["x"], rec["y"], rec["z"] = pts.T
    if colors is not None:
        rec["red"], rec["green"], rec["blue"] = np.clip(cols, 0, 255).astype(np.uint8).T
    with atomic_write(path) as f:
        f.write(("\n".join(header) + "\nend_header\n").encode("ascii"))
        f.write(rec.tobytes())


def static_map(seq, poses: np.ndarray, masks: np.ndarray, stride: int = 4, voxel_ratio: float = 200.0,
               conf_quantile: float = 0.3):
    """Static point cloud of a sequence: every ``stride``-th pixel that is static (``~masks``), has
    positive depth and confidence above the sequence's ``conf_quantile``, lifted with the prior depth
    and the refined ``poses`` (S, 4, 4), averaged per voxel (extent / ``voxel_ratio``).
    Returns (points (N, 3) float32, colours (N, 3) uint8)."""
    d = np.asarray(seq.depth)[:, ::stride, ::stride].astype(np.float64)
    c = np.asarray(seq.depth_conf)[:, ::stride, ::stride]
    ok = (d > 0) & np.isfinite(d) & ~np.asarray(masks)[:, ::stride, ::stride]
    if not ok.any():
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
    ok &= c >= np.quantile(c[ok], conf_quantile)
    S, h, w = d.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64) * stride
    uv = np.stack([u, v], -1).reshape(-1, 2)
    pw = camera.backproject(uv, d.reshape(S, -1), np.asarray(seq.intrinsic, np.float64),
                            np.asarray(poses, np.float64)).reshape(S, h, w, 3)
    pts, cols = pw[ok], np.asarray(seq.images)[:, ::stride, ::stride][ok].astype(np.float64)
    extent = float(np.max(np.ptp(pts, axis=0))) if len(pts) > 1 else 1.0
    vs = max(extent / voxel_ratio, 1e-9)
    keys = np.floor(pts / vs).astype(np.int64)
    keys -= keys.min(0)
    span = keys.max(0) + 1
    if np.prod(span.astype(np.float64)) < 2.0**62:  # one int64 per voxel in the rows' lexicographic order: a
        keys = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]  # 1D unique (1.9 -> 0.6 s, 120 frames)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    mean = lambda x: np.stack([np.bincount(inv, x[:, k]) for k in range(3)], -1) / counts[:, None]  # noqa: E731
    return mean(pts).astype(np.float32), np.clip(np.round(mean(cols)), 0, 255).astype(np.uint8)


def _trajectory_metrics(ts, gt, est) -> dict:
    """ATE (Sim3, SE3), RPE, the alignment-free rotation error (deg), the ground truth's extent and
    whether the Sim(3) ATE is defined (:func:`cm3d.eval.metrics.ate_is_defined`)."""
    from cm3d.eval import metrics

    return metrics.evaluate_trajectories(ts, gt, ts, est)


def _depth_metrics_jit(pred, gt):
    """Prior depth against the ground truth on pixels with both (one stored program per shape)."""
    from cm3d.eval import metrics

    return metrics.depth_metrics(pred, gt, (gt > 0) & (pred > 0))


def _mask_metrics_jit(pred, gt):
    from cm3d.eval import metrics

    return metrics.mask_metrics(pred, gt)


def _align_jit(est, gt):
    from cm3d.eval import metrics

    return metrics.align_trajectory(est, gt)


_depth_metrics_jit, _mask_metrics_jit, _align_jit = (jax.jit(f) for f in (_depth_metrics_jit, _mask_metrics_jit,
                                                                           _align_jit))


def sequence_metrics(result) -> dict | None:
    """Metrics of a :class:`cm3d.pipeline.SequenceResult` against its ground truth (None without):
    ATE (Sim3, SE3), RPE and rotation error of the prior and the refined trajectory, whether ATE is
    defined, prior depth Abs Rel / δ<1.25 (pixels with ground truth and a prediction), mask IoU, and
    the run's warnings and whether its refinement was kept; with the windows' chain and the global
    pose graph (:mod:`cm3d.pipeline.global_graph`), the chained trajectory's figures (``chained``)
    and the graph's facts (``global_graph``: whether it ran and was kept, the consistency test)."""
    from cm3d.eval import metrics

    seq = result.sequence
    gt = seq.gt
    if gt is None:
        return None
    ts = seq.timestamps
    out = {"frames": int(seq.num_frames),
           "prior": _trajectory_metrics(ts, gt.cam_to_world, result.prior),
           "refined": _trajectory_metrics(ts, gt.cam_to_world, result.poses)}
    chained = getattr(result, "chained", None)
    if chained is not None:  # the windows chained anchor to anchor, before the global graph (issue 26)
        out["chained"] = _trajectory_metrics(ts, gt.cam_to_world, chained)
    a, b = out["prior"]["ate"], out["refined"]["ate"]
    out["ate_defined"] = out["prior"]["ate_defined"] and out["refined"]["ate_defined"]
    out["ate_reduction_pct"] = 100.0 * (a - b) / a if a > 0 else None
    pred = np.asarray(seq.depth)
    dm = programs.call("depth_metrics", _depth_metrics_jit, {}, pred, np.asarray(gt.depth))
    out["depth_prior"] = {k: float(v) for k, v in dm.items()}
    if gt.dynamic_mask is not None:
        mm = programs.call("mask_metrics", _mask_metrics_jit, {}, np.asarray(result.masks, bool),
                           np.asarray(gt.dynamic_mask))
        out["mask"] = {k: float(v) for k, v in mm.items()}
    g = getattr(result, "global_graph", None)
    if g is not None:
        out["global_graph"] = {k: v for k, v in g.items() if isinstance(v, (bool, int, float, str, list))}
    report = getattr(result, "report", None)
    if report is not None:
        out["refinement_kept"] = report.refinement_kept
        out["warnings"] = list(report.warnings)
    return out


def headline(m: dict) -> str:
    """The one-line summary of :func:`sequence_metrics`: never a percentage of a zero or of an
    undefined ATE; the rotation error beside it."""
    p, r = m["prior"], m["refined"]
    rot = f"rotation {p['rot_rmse']:.2f} -> {r['rot_rmse']:.2f} deg"
    if not m["ate_defined"]:
        ate = (f"ATE undefined (the camera's extent {p['extent']:.5f} is below its noise: Sim(3) ATE prior "
               f"{p['ate']:.5f}, refined {r['ate']:.5f}); ATE SE3 {p['ate_se3']:.5f} -> {r['ate_se3']:.5f}")
    else:
        pct = "" if m["ate_reduction_pct"] is None else f" ({-m['ate_reduction_pct']:+.1f} %)"
        ate = f"ATE prior {p['ate']:.5f} -> refined {r['ate']:.5f}{pct}"
    iou = m.get("mask", {}).get("iou", float("nan"))
    return f"{ate}, {rot}, RPE trans {p['rpe_trans']:.5f} -> {r['rpe_trans']:.5f}, mask IoU {iou:.3f}"


def commit_line(commit) -> str:
    """One line on a :class:`cm3d.memory.CommitReport`: the bank, its maps, where moved maps went."""
    line = f"memory bank {commit.path} ({commit.num_maps} maps)"
    if not commit.maps:
        line += ": nothing stored from this run"
    moved = [w for w in commit.maps if w.action in ("appended", "not stored")]
    if commit.bank_changed:
        line += "; another process wrote it during this run" + (
            ": " + ", ".join(f"this run's map {w.run_map} " + (f"stored as map {w.bank_map}" if w.bank_map >= 0
                                                               else "not stored (bank full)") for w in moved)
            if moved else ", merged without conflict")
    if commit.upgraded_from is not None:
        line += f"; rewritten from format version {commit.upgraded_from}"
    return line


def check_output_folder(out_dir) -> Path:
    """Fail early (``ValueError``, one line) when ``out_dir`` cannot hold the outputs; creates it."""
    return check_writable_folder(out_dir, "--out")


def memory_points(bank, result):
    """Points of the map this sequence was last recalled into / wrote, in the sequence's frame, and
    whether that map was *recalled* (it existed before this sequence) -> (points, colours, recalled)."""
    wins = [w for w in result.windows if w.map_id >= 0]
    if bank is None or not wins:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), False
    acc = [w for w in result.windows if w.accepted]
    w = acc[-1] if acc else wins[-1]
    m = w.recalled_map if acc else w.map_id
    T = w.transform if acc else np.eye(4)
    ok = np.asarray(bank.point_valid)[m]  # NumPy views of the bank: no JAX dispatch on the host
    pts = sim3.apply(sim3.inverse(np.asarray(T, np.float64)), np.asarray(bank.points)[m][ok].astype(np.float64))
    created = {x.map_id for x in result.windows if x.created_map}
    return pts.astype(np.float32), np.asarray(bank.colors)[m][ok], bool(acc) and m not in created


def window_line(w) -> str:
    """One line per :class:`cm3d.pipeline.WindowRecord`: frames, memory decision, refinement."""
    a, b = w.frames
    if not w.memory:
        mem = "memory off"
    elif w.accepted:
        mem = (f"recalled map {w.recalled_map} ({w.keypoint_inliers[0] if w.keypoint_inliers else 0} keypoint"
               f" / {w.inlier_count} ICP inliers, RMSE {w.rmse:.4f}, scale {w.scale:.3f})")
    elif w.created_map:
        mem = f"new map {w.map_id}" + (f" (candidates {list(w.candidates)} rejected)" if w.candidates else "")
    elif w.map_id >= 0:
        mem = f"merged into map {w.map_id} (this visit's map)"
    else:
        mem = "not stored (bank full)"
    ref = "refined" if w.refined else "kept prior (gate)"
    chunk = "" if w.chunk is None else f"chunk {w.chunk}: "
    return (f"{chunk}frames {a:4d}-{b:4d}: {mem}; {ref}, {w.landmarks} landmarks "
            f"({w.memory_landmarks} from memory), {w.observations} observations")


def _trajectory_pictures(out: Path, result, overlay_every: int) -> None:
    """Mask overlays and the trajectories' picture of :func:`write_results`."""
    from cm3d.eval import plots

    seq = result.sequence
    plots.save_mask_overlays(out / "overlays", seq.images, result.masks, every=overlay_every)
    trajs = {"prior": result.prior, "refined": result.poses}
    if seq.gt is not None:  # aligned in float32: a picture
        gt_c2w = np.asarray(seq.gt.cam_to_world, np.float32)
        trajs = {k: np.asarray(programs.call("align_trajectory", _align_jit, {}, np.asarray(v, np.float32),
                                             gt_c2w)) for k, v in trajs.items()}
        trajs["ground truth"] = seq.gt.cam_to_world
    plots.plot_trajectories(out / "trajectory.png", trajs, title="prior vs refined" +
                            (" vs ground truth (Sim3-aligned)" if seq.gt is not None else ""))


def _map_picture(out: Path, result, bank, pts: np.ndarray, cols: np.ndarray) -> None:
    """The top-down picture of the static map (and the recalled memory) of :func:`write_results`."""
    from cm3d.eval import plots

    mpts, mcols, recalled = memory_points(bank, result)
    allp = np.concatenate([pts, mpts]) if len(mpts) else pts
    if len(allp):
        allc = np.concatenate([cols, mcols]) if len(mpts) else cols
        flag = np.concatenate([np.zeros(len(pts), bool), np.full(len(mpts), recalled)])
        plots.plot_topdown_map(out / "topdown_map.png", allp, allc, from_memory=flag, cameras=result.poses,
                               title="static map" + (" (recalled memory brighter)" if recalled else ""))


def write_results(out_dir, result, bank=None, overlay_every: int = 5, pictures: bool = True,
                  commit=None) -> dict:
    """Everything a user looks at for one sequence, in ``out_dir``: trajectory.txt (refined, TUM),
    trajectory_prior.txt, masks/NNNNNN.png, static_map.ply, recall.json (windows, the run's checks
    and, with ``commit`` (:class:`cm3d.memory.CommitReport`), where its maps went in the bank file),
    metrics.json (with ground truth) and pictures (mask overlays, trajectories, top-down map; ``bank``:
    the run's own bank, whose map ids the windows name). Returns the metrics (or {})."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    seq = result.sequence
    # the pictures (matplotlib, one thread at a time) in a worker thread beside the files
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="cm3d-pictures") if pictures else None
    try:
        if pool is not None:
            jobs = [pool.submit(_trajectory_pictures, out, result, overlay_every)]
        write_tum(out / "trajectory.txt", seq.timestamps, result.poses)
        write_tum(out / "trajectory_prior.txt", seq.timestamps, result.prior)
        write_masks(out / "masks", result.masks)
        pts, cols = static_map(seq, result.poses, result.masks)
        if pool is not None:
            jobs.append(pool.submit(_map_picture, out, result, bank, pts, cols))
        write_ply(out / "static_map.ply", pts, cols)
        recall = {"windows": [w.to_json() for w in result.windows]}
        report = getattr(result, "report", None)
        if report is not None:
            recall["run"] = report.to_json()
        if commit is not None:
            recall["memory"] = commit.to_json()
        write_json(out / "recall.json", recall)
        m = sequence_metrics(result)
        if m is not None:
            write_json(out / "metrics.json", m)
        if pool is not None:
            for job in jobs:
                job.result()
    finally:
        if pool is not None:
            pool.shutdown(wait=True)
    return m or {}
