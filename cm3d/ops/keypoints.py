"""Keypoint matches between two frames (host side, OpenCV), padded to a fixed capacity.
SIFT (default) or ORB, brute-force k=2 matching with Lowe's ratio test, best first, padded to
``max_matches`` with a validity mask; pixel ``(u, v)`` (:mod:`cm3d.ops.camera`). Also floor keypoints."""

from __future__ import annotations

import dataclasses

import numpy as np
from flax import struct

from cm3d.ops import camera


@dataclasses.dataclass(frozen=True)
class KeypointConfig:
    """detector: "sift" or "orb"; max_matches: capacity (static); ratio: Lowe ratio threshold."""

    detector: str = "sift"
    max_matches: int = 512
    ratio: float = 0.8
    max_features: int = 2000
    # SIFT's contrast threshold (None: OpenCV's 0.04, which finds almost nothing on weakly textured walls)
    contrast_threshold: float | None = None
    # features_from's order: 0 strongest first; n > 0 round robin over an n x n grid of the detections'
    # bounding box (every cell's strongest, then every cell's second, ...), so that a frame's memory
    # features cover its weakly textured surfaces too, not only its few strongest corners
    spread_cells: int = 0
    # the SIFT contrast threshold the keypoints used for matching must pass (None: all detected): with a
    # low ``contrast_threshold`` for the memory features, matching only keypoints of response >=
    # match_contrast / 3 (OpenCV's test: |DoG| * nOctaveLayers >= threshold) keeps the matches, and their
    # cost, of a detection at ``match_contrast``
    match_contrast: float | None = None

    def __post_init__(self):
        if self.detector not in ("sift", "orb"):
            raise ValueError(f"KeypointConfig.detector: unknown {self.detector!r} (sift, orb)")
        if self.max_matches < 1:
            raise ValueError("KeypointConfig.max_matches: must be >= 1")
        if self.contrast_threshold is not None and not self.contrast_threshold > 0:
            raise ValueError(f"KeypointConfig.contrast_threshold: must be > 0 or None, "
                             f"got {self.contrast_threshold}")
        if self.match_contrast is not None and not self.match_contrast > 0:
            raise ValueError(f"KeypointConfig.match_contrast: must be > 0 or None, got {self.match_contrast}")
        if self.spread_cells < 0:
            raise ValueError(f"KeypointConfig.spread_cells: must be >= 0, got {self.spread_cells}")


@struct.dataclass
class Matches:
    """Matched pixels: uv0, uv1 (..., N, 2) float32; valid (..., N) bool; N = max_matches."""

    uv0: np.ndarray
    uv1: np.ndarray
    valid: np.ndarray


def _norm(cfg: KeypointConfig):
    """The descriptor distance of ``cfg``'s detector (OpenCV norm type)."""
    import cv2

    return cv2.NORM_L2 if cfg.detector == "sift" else cv2.NORM_HAMMING


def _detector(cfg: KeypointConfig, precise: bool = False):
    """OpenCV's detector of ``cfg`` and its norm; ``precise``: SIFT's exact 2x upscale of the first octave
    (OpenCV's default shifts every keypoint by +0.25 px)."""
    import cv2

    if cfg.detector == "sift":
        extra = {} if cfg.contrast_threshold is None else {"contrastThreshold": cfg.contrast_threshold}
        return cv2.SIFT_create(nfeatures=cfg.max_features, enable_precise_upscale=precise, **extra), _norm(cfg)
    return cv2.ORB_create(nfeatures=cfg.max_features), _norm(cfg)


def _gray(img):
    import cv2

    img = np.asarray(img)
    if img.dtype != np.uint8 or img.ndim not in (2, 3):
        raise ValueError(f"image: expected uint8 (H, W[, 3]), got {img.dtype} {img.shape}")
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img


