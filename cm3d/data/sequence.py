"""A video with its per-frame priors (and optional ground truth), as host-side numpy arrays.
What loaders produce and ``prepare`` consumes. Poses cam_to_world 4x4; priors in the prior's own
frame and scale (VGGT: first camera at the origin), ground truth in metric world coordinates."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from cm3d.ops import camera


@dataclasses.dataclass(frozen=True)
class GroundTruth:
    """Ground truth of a sequence, metric world frame.

    cam_to_world: (S, 4, 4) float64; depth: (S, H, W) float32 camera z (0 where nothing was hit);
    dynamic_mask: (S, H, W) bool, pixels on moving objects; flow: (S-1, H, W, 2) float32, forward
    flow from frame t to t+1 (see :mod:`cm3d.ops.camera`), or None; intrinsic: (S, 3, 3) float64.
    """

    cam_to_world: np.ndarray
    depth: np.ndarray
    intrinsic: np.ndarray
    dynamic_mask: np.ndarray | None = None
    flow: np.ndarray | None = None

    def world_points(self, stride: int = 1) -> np.ndarray:
        """World points (S, H', W', 3) of every ``stride``-th pixel from ground-truth depth and poses."""
        S, H, W = self.depth.shape
        v, u = np.mgrid[0:H:stride, 0:W:stride].astype(np.float64)
        d = self.depth[:, ::stride, ::stride]
        h, w = d.shape[1:]
        uv = np.stack([u, v], -1).reshape(-1, 2)
        pts = camera.backproject(uv, d.reshape(S, -1), np.asarray(self.intrinsic), np.asarray(self.cam_to_world))
        return pts.reshape(S, h, w, 3)

    def static_points(self, stride: int = 1) -> np.ndarray:
        """Static world points (N, 3): pixels with depth that are not on moving objects."""
        pts = self.world_points(stride)
        keep = self.depth[:, ::stride, ::stride] > 0
        if self.dynamic_mask is not None:
            keep &= ~self.dynamic_mask[:, ::stride, ::stride]
        return pts[keep]


@dataclasses.dataclass(frozen=True)
class Sequence:
    """Images and foundation-model priors of one video.

    images: (S, H, W, 3) uint8 RGB; depth: (S, H, W) float32 prior depth (camera z, prior units);
    depth_conf: (S, H, W) float32 confidence (larger is better); intrinsic: (S, 3, 3) float64;
    cam_to_world: (S, 4, 4) float64 prior poses; timestamps: (S,) float64 seconds (or frame index);
    world_points: optional (S, H, W, 3) prior point map; gt: optional :class:`GroundTruth`;
    meta: free-form JSON-serialisable facts (scene id, visit, noise level, prior scale, ...).
    """

    images: np.ndarray
    depth: np.ndarray
    depth_conf: np.ndarray
    intrinsic: np.ndarray
    cam_to_world: np.ndarray
    timestamps: np.ndarray
    world_points: np.ndarray | None = None
    gt: GroundTruth | None = None
    meta: dict[str, Any] = dataclasses.field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(self.images.shape[0])

    @property
    def image_size(self) -> tuple[int, int]:
        """(H, W)."""
        return int(self.images.shape[1]), int(self.images.shape[2])

    def replace(self, **changes) -> "Sequence":
        return dataclasses.replace(self, **changes)

    def slice(self, start: int, stop: int) -> "Sequence":
        """Frames ``start:stop`` (ground-truth flow trimmed to the pairs inside)."""
        sl = slice(start, stop)
        gt = None
        if self.gt is not None:
            g = self.gt
            gt = GroundTruth(
                cam_to_world=g.cam_to_world[sl],
                depth=g.depth[sl],
                intrinsic=g.intrinsic[sl],
                dynamic_mask=None if g.dynamic_mask is None else g.dynamic_mask[sl],
                flow=None if g.flow is None else g.flow[start : max(start, stop - 1)],
            )
        return Sequence(
            images=self.images[sl],
            depth=self.depth[sl],
            depth_conf=self.depth_conf[sl],
            intrinsic=self.intrinsic[sl],
            cam_to_world=self.cam_to_world[sl],
            timestamps=self.timestamps[sl],
            world_points=None if self.world_points is None else self.world_points[sl],
            gt=gt,
            meta=dict(self.meta),
        )
