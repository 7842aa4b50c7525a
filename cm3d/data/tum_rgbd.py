"""TUM RGB-D folders as sequences: sensor depth, Open3D RGB-D odometry as the pose prior.

A folder holds ``rgb.txt`` and ``depth.txt`` (``timestamp path``), the PNGs (depth uint16, metres =
value / 5000, 0 = invalid) and optionally ``groundtruth.txt``; frames are associated by nearest
timestamp. Intrinsics: ``K``, else ``intrinsics.txt`` (``fx fy cx cy``), else the freiburg1/2/3
calibration named in the folder name, else TUM's default. The prior chains Open3D's odometry
(failures reuse the previous motion, counted in ``meta["odometry_failures"]``); metric, scale 1.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cm3d.data.sequence import GroundTruth, Sequence
from cm3d.data.tum import read_tum

DEPTH_SCALE = 5000.0
CALIBRATIONS = {  # fx, fy, cx, cy of the TUM RGB-D cameras
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}
DEFAULT_CALIBRATION = (525.0, 525.0, 319.5, 239.5)


def read_file_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """``timestamp path`` lines of rgb.txt / depth.txt (``#`` comments allowed)."""
    ts, names = [], []
    for i, line in enumerate(Path(path).read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) < 2:
            raise ValueError(f"{path}:{i}: expected 'timestamp filename', got {line!r}")
        try:
            ts.append(float(parts[0]))
        except ValueError:
            raise ValueError(f"{path}:{i}: bad timestamp {parts[0]!r}") from None
        names.append(parts[1])
    if not ts:
        raise ValueError(f"{path}: no frames listed")
    return np.array(ts), names


def nearest(ts_query: np.ndarray, ts_ref: np.ndarray, max_diff: float) -> np.ndarray:
    """Index of the nearest reference stamp for each query stamp, -1 where none is within max_diff."""
    order = np.argsort(ts_ref)
    sref = ts_ref[order]
    j = np.clip(np.searchsorted(sref, ts_query), 1, len(sref) - 1) if len(sref) > 1 else np.zeros(len(ts_query), int)
    if len(sref) > 1:
        j = np.where(np.abs(sref[j - 1] - ts_query) <= np.abs(sref[j] - ts_query), j - 1, j)
    idx = order[j]
    return np.where(np.abs(ts_ref[idx] - ts_query) <= max_diff, idx, -1)


def intrinsics_for(folder: Path) -> np.ndarray:
    path = folder / "intrinsics.txt"
    if path.exists():
        vals = [float(v) for v in path.read_text().split()]
        if len(vals) != 4:
            raise ValueError(f"{path}: expected 'fx fy cx cy', got {len(vals)} numbers")
        fx, fy, cx, cy = vals
    else:
        fx, fy, cx, cy = next((c for k, c in CALIBRATIONS.items() if k in folder.resolve().name),
                              DEFAULT_CALIBRATION)
    if fx <= 0 or fy <= 0:
        raise ValueError(f"{folder}: intrinsics must have positive focal lengths, got fx={fx}, fy={fy}")
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])


def rgbd_odometry(images: np.ndarray, depth: np.ndarray, K: np.ndarray, depth_trunc: float = 4.0):
    """cam_to_world (S, 4, 4) chained from Open3D RGB-D odometry (first camera at the origin),
    and the number of failed pairs."""
    import open3d as o3d

    S, H, W = depth.shape
    intr = o3d.camera.PinholeCameraIntrinsic(W, H, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    option = o3d.pipelines.odometry.OdometryOption(depth_max=depth_trunc)
    jac = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()

    def rgbd(i):
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(images[i])),
            o3d.geometry.Image(np.ascontiguousarray(depth[i], dtype=np.float32)),
            depth_scale=1.0, depth_trunc=depth_trunc, convert_rgb_to_intensity=True)

    poses, rel, failures = [np.eye(4)], np.eye(4), 0
    prev = rgbd(0)
    for i in range(1, S):
        cur = rgbd(i)
        # source = frame i, target = frame i-1: trans maps camera-i points into camera i-1
        ok, trans, _ = o3d.pipelines.odometry.compute_rgbd_odometry(cur, prev, intr, rel, jac, option)
        if ok and np.all(np.isfinite(trans)):
            rel = np.asarray(trans)
        else:
            failures += 1
        poses.append(poses[-1] @ rel)
        prev = cur
    return np.array(poses), failures


