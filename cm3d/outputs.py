"""Writers for what a user looks at in ``--out DIR``: trajectories, masks, point clouds, JSON.

Every writer is atomic (:func:`cm3d.data.atomic.atomic_write`): an interrupted run never leaves a
half-written file in place of a good one.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from cm3d.data.atomic import atomic_write
from cm3d.data.tum import write_tum

__all__ = ["write_json", "write_masks", "write_ply", "write_tum"]


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