def detect(image: np.ndarray, cfg: KeypointConfig = KeypointConfig(), mask: np.ndarray | None = None,
           precise: bool = False):
    """OpenCV keypoints and raw descriptors of ``image`` with ``cfg``'s detector (``mask`` (H, W) bool
    optionally restricts detection; ``precise``: see :func:`_detector`): ``(keypoints, descriptors or None)``.
    One detection serves :func:`match_detections` (both as the first and the second image) and
    :func:`features_from`."""
    det, _ = _detector(cfg, precise)
    m8 = None if mask is None else np.asarray(mask, np.uint8) * 255
    return det.detectAndCompute(_gray(image), m8)


def detect_reduced(image: np.ndarray, cfg: KeypointConfig = KeypointConfig(), factor: int = 2):
    """:func:`detect` on ``image`` area-averaged by ``factor`` (SIFT's cost grows with the pixels: 480x640
    at ``factor`` 2 is ~5x cheaper), the keypoints in ``image``'s pixels: a reduced pixel ``u`` is the mean
    of full pixels ``f u .. f u + f - 1``, centred at ``f (u + 0.5) - 0.5`` (``f`` = full / reduced size).
    SIFT runs with its exact first-octave upscale, so the positions carry no half-pixel bias."""
    import cv2

    g = _gray(image)
    H, W = g.shape
    h, w = -(-H // factor), -(-W // factor)
    small = cv2.resize(g, (w, h), interpolation=cv2.INTER_AREA) if factor > 1 else g
    kps, desc = detect(small, cfg, precise=True)
    fx, fy = W / w, H / h
    out = [cv2.KeyPoint(fx * (k.pt[0] + 0.5) - 0.5, fy * (k.pt[1] + 0.5) - 0.5, k.size * fx, k.angle, k.response,
                        k.octave, k.class_id) for k in kps]
    return out, desc


_SIFT_OCTAVE_LAYERS = 3  # OpenCV's default nOctaveLayers, which _detector keeps


def _for_matching(det, cfg: KeypointConfig):
    """The keypoints of a :func:`detect` result that ``cfg.match_contrast`` lets into matching."""
    kps, desc = det
    if cfg.match_contrast is None or cfg.detector != "sift" or desc is None or len(kps) == 0:
        return kps, desc
    keep = np.flatnonzero(np.array([k.response for k in kps]) * _SIFT_OCTAVE_LAYERS >= cfg.match_contrast)
    return [kps[i] for i in keep], desc[keep]


def match_detections(det0, det1, cfg: KeypointConfig = KeypointConfig()) -> Matches:
    """Ratio-test matches between two :func:`detect` results, best first, padded to ``cfg.max_matches``
    (only keypoints that pass ``cfg.match_contrast``)."""
    import cv2

    (k0, d0), (k1, d1) = _for_matching(det0, cfg), _for_matching(det1, cfg)
    norm = _norm(cfg)
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


def match_keypoints(img0: np.ndarray, img1: np.ndarray, cfg: KeypointConfig = KeypointConfig(),
                    mask0: np.ndarray | None = None) -> Matches:
    """Ratio-test matches from ``img0`` to ``img1``, best first, padded to ``cfg.max_matches``; ``mask0``
    (H, W) bool optionally restricts detection in ``img0``."""
    return match_detections(detect(img0, cfg, mask0), detect(img1, cfg), cfg)


def sequence_matches(images: np.ndarray, cfg: KeypointConfig = KeypointConfig()) -> Matches:
    """Matches between consecutive frames, stacked: arrays with a leading (S-1) axis."""
    pairs = [match_keypoints(images[i], images[i + 1], cfg) for i in range(len(images) - 1)]
    if not pairs:
        N = cfg.max_matches
        return Matches(np.zeros((0, N, 2), np.float32), np.zeros((0, N, 2), np.float32), np.zeros((0, N), bool))
    return Matches(*(np.stack([getattr(p, f) for p in pairs]) for f in ("uv0", "uv1", "valid")))


@struct.dataclass
class Features:
    """Detected keypoints of one image, strongest first (with ``KeypointConfig.spread_cells``: a round
    robin over image cells, each cell's strongest first): uv (N, 2) float32 pixels, desc (N, D) float32
    unit-norm descriptors, valid (N,) bool; N = capacity."""

    uv: np.ndarray
    desc: np.ndarray
    valid: np.ndarray


DESCRIPTOR_DIM = {"sift": 128, "orb": 256}


def detect_features(image: np.ndarray, mask: np.ndarray | None = None, capacity: int = 256,
                    cfg: KeypointConfig = KeypointConfig(), contrast_threshold: float | None = None) -> Features:
    """Keypoints and descriptors of ``image`` inside ``mask`` (H, W) bool, padded to ``capacity``,
    strongest first. SIFT descriptors are RootSIFT (Euclidean = Hellinger); ORB's 256 bits become
    +-1/16 (unit L2). ``contrast_threshold``: SIFT's (overrides ``cfg.contrast_threshold``)."""
    if capacity < 1:
        raise ValueError(f"capacity: must be >= 1, got {capacity}")
    img = _gray(image)
    if mask is not None and np.asarray(mask).shape != img.shape:
        raise ValueError(f"mask: expected shape {img.shape}, got {np.asarray(mask).shape}")
    if contrast_threshold is not None:
        cfg = dataclasses.replace(cfg, contrast_threshold=contrast_threshold)
    det, _ = _detector(cfg)
    m8 = None if mask is None else np.asarray(mask, np.uint8) * 255
    return features_from(det.detectAndCompute(img, m8), capacity, cfg)


def spread_order(uv: np.ndarray, cells: int, order: np.ndarray | None = None) -> np.ndarray:
    """A round robin over a ``cells`` x ``cells`` grid of the bounding box of ``uv`` (N, 2), listed in
    priority order (``order``: their indices, default ``arange(N)``): every cell's first entry, then every
    cell's second, ... (within a round, priority order). Returns the reordered ``order``."""
    uv = np.asarray(uv, np.float64)
    order = np.arange(len(uv)) if order is None else np.asarray(order)
    if len(uv) == 0:
        return order
    lo, span = uv.min(0), np.maximum(np.ptp(uv, axis=0), 1e-9)
    ij = np.minimum(np.floor((uv - lo) / span * cells), cells - 1).astype(np.int64)
    cell = ij[:, 1] * cells + ij[:, 0]
    by_cell = np.argsort(cell, kind="stable")  # grouped by cell, priority order within a cell
    sorted_cells = cell[by_cell]
    starts = np.flatnonzero(np.r_[True, sorted_cells[1:] != sorted_cells[:-1]])
    rank = np.empty(len(uv), np.int64)
    rank[by_cell] = np.arange(len(uv)) - np.repeat(starts, np.diff(np.r_[starts, len(uv)]))
    return order[np.argsort(rank, kind="stable")]


def features_from(detection, capacity: int = 256, cfg: KeypointConfig = KeypointConfig()) -> Features:
    """:class:`Features` of a :func:`detect` result (see :func:`detect_features`)."""
    if capacity < 1:
        raise ValueError(f"capacity: must be >= 1, got {capacity}")
    kps, desc = detection
    D = DESCRIPTOR_DIM[cfg.detector]
    uv, out, valid = np.zeros((capacity, 2), np.float32), np.zeros((capacity, D), np.float32), np.zeros(capacity, bool)
    if desc is None or len(kps) == 0:
        return Features(uv, out, valid)
    order = np.argsort([-k.response for k in kps], kind="stable")
    if cfg.spread_cells > 0:
        order = spread_order(np.array([k.pt for k in kps], np.float64)[order], cfg.spread_cells, order)
    order = order[:capacity]
    n = len(order)
    if cfg.detector == "sift":
        d = _rootsift(desc[order])
    else:
        d = (np.unpackbits(desc[order], axis=1).astype(np.float32) * 2 - 1) / 16.0
        d /= np.linalg.norm(d, axis=1, keepdims=True)
    uv[:n] = [kps[i].pt for i in order]
    out[:n] = d
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


# Floor orthophoto keypoints


@dataclasses.dataclass(frozen=True)
class FloorConfig:
    """Options of :func:`floor_features`.

    pixels_per_height: orthophoto pixels per first-camera height above the floor (follows the scene,
    not the prior's unknown scale); plane_tolerance: relative depth error of a floor pixel;
    max_tilt: degrees between floor normal and the first camera's up (``up_prior``, OpenCV -y);
    ransac_iterations / stride: plane fit; max_canvas: orthophoto side cap (px); contrast_threshold: SIFT's.
    """

    pixels_per_height: float = 60.0
    plane_tolerance: float = 0.05
    max_tilt: float = 30.0
    ransac_iterations: int = 256
    stride: int = 4
    max_canvas: int = 1024
    contrast_threshold: float = 0.01
    up_prior: tuple[float, float, float] = (0.0, -1.0, 0.0)

    def __post_init__(self):
        for name in ("pixels_per_height", "plane_tolerance", "max_tilt", "contrast_threshold"):
            if not getattr(self, name) > 0:
                raise ValueError(f"FloorConfig.{name}: must be > 0, got {getattr(self, name)}")
        if self.ransac_iterations < 1 or self.stride < 1 or self.max_canvas < 16:
            raise ValueError("FloorConfig: ransac_iterations and stride must be >= 1, max_canvas >= 16")
        if len(self.up_prior) != 3 or not 0 < float(np.linalg.norm(self.up_prior)) < np.inf:
            raise ValueError(f"FloorConfig.up_prior: need a non-zero 3-vector, got {self.up_prior}")


@struct.dataclass
class FloorFeatures:
    """3D keypoints on the floor, strongest first: points (N, 3) in the frame of ``cam_to_world``,
    desc (N, 128) RootSIFT of the orthophoto, valid (N,) bool; N = capacity."""

    points: np.ndarray
    desc: np.ndarray
    valid: np.ndarray


def _rootsift(desc: np.ndarray) -> np.ndarray:
    """RootSIFT (L1-normalise, square root), then unit L2."""
    d = np.sqrt(desc.astype(np.float32) / np.maximum(desc.sum(1, keepdims=True), 1e-12))
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def _check_views(images, depth, K, cam_to_world, static):
    images, depth = np.asarray(images), np.asarray(depth, np.float64)
    K, cam_to_world = np.asarray(K, np.float64), np.asarray(cam_to_world, np.float64)
    if depth.ndim != 3:
        raise ValueError(f"depth: expected (S, H, W), got {depth.shape}")
    S, H, W = depth.shape
    for name, a, shape in (("images", images, (S, H, W, 3)), ("K", K, (S, 3, 3)), ("cam_to_world", cam_to_world, (S, 4, 4))):
        if a.shape != shape:
            raise ValueError(f"{name}: expected {shape}, got {a.shape}")
    if images.dtype != np.uint8:
        raise ValueError(f"images: expected uint8, got {images.dtype}")
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(cam_to_world))):
        raise ValueError("K / cam_to_world: non-finite values")
    if np.any(np.abs(np.linalg.det(K)) < 1e-12):
        raise ValueError("K: singular intrinsics")
    static = np.ones((S, H, W), bool) if static is None else np.asarray(static, bool)
    if static.shape != (S, H, W):
        raise ValueError(f"static: expected {(S, H, W)}, got {static.shape}")
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
    return images, depth, K, cam_to_world, static


