"""VGGT-like priors from any sequence with ground truth (synthetic renders, 7-Scenes, TUM, ...).

One implementation of the prior model every benchmark uses (the paper's Table 6 protocol):

- the priors live in the first camera's frame (VGGT's convention), scaled so that the mean
  distance of the ground-truth points to the first camera is 1 (VGGT's normalisation) times an
  unknown factor ``exp(N(0, 0.1))``: priors of two segments differ from each other and from the
  world by a similarity transform;
- poses: ground-truth relative poses times errors of the level's RMS size
  (:data:`NOISE_LEVELS`: 1°/1 cm, 3°/3 cm, 5°/5 cm), half i.i.d. jitter and half random-walk
  drift, translations in metres of the true world before the prior's scale;
- depth ``d' = s d (1 + j_t)(1 + b(u, v))(1 + n)``: per-frame scale jitter ``j``, a smooth bias
  ``b`` and pixel noise ``n``, all of std :data:`DEPTH_NOISE`; sensor holes (ground-truth depth 0)
  stay 0;
- confidence (>= 1 like VGGT's where there is depth, 0 in holes): high on smooth, near surfaces,
  low at depth edges (hole borders included) and far away.

Everything is seeded: the same ``(level, seed)`` gives the same priors.
"""

from __future__ import annotations

import numpy as np

from cm3d.data.sequence import GroundTruth, Sequence

# name -> (rotation deg, translation m): RMS size of the pose error, half i.i.d. jitter, half drift.
NOISE_LEVELS = {
    "none": (0.0, 0.0),
    "slight": (1.0, 0.01),
    "moderate": (3.0, 0.03),
    "severe": (5.0, 0.05),
}
# name -> relative depth noise (per-pixel std, also scale of per-frame jitter and smooth bias).
DEPTH_NOISE = {"none": 0.0, "slight": 0.005, "moderate": 0.01, "severe": 0.02}


def check_level(level: str) -> None:
    """Raise ValueError naming the levels when ``level`` is not one of :data:`NOISE_LEVELS`."""
    if level not in NOISE_LEVELS:
        raise ValueError(f"level: unknown noise level {level!r}; choose from {list(NOISE_LEVELS)}")


def pose_errors(rng, num: int, rot_deg: float, trans_m: float, drift_factor: float = 1.0) -> np.ndarray:
    """Pose errors (num, 4, 4): i.i.d. jitter plus a random-walk drift, each of RMS half the level
    (the drift times ``drift_factor``); the first is the identity (it defines the prior frame)."""
    from scipy.spatial.transform import Rotation

    sig = np.array([trans_m] * 3 + [np.deg2rad(rot_deg)] * 3) / np.sqrt(3.0) / np.sqrt(2.0)
    jitter = rng.normal(size=(num, 6)) * sig
    drift = np.cumsum(rng.normal(size=(num, 6)) * sig / np.sqrt(max(num - 1, 1)), axis=0)
    xi = jitter + drift * drift_factor
    xi[0] = 0.0
    out = np.tile(np.eye(4), (num, 1, 1))
    out[:, :3, :3] = Rotation.from_rotvec(xi[:, 3:]).as_matrix()
    out[:, :3, 3] = xi[:, :3]
    return out


def smooth_field(rng, h: int, w: int, n: int = 4) -> np.ndarray:
    """A smooth random field (h, w) of unit-ish amplitude: a few low-frequency cosines."""
    v, u = np.mgrid[0:h, 0:w] / max(h, w)
    f = np.zeros((h, w))
    for _ in range(n):
        k = rng.uniform(0.5, 2.5, 2)
        f += np.cos(2 * np.pi * (k[0] * u + k[1] * v) + rng.uniform(0, 2 * np.pi))
    return f / np.sqrt(n / 2)


def confidence(depth: np.ndarray) -> np.ndarray:
    """VGGT-like confidence (S, H, W) float32 from metric depth: ``1 + 9 edge far`` (>= 1) where
    there is depth, 0 in holes (depth <= 0)."""
    gy, gx = np.gradient(np.log(np.maximum(depth, 1e-3)), axis=(1, 2))
    edge = np.exp(-20.0 * np.hypot(gx, gy))
    far = np.exp(-depth / 6.0)
    return np.where(depth > 0, 1.0 + 9.0 * edge * far, 0.0).astype(np.float32)


