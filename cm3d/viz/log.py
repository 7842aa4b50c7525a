"""Logging primitives: one rerun archetype per function, host NumPy in, nothing returned.

Entity layout of a cm3d recording (timelines ``frame``, a global frame counter, and ``visit``):
``world`` (the visit's refined frame, OpenCV axes) holds ``camera`` (pinhole + refined pose, with
``image`` and ``image/dynamic``), ``trajectory/{prior,refined,ground_truth}``, ``map/new``,
``memory/recalled``, ``landmarks``; ``frame`` (a 2D view at the back end's resolution) holds the
input image, ``depth``, ``confidence`` and ``cues/...``; ``plots/...`` scalars; ``log/...`` text.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from cm3d.viz import require_rerun

#: class ids of the segmentation layers (0 transparent)
STATIC, DYNAMIC = 0, 1


def open_recording(path, application_id: str = "cm3d"):
    """A rerun recording stream writing ``path`` (through a temporary file beside it, renamed by
    :func:`close_recording`: an interrupted run never leaves a half-written ``.rrd``), with the
    default layout (:func:`blueprint`) and the segmentation classes."""
    rr = require_rerun()
    path = Path(path)
    tmp = path.with_name(f".{path.name}.recording.tmp")
    rec = rr.RecordingStream(application_id)
    rec.save(tmp, default_blueprint=blueprint())
    rec.log("/", rr.ViewCoordinates.RIGHT_HAND_Y_DOWN, static=True)
    ctx = rr.AnnotationContext([(STATIC, "static", (0, 0, 0, 0)), (DYNAMIC, "dynamic", (255, 40, 40, 150))])
    for root in ("world/camera/image", "frame"):
        rec.log(root, ctx, static=True)
    rec.log("world", rr.ViewCoordinates.RDF, static=True)
    return rec, (tmp, path)


def close_recording(rec, paths) -> Path:
    """Flush the stream and move the finished file into place; returns its path."""
    tmp, path = paths
    rec.flush()
    rec.disconnect()
    os.replace(tmp, path)
    return path


def blueprint():
    """The default viewer layout: the 3D world beside the camera image, the cues, plots and logs."""
    import rerun.blueprint as rrb

    two_d = lambda name, *paths: rrb.Spatial2DView(origin="frame", name=name, contents=list(paths))  # noqa: E731
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="world (memory brighter)"),
            rrb.Vertical(rrb.Spatial2DView(origin="world/camera/image", name="camera + dynamic mask"),
                         rrb.Tabs(two_d("cues", "+ /frame/**", "- /frame/depth", "- /frame/confidence",
                                        "- /frame/cues/residual"),
                                  two_d("residual flow", "/frame/cues/residual"),
                                  two_d("prior depth", "/frame/depth"), two_d("confidence", "/frame/confidence")),
                         rrb.Horizontal(rrb.TimeSeriesView(origin="plots/ate_so_far", name="ATE so far"),
                                        rrb.TimeSeriesView(origin="plots", name="LM cost, memory landmarks",
                                                           contents=["/plots/lm_cost", "/plots/memory_landmarks"])),
                         rrb.TextLogView(origin="log", name="recall decisions")),
            column_shares=[3, 2]),
        rrb.TimePanel(timeline="frame", play_state="following"),  # opens on the last frame
        collapse_panels=True)


def set_time(rec, frame: int, visit: int) -> None:
    rec.set_time("frame", sequence=int(frame))
    rec.set_time("visit", sequence=int(visit))


def jpeg(rec, entity: str, image: np.ndarray, quality: int = 85) -> None:
    """An RGB (H, W, 3) or grey (H, W) uint8 image, JPEG-compressed."""
    rr = require_rerun()
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError(f"{entity}: image could not be encoded as JPEG")
    rec.log(entity, rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg"))


def heat(rec, entity: str, values: np.ndarray, vmax: float, quality: int = 85) -> None:
    """A scalar field (H, W) in [0, vmax] as a turbo-coloured JPEG."""
    v = np.clip(np.nan_to_num(np.asarray(values, np.float64)) / max(vmax, 1e-12), 0.0, 1.0)
    bgr = cv2.applyColorMap(np.round(255 * v).astype(np.uint8), cv2.COLORMAP_TURBO)
    jpeg(rec, entity, bgr[..., ::-1], quality)


def depth(rec, entity: str, depth_map: np.ndarray) -> None:
    """A depth map (H, W) in the prior's units as a 16-bit :class:`rerun.DepthImage`."""
    rr = require_rerun()
    d = np.nan_to_num(np.asarray(depth_map, np.float64), nan=0.0, posinf=0.0, neginf=0.0).clip(0)
    meter = float(np.clip(np.floor(65535.0 / max(float(d.max()), 1e-6)), 1.0, 10000.0))
    rec.log(entity, rr.DepthImage(np.round(d * meter).clip(0, 65535).astype(np.uint16), meter=meter))


