"""7-Scenes / tsdf-fusion style RGB-D folders as sequences.

A folder holds ``frame-XXXXXX.color.jpg`` (or ``.png``), ``frame-XXXXXX.depth.png`` (uint16
millimetres, 0 = no measurement, 65535 also invalid), ``frame-XXXXXX.pose.txt`` (4x4
camera-to-world, metres; optional) and ``camera-intrinsics.txt`` (3x3 K). Frame numbers are the
file names' own; ``frames="A:B:STRIDE"`` keeps the frames numbered ``A <= n < B`` (either end may
be left out) and then every ``STRIDE``-th of them.

The sequence's priors are the sensor's: metric depth with its holes (depth 0, confidence 0; 1
elsewhere) and the poses of the files (identity where there are none). With pose files the
ground truth is those poses and the sensor depth; VGGT-like priors come from
:func:`cm3d.data.priors.priors_for` (``cm3d run --prior-noise LEVEL``).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from cm3d.data.resize import resize_frame
from cm3d.data.sequence import GroundTruth, Sequence

DEPTH_SCALE = 1000.0  # uint16 millimetres
INVALID_DEPTH = 65535
_FRAME = re.compile(r"^frame-(\d+)\.color\.(jpg|png)$")


def is_sevenscenes_folder(folder) -> bool:
    """A folder holding at least one ``frame-XXXXXX.color.{jpg,png}``."""
    folder = Path(folder)
    return folder.is_dir() and any(_FRAME.match(p.name) for p in folder.iterdir())


def parse_frames(spec: str | None) -> tuple[int | None, int | None, int]:
    """``"A:B:STRIDE"`` (parts optional: ``"A:B"``, ``"::2"``) -> (start, stop, stride)."""
    if spec is None or spec == "":
        return None, None, 1
    parts = str(spec).split(":")
    if len(parts) > 3:
        raise ValueError(f"--frames {spec!r}: expected A:B:STRIDE")
    try:
        vals = [int(p) if p.strip() else None for p in parts] + [None] * (3 - len(parts))
    except ValueError:
        raise ValueError(f"--frames {spec!r}: expected integers A:B:STRIDE") from None
    start, stop, stride = vals
    stride = 1 if stride is None else stride
    if stride < 1:
        raise ValueError(f"--frames {spec!r}: STRIDE must be >= 1")
    if start is not None and stop is not None and stop <= start:
        raise ValueError(f"--frames {spec!r}: B must be larger than A")
    return start, stop, stride


def frame_numbers(folder, frames: str | None = None) -> list[int]:
    """The frame numbers of a folder's colour images (sorted), selected by ``frames``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder}: not a folder")
    nums = sorted(int(m.group(1)) for p in folder.iterdir() if (m := _FRAME.match(p.name)))
    if not nums:
        raise ValueError(f"{folder}: no frame-XXXXXX.color.jpg/png images (not a 7-Scenes folder)")
    start, stop, stride = parse_frames(frames)
    sel = [n for n in nums if (start is None or n >= start) and (stop is None or n < stop)][::stride]
    if not sel:
        raise ValueError(f"{folder}: --frames {frames} selects none of frames {nums[0]}..{nums[-1]}")
    return sel


def read_intrinsics(folder) -> np.ndarray:
    """``camera-intrinsics.txt``: a 3x3 K (or ``fx fy cx cy``)."""
    path = Path(folder) / "camera-intrinsics.txt"
    if not path.exists():
        raise ValueError(f"{Path(folder)}: camera-intrinsics.txt missing")
    try:
        vals = np.array(path.read_text().split(), float)
    except ValueError:
        raise ValueError(f"{path}: not a list of numbers") from None
    if vals.size == 9:
        K = vals.reshape(3, 3)
    elif vals.size == 4:
        K = np.array([[vals[0], 0, vals[2]], [0, vals[1], vals[3]], [0, 0, 1.0]])
    else:
        raise ValueError(f"{path}: expected a 3x3 matrix (9 numbers) or 'fx fy cx cy', got {vals.size} numbers")
    if not (np.isfinite(K).all() and K[0, 0] > 0 and K[1, 1] > 0 and abs(np.linalg.det(K)) > 1e-9):
        raise ValueError(f"{path}: not a valid pinhole K (fx={K[0, 0]}, fy={K[1, 1]})")
    return K