def write_tum_rgbd(folder, seq: Sequence, depth_scale: float = DEPTH_SCALE) -> None:
    """Write ``seq`` as a TUM RGB-D folder: ``rgb/`` and ``depth/`` PNGs (depth uint16 =
    metres x ``depth_scale``, stamped 4 ms after its image, as a real sensor's are), ``rgb.txt``,
    ``depth.txt``, ``intrinsics.txt`` and, with ground truth, ``groundtruth.txt``. The depth written
    is the ground truth's when present (a depth sensor), else the prior's."""
    import cv2

    from cm3d.data.atomic import atomic_write
    from cm3d.data.tum import write_tum

    folder = Path(folder)
    depth = seq.gt.depth if seq.gt is not None and seq.gt.depth is not None else seq.depth
    if np.nanmax(depth) * depth_scale > np.iinfo(np.uint16).max:
        raise ValueError(f"depth: {np.nanmax(depth):.3g} m does not fit a uint16 PNG at scale {depth_scale}")
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(exist_ok=True)

    def png(path, img):
        ok, buf = cv2.imencode(".png", img)
        if not ok:
            raise ValueError(f"{path}: cannot encode as PNG")
        with atomic_write(path, "wb") as f:
            f.write(buf.tobytes())

    rgb_lines, depth_lines = ["# color images"], ["# depth maps"]
    for i, t in enumerate(np.asarray(seq.timestamps, float)):
        png(folder / f"rgb/{t:.6f}.png", cv2.cvtColor(np.ascontiguousarray(seq.images[i]), cv2.COLOR_RGB2BGR))
        png(folder / f"depth/{t + 0.004:.6f}.png",
            np.round(np.nan_to_num(depth[i]) * depth_scale).astype(np.uint16))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{t + 0.004:.6f} depth/{t + 0.004:.6f}.png")
    for name, lines in (("rgb.txt", rgb_lines), ("depth.txt", depth_lines)):
        with atomic_write(folder / name, "w") as f:
            f.write("\n".join(lines) + "\n")
    if seq.gt is not None:
        write_tum(folder / "groundtruth.txt", seq.timestamps, seq.gt.cam_to_world)
    K = np.asarray(seq.intrinsic[0])
    with atomic_write(folder / "intrinsics.txt", "w") as f:
        f.write(f"{K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]}\n")


def load_tum_rgbd(folder, K: np.ndarray | None = None, max_frames: int | None = None,
                  stride: int = 1, max_diff: float = 0.02) -> Sequence:
    """A TUM RGB-D folder as a :class:`Sequence` (metric priors; ground truth when available)."""
    import cv2

    folder = Path(folder)
    for name in ("rgb.txt", "depth.txt"):
        if not (folder / name).exists():
            raise ValueError(f"{folder}: not a TUM RGB-D folder ({name} missing)")
    ts_rgb, rgb_names = read_file_list(folder / "rgb.txt")
    ts_d, d_names = read_file_list(folder / "depth.txt")
    match = nearest(ts_rgb, ts_d, max_diff)
    keep = np.flatnonzero(match >= 0)[::stride][:max_frames]
    if len(keep) < 2:
        raise ValueError(f"{folder}: fewer than 2 RGB frames have a depth frame within {max_diff} s")
    images, depth = [], []
    for i in keep:
        rgb = cv2.imread(str(folder / rgb_names[i]), cv2.IMREAD_COLOR)
        d = cv2.imread(str(folder / d_names[match[i]]), cv2.IMREAD_UNCHANGED)
        if rgb is None:
            raise ValueError(f"{folder / rgb_names[i]}: cannot read image")
        if d is None or d.dtype != np.uint16:
            raise ValueError(f"{folder / d_names[match[i]]}: expected a uint16 depth PNG")
        images.append(cv2.cvtColor(rgb, cv2.COLOR_BGR2RGB))
        depth.append(d.astype(np.float32) / DEPTH_SCALE)
    images, depth = np.stack(images), np.stack(depth)
    K = intrinsics_for(folder) if K is None else np.asarray(K, float)
    S = len(keep)
    poses, failures = rgbd_odometry(images, depth, K)
    Ks = np.broadcast_to(K, (S, 3, 3)).copy()
    gt, meta = None, {"source": "tum_rgbd", "folder": str(folder), "odometry_failures": failures}
    if (folder / "groundtruth.txt").exists():
        ts_gt, c2w_gt = read_tum(folder / "groundtruth.txt")
        g = nearest(ts_rgb[keep], ts_gt, max_diff)
        if np.all(g >= 0):
            gt = GroundTruth(cam_to_world=c2w_gt[g], depth=depth.copy(), intrinsic=Ks.copy())
        else:
            meta["ground_truth"] = f"{int(np.sum(g < 0))} frames without a pose within {max_diff} s"
    return Sequence(images=images, depth=depth, depth_conf=(depth > 0).astype(np.float32),
                    intrinsic=Ks, cam_to_world=poses, timestamps=ts_rgb[keep], gt=gt, meta=meta)
