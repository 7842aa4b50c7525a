"""MPI-Sintel file formats: ``.flo`` flow, ``.dpt`` depth, ``.cam`` cameras; and KITTI flow PNGs.

Little-endian, row-major, after the float32 tag 202021.25 and (``.flo``, ``.dpt``) int32 width,
height: ``.flo`` H*W*2 float32 (|v| > 1e9 unknown), ``.dpt`` H*W float32, ``.cam`` 3x3 K and 3x4
world-to-camera, float64. KITTI PNG: 16-bit, ``u = (R - 2^15) / 64``, ``v`` from G, valid ``B > 0``.
"""

from __future__ import annotations

import os

import numpy as np

from cm3d.data.atomic import atomic_write

TAG = np.float32(202021.25)
UNKNOWN_FLOW = 1e9


def _open_tagged(path: str | os.PathLike, what: str) -> bytes:
    data = open(path, "rb").read()
    if len(data) < 4 or np.frombuffer(data[:4], "<f4")[0] != TAG:
        raise ValueError(f"{path}: not a Sintel {what} file (bad tag, expected 202021.25)")
    return data


def _grid(path, data: bytes, channels: int, what: str) -> np.ndarray:
    if len(data) < 12:
        raise ValueError(f"{path}: truncated {what} header")
    w, h = (int(x) for x in np.frombuffer(data[4:12], "<i4"))
    if w <= 0 or h <= 0 or w * h > 1 << 28:
        raise ValueError(f"{path}: implausible {what} size {w}x{h}")
    n = w * h * channels
    if len(data) != 12 + 4 * n:
        raise ValueError(f"{path}: expected {12 + 4 * n} bytes for {w}x{h}x{channels}, got {len(data)}")
    arr = np.frombuffer(data[12:], "<f4").reshape(h, w, channels)
    return arr if channels > 1 else arr[..., 0]


def read_flo(path) -> tuple[np.ndarray, np.ndarray]:
    """Flow (H, W, 2) float32 and validity (H, W) bool (unknown values become 0, invalid)."""
    flow = _grid(path, _open_tagged(path, ".flo"), 2, ".flo").astype(np.float32)
    valid = np.all(np.abs(flow) < UNKNOWN_FLOW, axis=-1) & np.all(np.isfinite(flow), axis=-1)
    return np.where(valid[..., None], flow, 0.0).astype(np.float32), valid


def write_flo(path, flow: np.ndarray) -> None:
    """Write flow (H, W, 2) as ``.flo`` (atomically)."""
    flow = np.asarray(flow, "<f4")
    if flow.ndim != 3 or flow.shape[-1] != 2:
        raise ValueError(f"flow: expected (H, W, 2), got {flow.shape}")
    with atomic_write(path) as f:
        f.write(TAG.tobytes() + np.array(flow.shape[1::-1], "<i4").tobytes() + flow.tobytes())


def read_dpt(path) -> np.ndarray:
    """Depth (H, W) float32 from a Sintel ``.dpt`` file."""
    return _grid(path, _open_tagged(path, ".dpt"), 1, ".dpt").astype(np.float32)


def write_dpt(path, depth: np.ndarray) -> None:
    """Write depth (H, W) as ``.dpt`` (atomically)."""
    depth = np.asarray(depth, "<f4")
    if depth.ndim != 2:
        raise ValueError(f"depth: expected (H, W), got {depth.shape}")
    with atomic_write(path) as f:
        f.write(TAG.tobytes() + np.array(depth.shape[::-1], "<i4").tobytes() + depth.tobytes())


def read_cam(path) -> tuple[np.ndarray, np.ndarray]:
    """Intrinsic K (3, 3) and world-to-camera extrinsic (3, 4), float64, from a ``.cam`` file."""
    data = _open_tagged(path, ".cam")
    if len(data) != 4 + 8 * (9 + 12):
        raise ValueError(f"{path}: expected {4 + 8 * 21} bytes for a .cam file, got {len(data)}")
    vals = np.frombuffer(data[4:], "<f8")
    return vals[:9].reshape(3, 3).copy(), vals[9:].reshape(3, 4).copy()


def write_cam(path, K: np.ndarray, extrinsic: np.ndarray) -> None:
    """Write K (3, 3) and a world-to-camera extrinsic (3, 4) as ``.cam`` (atomically)."""
    K, E = np.asarray(K, "<f8"), np.asarray(extrinsic, "<f8")[:3]
    if K.shape != (3, 3) or E.shape != (3, 4):
        raise ValueError(f"cam: expected K (3, 3) and extrinsic (3, 4), got {K.shape}, {E.shape}")
    with atomic_write(path) as f:
        f.write(TAG.tobytes() + K.tobytes() + E.tobytes())


def read_kitti_flow(path) -> tuple[np.ndarray, np.ndarray]:
    """KITTI 16-bit flow PNG -> flow (H, W, 2) float32 and validity (H, W) bool."""
    import cv2

    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.dtype != np.uint16 or raw.ndim != 3:
        raise ValueError(f"{path}: not a 16-bit 3-channel KITTI flow PNG")
    b, g, r = raw[..., 0], raw[..., 1].astype(np.float32), raw[..., 2].astype(np.float32)
    valid = b > 0
    flow = np.stack([(r - 2**15) / 64.0, (g - 2**15) / 64.0], -1)
    return np.where(valid[..., None], flow, 0.0).astype(np.float32), valid