def make_priors(images, gt: GroundTruth, level: str = "moderate", seed: int = 0,
                timestamps=None, meta=None, drift: float = 1.0) -> Sequence:
    """A :class:`Sequence` of VGGT-like priors (module docstring) from images (S, H, W, 3) uint8 and
    metric ground truth; ``drift`` multiplies the random-walk part of the pose error (1: the level's;
    larger: a prior whose trajectory drifts). ``meta`` gains ``level``, ``prior_scale`` (the unknown
    scale: prior units per metre) and ``prior_seed``."""
    check_level(level)
    if not (np.isfinite(drift) and drift >= 0):
        raise ValueError(f"drift: must be a finite number >= 0, got {drift}")
    rng = np.random.default_rng([seed, 3])
    S, H, W = gt.depth.shape
    first_inv = np.linalg.inv(gt.cam_to_world[0])
    rel = first_inv @ gt.cam_to_world
    pts = gt.world_points(stride=4)
    pts_first = pts @ first_inv[:3, :3].T + first_inv[:3, 3]
    valid = gt.depth[:, ::4, ::4] > 0
    if not valid.any():
        raise ValueError("ground truth: no frame has any depth (cannot normalise the prior's scale)")
    scale = 1.0 / np.linalg.norm(pts_first[valid], axis=-1).mean() * np.exp(rng.normal(0, 0.1))

    rot_deg, trans_m = NOISE_LEVELS[level]
    noisy = rel @ pose_errors(rng, S, rot_deg, trans_m, drift)
    noisy[:, :3, 3] *= scale

    sd = DEPTH_NOISE[level]
    jit = 1 + sd * rng.normal(size=(S, 1, 1))
    bias = 1 + sd * smooth_field(rng, H, W)[None]
    noise = 1 + sd * rng.normal(size=(S, H, W))
    depth = (scale * gt.depth * jit * bias * noise).astype(np.float32)
    conf = confidence(gt.depth)

    ts = np.arange(S, dtype=np.float64) if timestamps is None else np.asarray(timestamps, float)
    meta = {**(meta or {}), "level": level, "prior_scale": float(scale), "prior_seed": seed}
    return Sequence(images=images, depth=depth, depth_conf=conf, intrinsic=gt.intrinsic.copy(),
                    cam_to_world=noisy, timestamps=ts, gt=gt, meta=meta)


def slice_ground_truth(gt: GroundTruth, start: int, stop: int) -> GroundTruth:
    """Frames ``start:stop`` of ground truth (flow trimmed to the pairs inside)."""
    return GroundTruth(cam_to_world=gt.cam_to_world[start:stop], depth=gt.depth[start:stop],
                       intrinsic=gt.intrinsic[start:stop],
                       dynamic_mask=None if gt.dynamic_mask is None else gt.dynamic_mask[start:stop],
                       flow=None if gt.flow is None else gt.flow[start:max(start, stop - 1)])


def segment_priors(images, gt: GroundTruth, ranges, level: str = "moderate", seed: int = 0,
                   timestamps=None, meta=None, drift: float = 1.0) -> list[Sequence]:
    """Priors of several segments ``[(start, stop), ...]`` of one video, each made on its own
    (:func:`make_priors`: its own first camera, unknown scale and noise, seed ``seed * 7919 + k``),
    as VGGT gives when run segment by segment. Ground truth stays in the common metric frame;
    timestamps are global (default: frame index); meta gains ``chunk``, ``chunk_start``, ``chunk_stop``."""
    S = len(images)
    ts = np.arange(S, dtype=np.float64) if timestamps is None else np.asarray(timestamps, np.float64)
    out = []
    for k, (a, b) in enumerate(ranges):
        m = {**(meta or {}), "chunk": k, "chunk_start": int(a), "chunk_stop": int(b)}
        out.append(make_priors(images[a:b], slice_ground_truth(gt, a, b), level, seed=seed * 7919 + k,
                               timestamps=ts[a:b], meta=m, drift=drift))
    return out


def priors_for(seq: Sequence, level: str = "moderate", seed: int = 0, drift: float = 1.0) -> Sequence:
    """VGGT-like priors for a loaded sequence that carries ground truth (``cm3d run --prior-noise``):
    its images, ground-truth poses and depth -> :func:`make_priors` (timestamps and meta kept)."""
    if seq.gt is None:
        raise ValueError(f"{seq.meta.get('folder', 'input')}: --prior-noise needs ground-truth poses and "
                         "depth, and this input has none")
    return make_priors(seq.images, seq.gt, level, seed, timestamps=seq.timestamps, meta=seq.meta, drift=drift)
