"""The run-level check a refinement must pass (host, numpy): do the refined poses make the images
agree better than the prior poses do? Evidence the factor graph never saw: the graph fits flow
tracks, this compares grey values of static pixels warped between frames with the prior depth.

For frame pairs ``(t, t + g)``, ``g`` in ``GAPS``, every ``stride``-th static pixel of frame t with
depth > 0 and confidence > 0 is lifted with its depth, moved by each trajectory's relative pose and
projected into frame t + g; a pixel counts when it lands inside the image on a static pixel under
every trajectory compared (a paired comparison). The error of a trajectory is the mean over pairs of
the mean absolute grey difference, truncated at ``TRUNCATE`` levels (occlusions, moving objects).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from cm3d.data import quality

GAPS = (1, 2, 4)
TRUNCATE = 40.0  # grey levels (0-255)
MAX_PIXELS = 3000  # pixels sampled per frame
MIN_PIXELS = 200  # fewer paired pixels in all: no evidence
SAME_POSES = 1e-5  # refined poses this close to the prior (float32 noise of the compiled step) are the prior
TIE = 1e-3  # relative error difference below which the images cannot tell the two trajectories apart
# the window's memory test (cm3d.pipeline.memory_graph.photometric_test): the frame pairs on which the memory
# solution is the better one, counted against chance (a one-sided sign test), must be this unlikely under "no
# difference"; a conventional level, the same on any data
SIGN_ALPHA = 0.05


def memory_wins(e_free, e_mem, p):
    """The memory solution's two photometric conditions (NumPy or JAX scalars): (its mean grey error is lower
    than the memory-free one's by more than ``TIE``, its sign test over the frame pairs has p < ``SIGN_ALPHA``)."""
    return e_mem < e_free * (1 - TIE), p < SIGN_ALPHA


def _bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    H, W = img.shape
    u0 = np.clip(np.floor(u).astype(np.int64), 0, W - 2)
    v0 = np.clip(np.floor(v).astype(np.int64), 0, H - 2)
    fu, fv = u - u0, v - v0
    top = img[v0, u0] * (1 - fu) + img[v0, u0 + 1] * fu
    bottom = img[v0 + 1, u0] * (1 - fu) + img[v0 + 1, u0 + 1] * fu
    return top * (1 - fv) + bottom * fv


def warp_errors(seq, trajectories, masks=None, gaps=GAPS, max_pixels: int = MAX_PIXELS):
    """Per frame pair, the truncated mean grey difference under each trajectory (see the module
    docstring). trajectories: list of cam_to_world (S, 4, 4); masks: (S, H, W) dynamic (None: none).
    Returns (errors (pairs, len(trajectories)), paired pixels per pair (pairs,))."""
    grey = quality.grey_levels(seq.images)  # a float64 mean of the channels, without a float64 copy of every channel
    S, H, W = grey.shape
    d = np.asarray(seq.depth)
    c = np.asarray(seq.depth_conf)
    dyn = np.zeros((S, H, W), bool) if masks is None else np.asarray(masks, bool)
    K = np.asarray(seq.intrinsic, np.float64)
    Ps = [np.asarray(P, np.float64) for P in trajectories]
    st = max(1, int(np.sqrt(H * W / max_pixels)))
    v, u = np.mgrid[0:H:st, 0:W:st]
    u, v = u.ravel().astype(np.float64), v.ravel().astype(np.float64)
    iu, iv = u.astype(np.int64), v.astype(np.int64)
    errors, counts = [], []
    for t in range(S):
        dt = d[t, iv, iu].astype(np.float64)
        src = np.isfinite(dt) & (dt > 0) & (c[t, iv, iu] > 0) & ~dyn[t, iv, iu]
        rays = np.linalg.solve(K[t], np.stack([u, v, np.ones_like(u)]))  # (3, N)
        X = rays * np.where(src, dt, 0.0)
        for g in gaps:
            j = t + g
            if j >= S:
                continue
            ok = src.copy()
            samples = []
            for P in Ps:
                rel = np.linalg.solve(P[j], P[t])
                Y = rel[:3, :3] @ X + rel[:3, 3:]
                z = Y[2]
                zs = np.where(z > 1e-9, z, 1.0)
                uj = (K[j, 0, 0] * Y[0] + K[j, 0, 1] * Y[1]) / zs + K[j, 0, 2]
                vj = K[j, 1, 1] * Y[1] / zs + K[j, 1, 2]
                inside = (z > 1e-9) & (uj >= 0) & (uj <= W - 1) & (vj >= 0) & (vj <= H - 1)
                uc = np.clip(np.round(uj), 0, W - 1).astype(np.int64)
                vc = np.clip(np.round(vj), 0, H - 1).astype(np.int64)
                ok &= inside & ~dyn[j, vc, uc]
                samples.append((uj, vj))
            n = int(ok.sum())
            if n == 0:
                continue
            ref = grey[t, iv[ok], iu[ok]]
            errors.append([np.minimum(np.abs(_bilinear(grey[j], uj[ok], vj[ok]) - ref), TRUNCATE).mean()
                           for uj, vj in samples])
            counts.append(n)
    return np.asarray(errors, np.float64).reshape(-1, len(Ps)), np.asarray(counts, np.int64)


@dataclasses.dataclass(frozen=True)
class PhotometricCheck:
    """The run-level check: grey-value error (levels) of the prior and the refined poses, the frame
    pairs and paired pixels it rests on, and whether the refinement is kept (``reason`` says why)."""

    prior_error: float
    refined_error: float
    pairs: int
    pixels: int
    kept: bool
    reason: str

    def to_json(self) -> dict:
        return {"prior_error": round(self.prior_error, 4), "refined_error": round(self.refined_error, 4),
                "pairs": self.pairs, "pixels": self.pixels, "kept": self.kept, "reason": self.reason}


def check_refinement(seq, prior, refined, masks=None) -> PhotometricCheck:
    """Keep the refined poses only when they do not make the static pixels agree worse than the prior
    does (on at least ``MIN_PIXELS`` paired pixels; a difference within ``TIE`` is no difference);
    refined poses equal to the prior (within ``SAME_POSES``) pass."""
    prior, refined = np.asarray(prior, np.float64), np.asarray(refined, np.float64)
    if np.allclose(prior, refined, rtol=0.0, atol=SAME_POSES):
        return PhotometricCheck(np.nan, np.nan, 0, 0, True, "the refinement left the prior poses unchanged")
    err, n = warp_errors(seq, [prior, refined], masks, GAPS)
    if n.sum() < MIN_PIXELS:
        return PhotometricCheck(np.nan, np.nan, len(n), int(n.sum()), False,
                                f"no evidence: only {int(n.sum())} static pixels are seen by two frames")
    a, b = (float(x) for x in err.mean(0))
    if b < a:
        return PhotometricCheck(a, b, len(n), int(n.sum()), True,
                                f"static pixels agree better: grey error {a:.3f} -> {b:.3f}")
    if b <= a * (1 + TIE):
        return PhotometricCheck(a, b, len(n), int(n.sum()), True,
                                f"the images cannot tell the refined poses from the prior: grey error {a:.4f} -> {b:.4f}")
    return PhotometricCheck(a, b, len(n), int(n.sum()), False,
                            f"the refined poses make static pixels agree worse than the prior: grey error "
                            f"{a:.3f} -> {b:.3f}")