def _pixel_rays(K, H, W, stride=1):
    v, u = np.mgrid[0:H:stride, 0:W:stride]
    return camera.rays(np.stack([u, v], -1).astype(np.float64), np.asarray(K, np.float64))  # (h, w, 3), z = 1


def floor_plane(depth, K, cam_to_world, static=None, cfg: FloorConfig = FloorConfig(), seed: int = 0):
    """The floor ``(n, c)`` (unit normal up, ``n . x + c = 0``, ``c`` > 0: the first camera's height) in
    the frame of ``cam_to_world``, or None when no plane qualifies.

    RANSAC over the static pixels' points for planes within ``cfg.max_tilt`` of the first camera's up
    and below it, refitted on the inliers: the dominant horizontal surface (a floor, or a table top).
    """
    depth, K, cam_to_world = np.asarray(depth, np.float64), np.asarray(K, np.float64), np.asarray(cam_to_world, np.float64)
    S, H, W = depth.shape
    st = cfg.stride
    static = np.ones((S, H, W), bool) if static is None else np.asarray(static, bool)
    pts = []
    for s in range(S):
        d = depth[s, ::st, ::st]
        ok = static[s, ::st, ::st] & np.isfinite(d) & (d > 0)
        X = _pixel_rays(K[s], H, W, st)[ok] * d[ok][:, None]
        pts.append(X @ cam_to_world[s, :3, :3].T + cam_to_world[s, :3, 3])
    P = np.concatenate(pts) if pts else np.zeros((0, 3))
    if len(P) < 3:
        return None
    up = cam_to_world[0, :3, :3] @ np.asarray(cfg.up_prior, np.float64)
    up /= np.linalg.norm(up)
    origin = cam_to_world[0, :3, 3]
    rng = np.random.default_rng(seed)
    tri = rng.integers(0, len(P), (cfg.ransac_iterations, 3))
    n = np.cross(P[tri[:, 1]] - P[tri[:, 0]], P[tri[:, 2]] - P[tri[:, 0]])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(norm > 1e-12, n / np.maximum(norm, 1e-12), 0.0)
    n *= np.where(n @ up < 0, -1.0, 1.0)[:, None]
    c = -np.einsum("ij,ij->i", n, P[tri[:, 0]])
    h = n @ origin + c  # first camera's height above each plane
    ok = (n @ up >= np.cos(np.radians(cfg.max_tilt))) & (h > 0)
    if not ok.any():
        return None
    n, c, h = n[ok], c[ok], h[ok]
    count = np.zeros(len(n), np.int64)
    for i in range(0, len(n), 32):  # (planes x points) in blocks
        count[i:i + 32] = (np.abs(P @ n[i:i + 32].T + c[i:i + 32]) < 0.01 * h[i:i + 32]).sum(0)
    b = int(np.argmax(count))
    if count[b] < 3:
        return None
    inl = P[np.abs(P @ n[b] + c[b]) < 0.015 * h[b]]
    m = inl.mean(0)
    nf = np.linalg.svd(inl - m, full_matrices=False)[2][2]
    nf *= 1.0 if nf @ up >= 0 else -1.0
    cf = -float(nf @ m)
    if nf @ origin + cf <= 0:
        return None
    return nf, cf


