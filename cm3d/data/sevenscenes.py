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

7-Scenes' own K is the Kinect's *depth* camera's and its depth is not registered to the colour
frames. With ``colour=`` a :class:`ColourCamera` (:data:`KINECT_COLOUR`: the Kinect colour camera's
published K and baseline, measured on the shared redkitchen by ``experiments/sevenscenes_calibration.py``)
the sequence is the colour camera's: its K, the depth re-projected into it (:func:`register_depth`)
and the files' poses moved onto it.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np

from cm3d.data.resize import resize_frame
from cm3d.data.sequence import GroundTruth, Sequence
from cm3d.ops import camera

DEPTH_SCALE = 1000.0  # uint16 millimetres
INVALID_DEPTH = 65535
_FRAME = re.compile(r"^frame-(\d+)\.color\.(jpg|png)$")


@dataclasses.dataclass(frozen=True)
class ColourCamera:
    """A colour camera beside the depth camera: pinhole ``f`` (px, square pixels), centre (``cx``,
    ``cy``) at the folder's image size, and the rigid map from depth-camera to colour-camera
    coordinates, ``x_c = R x_d + t`` (``rotvec``: R as a rotation vector, rad; ``translation``: t, m)."""

    f: float
    cx: float
    cy: float
    rotvec: tuple[float, float, float] = (0.0, 0.0, 0.0)
    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def K(self) -> np.ndarray:
        return np.array([[self.f, 0.0, self.cx], [0.0, self.f, self.cy], [0.0, 0.0, 1.0]])

    def depth_to_colour(self) -> np.ndarray:
        """4x4 ``T_cd``: depth-camera coordinates -> colour-camera coordinates."""
        from scipy.spatial.transform import Rotation

        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(self.rotvec).as_matrix()
        T[:3, 3] = self.translation
        return T


#: The Kinect v1 colour camera of 7-Scenes: its published intrinsics (f = 525 px, centre (319.5, 239.5)
#: at 640x480) and the Kinect's 2.5 cm baseline along the depth camera's x axis (x_c = x_d - 2.5 cm: the
#: sign the data prefer). Measured by ``experiments/sevenscenes_calibration.py`` on the shared redkitchen
#: (SIFT matches of colour frames reprojected through the sensor depth and the files' poses; median over
#: 60 pairs of frames 460-938): 1.81 px, against 2.76 px with the folder's K for both cameras, 1.87 px
#: with the two cameras at one place, 1.92 px with the opposite sign, and 1.84 px for f, cx, cy fitted on
#: frames 100-398 at one place.
KINECT_COLOUR = ColourCamera(f=525.0, cx=319.5, cy=239.5, translation=(-0.025, 0.0, 0.0))


def _bilinear_depth(depth: np.ndarray, uv: np.ndarray, max_ratio: float = 1.05):
    """Depth at sub-pixel ``uv`` (N, 2): bilinear where all four neighbours hold depth within
    ``max_ratio`` of each other (else invalid: a hole or a depth edge). Returns (z (N,), valid (N,))."""
    H, W = depth.shape
    u0, v0 = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    inside = (u0 >= 0) & (v0 >= 0) & (u0 < W - 1) & (v0 < H - 1)
    u0c, v0c = np.clip(u0, 0, W - 2), np.clip(v0, 0, H - 2)
    q = np.stack([depth[v0c, u0c], depth[v0c, u0c + 1], depth[v0c + 1, u0c], depth[v0c + 1, u0c + 1]], 1)
    a, b = uv[:, 0] - u0c, uv[:, 1] - v0c
    z = (q[:, 0] * (1 - a) * (1 - b) + q[:, 1] * a * (1 - b) + q[:, 2] * (1 - a) * b + q[:, 3] * a * b)
    lo, hi = q.min(1), q.max(1)
    return z, inside & (lo > 0) & (hi <= max_ratio * lo)


