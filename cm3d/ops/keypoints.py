"""Keypoint matches between two frames (host side, OpenCV), padded to a fixed capacity.

SIFT (default) or ORB features, brute-force k=2 matching with Lowe's ratio test, best matches
first, truncated or zero-padded to ``max_matches`` with a validity mask so that jitted stages see
one shape. Coordinates are pixel ``(u, v)`` (see :mod:`cm3d.ops.camera`).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from flax import struct


@dataclasses.dataclass(frozen=True)
class KeypointConfig:
    """detector: "sift" or "orb"; max_matches: capacity (static); ratio: Lowe ratio threshold."""

    detector: str = "sift"
    max_matches: int = 512
    ratio: float = 0.8
    max_features: int = 2000

    def __post_init__(self):
        if self.detector not in ("sift", "orb"):
            raise ValueError(f"KeypointConfig.detector: unknown {self.detector!r} (sift, orb)")
        if self.max_matches < 1:
            raise ValueError("KeypointConfig.max_matches: must be >= 1")


@struct.dataclass
class Matches:
    """Matched pixels: uv0, uv1 (..., N, 2) float32; valid (..., N) bool; N = max_matches."""

    uv0: np.ndarray
    uv1: np.ndarray
    valid: np.ndarray


def _detector(cfg: KeypointConfig):
    import cv2

    if cfg.detector == "sift":
        return cv2.SIFT_create(nfeatures=cfg.max_features), cv2.NORM_L2
    return cv2.ORB_create(nfeatures=cfg.max_features), cv2.NORM_HAMMING


def _gray(img):
    import cv2

    img = np.asarray(img)
    if img.dtype != np.uint8 or img.ndim not in (2, 3):
        raise ValueError(f"image: expected uint8 (H, W[, 3]), got {img.dtype} {img.shape}")
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img


def match_keypoints(img0: np.ndarray, img1: np.ndarray, cfg: KeypointConfig = KeypointConfig(),
                    mask0: np.ndarray | None = None) -> Matches:
    """Ratio-test matches from ``img0`` to ``img1``, best first, padded to ``cfg.max_matches``.

    ``mask0`` (H, W) bool optionally restricts detection in ``img0``.
    """
    import cv2

    det, norm = _detector(cfg)
    m8 = None if mask0 is None else np.asarray(mask0, np.uint8) * 255
    k0, d0 = det.detectAndCompute(_gray(img0), m8)
    k1, d1 = det.detectAndCompute(_gray(img1), None)
    N = cfg.max_matches
    uv0, uv1, valid = np.zeros((N, 2), np.float32), np.zeros((N, 2), np.float32), np.zeros(N, bool)
    if d0 is None or d1 is None or len(k0) == 0 or len(k1) < 2:
        return Matches(uv0, uv1, valid)
    knn = cv2.BFMatcher(norm).knnMatch(d0, d1, k=2)
    good = [p[0] for p in knn if len(p) == 2 and p[0].distance < cfg.ratio * p[1].distance]
    good.sort(key=lambda m: m.distance)
    good = good[:N]
    n = len(good)
    if n:
        uv0[:n] = [k0[m.queryIdx].pt for m in good]
        uv1[:n] = [k1[m.trainIdx].pt for m in good]
        valid[:n] = True
    return Matches(uv0, uv1, valid)


def sequence_matches(images: np.ndarray, cfg: KeypointConfig = KeypointConfig()) -> Matches:
    """Matches between consecutive frames, stacked: arrays with a leading (S-1) axis."""
    pairs = [match_keypoints(images[i], images[i + 1], cfg) for i in range(len(images) - 1)]
    if not pairs:
        N = cfg.max_matches
        return Matches(np.zeros((0, N, 2), np.float32), np.zeros((0, N, 2), np.float32), np.zeros((0, N), bool))
    return Matches(*(np.stack([getattr(p, f) for p in pairs]) for f in ("uv0", "uv1", "valid")))


@struct.dataclass
class Features:
    """Detected keypoints of one image, strongest first: uv (N, 2) float32 pixels, desc (N, D)
    float32 unit-norm descriptors, valid (N,) bool; N = capacity."""

    uv: np.ndarray
    desc: np.ndarray
    valid: np.ndarray


DESCRIPTOR_DIM = {"sift": 128, "orb": 256}


def detect_features(image: np.ndarray, mask: np.ndarray | None = None, capacity: int = 256,
                    cfg: KeypointConfig = KeypointConfig(), contrast_threshold: float | None = None) -> Features:
    """Keypoints and descriptors of ``image`` inside ``mask`` (H, W) bool, padded to ``capacity``.

    SIFT descriptors are RootSIFT (L1-normalised, square-rooted: unit L2, so the Euclidean distance
    is Hellinger's); ORB's 256 bits become +-1/16 (unit L2, distance a monotone function of Hamming).
    The strongest ``capacity`` responses are kept, strongest first. ``contrast_threshold``: SIFT's
    (OpenCV default 0.04); lower finds keypoints on weakly textured, small images.
    """
    import cv2

    if capacity < 1:
        raise ValueError(f"capacity: must be >= 1, got {capacity}")
    img = _gray(image)
    if mask is not None and np.asarray(mask).shape != img.shape:
        raise ValueError(f"mask: expected shape {img.shape}, got {np.asarray(mask).shape}")
    if cfg.detector == "sift" and contrast_threshold is not None:
        det = cv2.SIFT_create(nfeatures=cfg.max_features, contrastThreshold=contrast_threshold)
    else:
        det, _ = _detector(cfg)
    m8 = None if mask is None else np.asarray(mask, np.uint8) * 255
    kps, desc = det.detectAndCompute(img, m8)
    D = DESCRIPTOR_DIM[cfg.detector]
    uv, out, valid = np.zeros((capacity, 2), np.float32), np.zeros((capacity, D), np.float32), np.zeros(capacity, bool)
    if desc is None or len(kps) == 0:
        return Features(uv, out, valid)
    order = np.argsort([-k.response for k in kps], kind="stable")[:capacity]
    n = len(order)
    if cfg.detector == "sift":
        d = desc[order].astype(np.float32)
        d = np.sqrt(d / np.maximum(d.sum(1, keepdims=True), 1e-12))
    else:
        d = (np.unpackbits(desc[order], axis=1).astype(np.float32) * 2 - 1) / 16.0
    uv[:n] = [kps[i].pt for i in order]
    out[:n] = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    valid[:n] = True
    return Features(uv, out, valid)


def detect_sequence(images: np.ndarray, masks: np.ndarray | None = None, capacity: int = 256,
                    cfg: KeypointConfig = KeypointConfig(), contrast_threshold: float | None = None) -> Features:
    """:func:`detect_features` per frame, stacked: arrays with a leading (S,) axis."""
    feats = [detect_features(images[i], None if masks is None else masks[i], capacity, cfg, contrast_threshold)
             for i in range(len(images))]
    D = DESCRIPTOR_DIM[cfg.detector]
    if not feats:
        return Features(np.zeros((0, capacity, 2), np.float32), np.zeros((0, capacity, D), np.float32),
                        np.zeros((0, capacity), bool))
    return Features(*(np.stack([getattr(f, k) for f in feats]) for k in ("uv", "desc", "valid")))