def floor_orthophoto(images, depth, K, cam_to_world, static, plane, cfg: FloorConfig = FloorConfig()):
    """A top-down mosaic of the floor ``plane``: ``(image (h, w, 3) uint8, valid (h, w) bool, to_world
    (3, 3))``, ``to_world`` taking orthophoto pixels ``(u, v, 1)`` to points on the plane.

    Floor pixels of every frame are warped by the plane's homography (the closest camera wins). Why:
    views of the floor from anywhere differ by a 2D similarity, which SIFT is invariant to.
    """
    return _orthophoto(*_check_views(images, depth, K, cam_to_world, static), plane, cfg)


def _orthophoto(images, depth, K, cam_to_world, static, plane, cfg: FloorConfig):
    """:func:`floor_orthophoto` of checked inputs (:func:`_check_views`)."""
    import cv2

    S, H, W = depth.shape
    n, c = np.asarray(plane[0], np.float64), float(plane[1])
    h = n @ cam_to_world[0, :3, 3] + c
    e1 = np.cross(n, cam_to_world[0, :3, 2])  # u axis: across the first camera's view
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(n, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    o = cam_to_world[0, :3, 3] - h * n  # the first camera's foot on the floor
    # the floor pixels of every frame and their plane coordinates
    masks, ab = [], []
    for s in range(S):
        R, C = cam_to_world[s, :3, :3], cam_to_world[s, :3, 3]
        ray = _pixel_rays(K[s], H, W) @ R.T  # world directions, camera z = 1
        den = ray @ n
        t = -(n @ C + c) / np.where(np.abs(den) > 1e-12, den, np.nan)  # plane depth along each ray
        with np.errstate(invalid="ignore"):
            m = static[s] & (depth[s] > 0) & (t > 0) & (np.abs(depth[s] / t - 1) < cfg.plane_tolerance)
        masks.append(m)
        X = C + ray[m] * t[m][:, None] - o
        ab.append(np.stack([X @ e1, X @ e2], -1))
    ab = np.concatenate(ab)
    if len(ab) < 16:
        return np.zeros((1, 1, 3), np.uint8), np.zeros((1, 1), bool), np.eye(3)
    lo, hi = np.quantile(ab, 0.002, axis=0), np.quantile(ab, 0.998, axis=0)
    delta = max(h / cfg.pixels_per_height, float((hi - lo).max()) / cfg.max_canvas)
    w, hh = int((hi[0] - lo[0]) / delta) + 1, int((hi[1] - lo[1]) / delta) + 1
    A = np.array([[delta, 0, lo[0]], [0, delta, lo[1]], [0, 0, 1.0]])  # orthophoto pixel -> (a, b, 1)
    to_world = np.stack([e1, e2, o], 1) @ A  # (3, 3): (u, v, 1) -> point
    vv, uu = np.mgrid[0:hh, 0:w]
    grid = np.stack([uu, vv, np.ones_like(uu)], -1).astype(np.float64) @ to_world.T  # (hh, w, 3) points
    best = np.full((hh, w), np.inf)
    out = np.zeros((hh, w, 3), np.uint8)
    for s in range(S):
        R, C = cam_to_world[s, :3, :3], cam_to_world[s, :3, 3]
        Hm = K[s] @ np.concatenate([R.T @ to_world[:, :2], (R.T @ (to_world[:, 2] - C))[:, None]], 1)
        Hm = Hm / Hm[2, 2] if abs(Hm[2, 2]) > 1e-12 else Hm
        flags = cv2.WARP_INVERSE_MAP
        img = cv2.warpPerspective(images[s], Hm, (w, hh), flags=flags | cv2.INTER_LINEAR)
        m = cv2.warpPerspective(masks[s].astype(np.uint8), Hm, (w, hh), flags=flags | cv2.INTER_NEAREST) > 0
        rel = grid - C
        dist = np.linalg.norm(rel, axis=-1)
        take = m & (rel @ R[:, 2] > 0) & (dist < best)  # in front of the camera, closest so far
        best[take], out[take] = dist[take], img[take]
    return out, np.isfinite(best), to_world


def floor_features(images, depth, K, cam_to_world, static=None, capacity: int = 512,
                   cfg: FloorConfig = FloorConfig(), seed: int = 0) -> FloorFeatures:
    """SIFT keypoints of the floor orthophoto as 3D points in the frame of ``cam_to_world`` with RootSIFT
    descriptors, the ``capacity`` strongest first (host, NumPy + OpenCV; no floor: none valid).
    images (S, H, W, 3) uint8, depth (S, H, W), K (S, 3, 3), cam_to_world (S, 4, 4), static (S, H, W)."""
    import cv2

    if capacity < 1:
        raise ValueError(f"capacity: must be >= 1, got {capacity}")
    images, depth, K, cam_to_world, static = _check_views(images, depth, K, cam_to_world, static)
    pts, out, valid = np.zeros((capacity, 3), np.float32), np.zeros((capacity, 128), np.float32), np.zeros(capacity, bool)
    plane = floor_plane(depth, K, cam_to_world, static, cfg, seed)
    if plane is None:
        return FloorFeatures(pts, out, valid)
    img, ok, to_world = _orthophoto(images, depth, K, cam_to_world, static, plane, cfg)
    mask = cv2.erode(ok.astype(np.uint8) * 255, np.ones((5, 5), np.uint8))
    det = cv2.SIFT_create(contrastThreshold=cfg.contrast_threshold)
    kps, desc = det.detectAndCompute(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), mask)
    if desc is None or len(kps) == 0:
        return FloorFeatures(pts, out, valid)
    order = np.argsort([-k.response for k in kps], kind="stable")[:capacity]
    uv = np.array([kps[i].pt for i in order], np.float64)
    k = len(order)
    pts[:k] = np.concatenate([uv, np.ones((k, 1))], 1) @ to_world.T
    out[:k] = _rootsift(desc[order])
    valid[:k] = True
    return FloorFeatures(pts, out, valid)