def lift_colour_pixels(uv, depth, K_depth, cam: ColourCamera, iterations: int = 5):
    """Colour-camera points (N, 3) of colour pixels ``uv`` (N, 2), their depth read where the depth
    camera sees each colour ray (a fixed point over the two cameras' baseline; ``depth`` (H, W) the
    depth camera's, metres, 0 = none). Returns (points, valid (N,))."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    ray = camera.rays(uv, cam.K())
    T = cam.depth_to_colour()
    R, t = T[:3, :3], T[:3, 3]
    r_d, t_d = ray @ R, R.T @ t  # x_d = R^T (z ray - t) = z r_d - t_d
    z = np.full(len(uv), 2.0)
    valid = np.zeros(len(uv), bool)
    for _ in range(iterations):
        X = z[:, None] * r_d - t_d
        front = X[:, 2] > 1e-6
        pix = (X @ np.asarray(K_depth, np.float64).T)[:, :2] / np.where(front, X[:, 2], 1.0)[:, None]
        zd, valid = _bilinear_depth(depth, pix)
        valid &= front
        z = np.where(valid, (zd + t_d[2]) / r_d[:, 2], z)
    return z[:, None] * ray, valid


def register_depth(depth, K_depth, cam: ColourCamera, shape=None) -> np.ndarray:
    """The depth camera's ``depth`` (H, W) re-projected into the colour camera (``shape``, default
    ``depth.shape``): every measured pixel moved to the colour camera and splatted to its nearest
    pixel, the nearest surface kept where several land (a z-buffer); 0 where none lands."""
    depth = np.asarray(depth, np.float64)
    H, W = depth.shape if shape is None else shape
    v, u = np.nonzero(depth > 0)
    Y = camera.backproject(np.stack([u, v], 1).astype(np.float64), depth[v, u], np.asarray(K_depth, np.float64),
                           cam.depth_to_colour())  # depth camera -> colour camera coordinates
    Y = Y[Y[:, 2] > 1e-6]
    pu = np.rint(cam.f * Y[:, 0] / Y[:, 2] + cam.cx).astype(np.int64)
    pv = np.rint(cam.f * Y[:, 1] / Y[:, 2] + cam.cy).astype(np.int64)
    ok = (pu >= 0) & (pu < W) & (pv >= 0) & (pv < H)
    flat, zc = pv[ok] * W + pu[ok], Y[ok, 2]
    order = np.lexsort((zc, flat))  # by pixel, nearest first
    first = np.unique(flat[order], return_index=True)[1]
    out = np.zeros(H * W, np.float32)
    out[flat[order][first]] = zc[order][first]
    return out.reshape(H, W)


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
                     resize: float = 1.0, colour: ColourCamera | None = None) -> Sequence:
    """A 7-Scenes folder (module docstring) as a :class:`Sequence`: sensor depth and confidence
    (0 in holes), the files' poses as the prior (identity without pose files) and, with pose files,
    the ground truth; timestamps are the frame numbers; ``resize`` scales images, depth (nearest)
    and K (``0.5``: 640x480 -> 320x240). ``require_poses``: an error when any selected frame has
    no pose file (``--prior-noise`` needs them). ``colour``: the colour camera (e.g.
    :data:`KINECT_COLOUR`; None: the folder's K for both images, the depth as it is): its K, the depth
    registered into it (:func:`register_depth`) and the poses moved onto it (``T_wc = T_wd T_cd^-1``)."""
    import cv2

    folder = Path(folder)
    nums = frame_numbers(folder, frames)
    K_depth = read_intrinsics(folder)
    K = K_depth if colour is None else colour.K()
    T_dc = np.eye(4) if colour is None else np.linalg.inv(colour.depth_to_colour())
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
        if colour is not None:
            d = register_depth(d, K_depth, colour, img.shape[:2])
        img, d = resize_frame(img, d, resize)
        images.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
        depth.append(d)
        pose_path = folder / f"frame-{n:06d}.pose.txt"
        poses.append(read_pose(pose_path) @ T_dc if pose_path.exists() else np.eye(4))
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
            "prior": "sensor depth, poses of the files" if all(has_pose) else "sensor depth, identity poses",
            "colour_camera": None if colour is None else dataclasses.asdict(colour)}
    return Sequence(images=images, depth=depth, depth_conf=(depth > 0).astype(np.float32), intrinsic=Ks,
                    cam_to_world=poses, timestamps=np.array(nums, np.float64), gt=gt, meta=meta)