def mask(rec, entity: str, dynamic: np.ndarray) -> None:
    """A bool mask (H, W) as a segmentation layer (class :data:`DYNAMIC` where set)."""
    rr = require_rerun()
    rec.log(entity, rr.SegmentationImage(np.where(np.asarray(dynamic, bool), DYNAMIC, STATIC).astype(np.uint8)))


def camera(rec, entity: str, cam_to_world: np.ndarray, K: np.ndarray, width: int, height: int) -> None:
    """A pinhole camera (intrinsics K (3, 3), image size) at pose ``cam_to_world`` (4, 4)."""
    rr = require_rerun()
    T = np.asarray(cam_to_world, np.float64)
    rec.log(entity, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]),
            rr.Pinhole(image_from_camera=np.asarray(K, np.float64), resolution=[width, height],
                       camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.15))


def points2d(rec, entity: str, uv: np.ndarray, color, radius: float = 1.5) -> None:
    rr = require_rerun()
    rec.log(entity, rr.Points2D(np.asarray(uv, np.float32).reshape(-1, 2), colors=color, radii=radius))


def points3d(rec, entity: str, points: np.ndarray, colors, radius: float) -> None:
    rr = require_rerun()
    rec.log(entity, rr.Points3D(np.asarray(points, np.float32).reshape(-1, 3), colors=colors, radii=radius))


def strip(rec, entity: str, positions: np.ndarray, color, radius: float = 0.004) -> None:
    """One line strip through ``positions`` (N, 3)."""
    rr = require_rerun()
    rec.log(entity, rr.LineStrips3D([np.asarray(positions, np.float32).reshape(-1, 3)], colors=[color],
                                    radii=radius))


def segments(rec, entity: str, pairs: np.ndarray, color, radius: float = 0.006) -> None:
    """Line segments (M, 2, 3)."""
    rr = require_rerun()
    rec.log(entity, rr.LineStrips3D(np.asarray(pairs, np.float32).reshape(-1, 2, 3), colors=[color], radii=radius))


def text(rec, entity: str, message: str, level: str = "INFO") -> None:
    rr = require_rerun()
    rec.log(entity, rr.TextLog(message, level=level))


def scalar(rec, entity: str, value: float) -> None:
    rr = require_rerun()
    if np.isfinite(value):
        rec.log(entity, rr.Scalars(float(value)))


def clear(rec, entity: str) -> None:
    """Remove ``entity`` and its children from this time on."""
    rr = require_rerun()
    rec.log(entity, rr.Clear(recursive=True))


def brighter(colors: np.ndarray, amount: float = 0.55) -> np.ndarray:
    """Colours (N, 3) uint8 moved ``amount`` of the way to white (the recalled memory)."""
    c = np.asarray(colors, np.float64)
    return np.clip(np.round(c + amount * (255.0 - c)), 0, 255).astype(np.uint8)
