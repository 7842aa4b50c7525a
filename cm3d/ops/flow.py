"""Optical flow between consecutive frames (host side, OpenCV).

Forward flow ``F[v, u] = (du, dv)`` sends pixel ``(u, v)`` of frame ``t`` to ``(u + du, v + dv)`` in
frame ``t + 1`` (float32 px), as :func:`cm3d.ops.camera.ego_flow` and OpenCV's ``calcOpticalFlow*``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

DIS_PRESETS = ("ultrafast", "fast", "medium")


@dataclasses.dataclass(frozen=True)
class FlowConfig:
    """method: "dis" (default), "farneback" or "precomputed"; dis_preset: ultrafast/fast/medium."""

    method: str = "dis"
    dis_preset: str = "medium"

    def __post_init__(self):
        if self.method not in ("dis", "farneback", "precomputed"):
            raise ValueError(f"FlowConfig.method: unknown {self.method!r} (dis, farneback, precomputed)")
        if self.dis_preset not in DIS_PRESETS:
            raise ValueError(f"FlowConfig.dis_preset: unknown {self.dis_preset!r} {DIS_PRESETS}")


def _gray(img: np.ndarray, name: str) -> np.ndarray:
    import cv2

    img = np.asarray(img)
    if img.ndim == 3 and img.shape[-1] == 3 and img.dtype == np.uint8:
        return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    if img.ndim == 2 and img.dtype == np.uint8:
        return img
    raise ValueError(f"{name}: expected a uint8 RGB (H, W, 3) or gray (H, W) image, got {img.dtype} {img.shape}")


def compute_flow(img0: np.ndarray, img1: np.ndarray, cfg: FlowConfig = FlowConfig()) -> np.ndarray:
    """Forward flow (H, W, 2) float32 from ``img0`` to ``img1`` (uint8 RGB or gray)."""
    import cv2

    g0, g1 = _gray(img0, "img0"), _gray(img1, "img1")
    if g0.shape != g1.shape:
        raise ValueError(f"img1: shape {g1.shape} differs from img0 {g0.shape}")
    if cfg.method == "dis":
        preset = getattr(cv2, f"DISOPTICAL_FLOW_PRESET_{cfg.dis_preset.upper()}")
        flow = cv2.DISOpticalFlow_create(preset).calc(g0, g1, None)
    elif cfg.method == "farneback":
        flow = cv2.calcOpticalFlowFarneback(g0, g1, None, 0.5, 4, 21, 5, 7, 1.5, 0)
    else:
        raise ValueError("FlowConfig.method='precomputed': pass the flow array to sequence_flow")
    return np.ascontiguousarray(flow, dtype=np.float32)


def sequence_flow(images: np.ndarray, cfg: FlowConfig = FlowConfig(), precomputed=None) -> np.ndarray:
    """Flow (S-1, H, W, 2) between consecutive frames of ``images`` (S, H, W, 3), or the checked
    ``precomputed`` array when ``cfg.method == "precomputed"``."""
    S, H, W = images.shape[:3]
    if cfg.method == "precomputed":
        if precomputed is None:
            raise ValueError("flow: method 'precomputed' needs the flow array")
        flow = np.asarray(precomputed, np.float32)
        if flow.shape != (S - 1, H, W, 2):
            raise ValueError(f"flow: expected shape {(S - 1, H, W, 2)}, got {flow.shape}")
        if not np.all(np.isfinite(flow)):
            raise ValueError(f"flow: {int(np.sum(~np.isfinite(flow)))} non-finite values")
        return flow
    if S < 2:
        return np.zeros((0, H, W, 2), np.float32)
    return np.stack([compute_flow(images[i], images[i + 1], cfg) for i in range(S - 1)])