def read_pose(path) -> np.ndarray:
    """A ``frame-XXXXXX.pose.txt``: 4x4 camera-to-world (metres), rigid."""
    try:
        T = np.array(Path(path).read_text().split(), float)
    except ValueError:
        raise ValueError(f"{path}: not a list of numbers") from None
    if T.size != 16:
        raise ValueError(f"{path}: expected a 4x4 matrix, got {T.size} numbers")
    T = T.reshape(4, 4)
    R = T[:3, :3]
    if not np.isfinite(T).all() or np.abs(R.T @ R - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
        raise ValueError(f"{path}: not a rigid camera-to-world pose")
    return T


def read_depth(path) -> np.ndarray:
    """A uint16 millimetre depth PNG -> metres float32 (H, W), 0 where there is no measurement."""
    import cv2

    d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if d is None or d.dtype != np.uint16 or d.ndim != 2:
        raise ValueError(f"{path}: unreadable depth (expected a single-channel uint16 PNG, millimetres)")
    d = d.astype(np.float32)
    d[d >= INVALID_DEPTH] = 0.0
    return d / DEPTH_SCALE


def _color_path(folder: Path, n: int) -> Path:
    for ext in ("jpg", "png"):
        p = folder / f"frame-{n:06d}.color.{ext}"
        if p.exists():
            return p
    raise ValueError(f"{folder}: frame {n}: colour image missing")


def load_sevenscenes(folder, frames: str | None = None, require_poses: bool = False,
                     resize: float = 1.0) -> Sequence:
    """A 7-Scenes folder (module docstring) as a :class:`Sequence`: sensor depth and confidence
    (0 in holes), the files' poses as the prior (identity without pose files) and, with pose files,
    the ground truth; timestamps are the frame numbers; ``resize`` scales images, depth (nearest)
    and K (``0.5``: 640x480 -> 320x240). ``require_poses``: an error when any selected frame has
    no pose file (``--prior-noise`` needs them)."""
    import cv2

    folder = Path(folder)
    nums = frame_numbers(folder, frames)
    K = read_intrinsics(folder)
    has_pose = [(folder / f"frame-{n:06d}.pose.txt").exists() for n in nums]
    if require_poses and not all(has_pose):
        missing = nums[has_pose.index(False)]
        raise ValueError(f"{folder}: frame {missing}: frame-{missing:06d}.pose.txt missing (ground-truth poses "
                         "are needed for --prior-noise)")
    images, depth, poses = [], [], []
    for n in nums:
        p = _color_path(folder, n)
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            raise ValueError(f"{p}: cannot read image")
        dpath = folder / f"frame-{n:06d}.depth.png"
        if not dpath.exists():
            raise ValueError(f"{folder}: frame {n}: frame-{n:06d}.depth.png missing")
        d = read_depth(dpath)
        if d.shape != img.shape[:2]:
            raise ValueError(f"{dpath}: depth is {d.shape[1]}x{d.shape[0]} but the image is "
                             f"{img.shape[1]}x{img.shape[0]}")
        if not (d > 0).any():
            raise ValueError(f"{dpath}: frame {n} has no usable depth (every pixel is a hole)")
        img, d = resize_frame(img, d, resize)
        images.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
        depth.append(d)
        pose_path = folder / f"frame-{n:06d}.pose.txt"
        poses.append(read_pose(pose_path) if pose_path.exists() else np.eye(4))
    shapes = {im.shape for im in images}
    if len(shapes) != 1:
        raise ValueError(f"{folder}: images differ in size {sorted(shapes)}")
    if resize != 1.0:
        K = K.copy()
        K[:2] *= resize
        K[:2, 2] += 0.5 * resize - 0.5  # pixel centres at integers: c' = (c + 0.5) r - 0.5
    images, depth, poses = np.stack(images), np.stack(depth), np.array(poses)
    S = len(nums)
    Ks = np.broadcast_to(K, (S, 3, 3)).copy()
    gt = GroundTruth(cam_to_world=poses.copy(), depth=depth.copy(), intrinsic=Ks.copy()) if all(has_pose) else None
    meta = {"source": "sevenscenes", "folder": str(folder), "frames": [int(n) for n in nums],
            "prior": "sensor depth, poses of the files" if all(has_pose) else "sensor depth, identity poses"}
    return Sequence(images=images, depth=depth, depth_conf=(depth > 0).astype(np.float32), intrinsic=Ks,
                    cam_to_world=poses, timestamps=np.array(nums, np.float64), gt=gt, meta=meta)
