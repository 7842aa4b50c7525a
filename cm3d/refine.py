"""Host-side mask refinement (seeded segmentation) and mask tracking over a sequence.

The paper prompts SAM2 in the dynamic regions; its weights are not available here, so OpenCV
GrabCut (default) or a scikit-image watershed serve the same :class:`MaskRefiner` interface.
:func:`refine_and_track` warps frame t-1's mask to t with the flow as the next seed and re-runs
detection only on the first frame and on new motion. NumPy / OpenCV, outside jit.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Protocol

import numpy as np


@dataclasses.dataclass(frozen=True)
class RefineHints:
    """Optional per-frame hints for a refiner: depth (H, W) prior depth, residual (H, W) px, uncertain
    (H, W) bool: seed pixels that are probably background (:func:`background_movers`)."""

    depth: np.ndarray | None = None
    residual: np.ndarray | None = None
    uncertain: np.ndarray | None = None


class MaskRefiner(Protocol):
    """Extension point (SAM2-like): refined mask (H, W) bool from an RGB uint8 image (H, W, 3), a
    coarse mask (H, W) bool, prompt points (P, 2) int ``(u, v)`` with their region ids (P,), and hints."""

    def __call__(self, image: np.ndarray, coarse: np.ndarray, prompts: np.ndarray, region_ids: np.ndarray,
                 hints: RefineHints) -> np.ndarray: ...


def _disk(r: int) -> np.ndarray:
    import cv2

    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def _dilate(mask, r):
    import cv2

    if r <= 0:
        return mask.astype(bool)
    return cv2.dilate(mask.astype(np.uint8), _disk(r)).astype(bool)


def _erode(mask, r):
    import cv2

    if r <= 0:
        return mask.astype(bool)
    return cv2.erode(mask.astype(np.uint8), _disk(r)).astype(bool)


def sample_prompts(mask: np.ndarray, per_region: int = 8, seed: int = 0, min_area: int = 1):
    """Prompt points sampled uniformly inside each 8-connected region of ``mask`` (eroded by 2 px when
    possible), at most ``per_region`` each. Returns (points (P, 2) int32 ``(u, v)``, region ids (P,),
    label image (H, W) int32, 0 = background)."""
    import cv2

    mask = np.asarray(mask, bool)
    n, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    rng = np.random.default_rng(seed)
    pts, ids = [], []
    inner = _erode(mask, 2)
    for k in range(1, n):
        region = labels == k
        if region.sum() < min_area:
            continue
        core = region & inner
        vv, uu = np.nonzero(core if core.any() else region)
        take = rng.choice(len(uu), size=min(per_region, len(uu)), replace=False)
        pts.append(np.stack([uu[take], vv[take]], -1))
        ids.append(np.full(len(take), k))
    if not pts:
        return np.zeros((0, 2), np.int32), np.zeros(0, np.int32), labels.astype(np.int32)
    return np.concatenate(pts).astype(np.int32), np.concatenate(ids).astype(np.int32), labels.astype(np.int32)


def _px(value: int, width: int, reference: int) -> int:
    """A pixel size given for images ``reference`` wide, scaled to ``width`` (at least 1 when > 0)."""
    return 0 if value <= 0 else max(1, int(round(value * width / reference)))


@dataclasses.dataclass(frozen=True)
class GrabCutRefiner:
    """OpenCV GrabCut seeded by the coarse mask and the prompts.

    Definite foreground around the prompts and in the coarse mask eroded by ``core_px``; probable
    foreground in the rest of it; probable background in a ``band_px`` ring; definite background
    elsewhere. Pixel sizes are for ``reference_width`` wide images and scale with the width.
    ``context=None`` (default): one GrabCut over the whole frame. A number: GrabCut on a window around
    each group of seed regions (:func:`context_boxes`: the region's box grown by ``context`` times its
    size on every side, overlapping windows merged), so the background colour model is the region's
    surroundings and the cost follows the regions' size, not the frame's (docs/motion.md: 2-3x faster
    on the kitchen's small false blobs, DAVIS J 0.692 against 0.699).
    """

    iterations: int = 3
    band_px: int = 8
    core_px: int = 14
    prompt_radius: int = 3
    reference_width: int = 512
    context: float | None = None

    def __call__(self, image, coarse, prompts, region_ids, hints: RefineHints = RefineHints()):
        import cv2

        coarse = np.asarray(coarse, bool)
        if not coarse.any():
            return coarse.copy()
        W = coarse.shape[1]
        px = lambda v: _px(v, W, self.reference_width)  # noqa: E731
        m = np.full(coarse.shape, cv2.GC_BGD, np.uint8)
        m[_dilate(coarse, px(self.band_px))] = cv2.GC_PR_BGD
        m[coarse] = cv2.GC_PR_FGD
        m[_erode(coarse, px(self.core_px))] = cv2.GC_FGD
        if hints.uncertain is not None:
            m[np.asarray(hints.uncertain, bool) & coarse] = cv2.GC_PR_BGD
        for u, v in np.asarray(prompts).reshape(-1, 2):
            cv2.circle(m, (int(u), int(v)), px(self.prompt_radius), int(cv2.GC_FGD), -1)
        if not ((m == cv2.GC_BGD) | (m == cv2.GC_PR_BGD)).any():
            return coarse.copy()  # nothing to contrast against: the whole frame is foreground
        H = coarse.shape[0]
        boxes = [(0, H, 0, W)] if self.context is None else context_boxes(m != cv2.GC_BGD, self.context)
        out = np.zeros_like(coarse)
        for r0, r1, c0, c1 in boxes:
            mb = np.ascontiguousarray(m[r0:r1, c0:c1])
            if not ((mb == cv2.GC_BGD) | (mb == cv2.GC_PR_BGD)).any() or not (mb != cv2.GC_BGD).any():
                out[r0:r1, c0:c1] |= coarse[r0:r1, c0:c1]
                continue
            bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
            try:
                cv2.grabCut(np.ascontiguousarray(image[r0:r1, c0:c1]), mb, None, bgd, fgd, self.iterations,
                            cv2.GC_INIT_WITH_MASK)
            except cv2.error:  # degenerate colour models (e.g. a flat image): keep the seed
                out[r0:r1, c0:c1] |= coarse[r0:r1, c0:c1]
                continue
            out[r0:r1, c0:c1] |= (mb == cv2.GC_FGD) | (mb == cv2.GC_PR_FGD)
        return out


def context_boxes(seeds: np.ndarray, context: float) -> list:
    """Windows (r0, r1, c0, c1) around the 8-connected regions of ``seeds`` (H, W) bool: each region's
    bounding box grown by ``context`` times its height / width on each side (at least 1 px), clipped
    to the frame; windows that overlap are merged into their bounding box until none do."""
    import cv2

    H, W = seeds.shape
    n, _, stats, _ = cv2.connectedComponentsWithStats(seeds.astype(np.uint8), connectivity=8)
    boxes = []
    for k in range(1, n):
        x, y, w, h = (int(v) for v in stats[k, :4])
        gy, gx = max(1, int(np.ceil(context * h))), max(1, int(np.ceil(context * w)))
        boxes.append([max(0, y - gy), min(H, y + h + gy), max(0, x - gx), min(W, x + w + gx)])
    merged = True
    while merged:
        merged = False
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                a, b = boxes[i], boxes[j]
                if a[0] < b[1] and b[0] < a[1] and a[2] < b[3] and b[2] < a[3]:
                    boxes[i] = [min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3])]
                    del boxes[j]
                    merged = True
                    break
            if merged:
                break
    return [tuple(b) for b in boxes]


@dataclasses.dataclass(frozen=True)
class WatershedRefiner:
    """scikit-image marker watershed on the gradients of gray, log depth and residual flow: markers are
    each region's eroded interior plus prompts and the background beyond a ``band_px`` ring."""

    band_px: int = 8
    core_px: int = 4
    depth_weight: float = 4.0
    residual_weight: float = 1.0

    def __call__(self, image, coarse, prompts, region_ids, hints: RefineHints = RefineHints()):
        import cv2
        from skimage.filters import sobel
        from skimage.segmentation import watershed

        coarse = np.asarray(coarse, bool)
        if not coarse.any():
            return coarse.copy()
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
        elev = sobel(gray)
        if hints.depth is not None:
            elev = elev + self.depth_weight * sobel(np.log(np.maximum(hints.depth, 1e-6)))
        if hints.residual is not None:
            elev = elev + self.residual_weight * sobel(np.log1p(np.maximum(hints.residual, 0.0)))
        n, labels = cv2.connectedComponents(coarse.astype(np.uint8), connectivity=8)
        markers = np.where(_erode(coarse, self.core_px), labels + 1, 0).astype(np.int32)
        for (u, v), k in zip(np.asarray(prompts).reshape(-1, 2), np.asarray(region_ids).reshape(-1)):
            markers[v, u] = k + 1
        markers[~_dilate(coarse, self.band_px)] = 1
        if not (markers == 1).any():
            return coarse.copy()
        return watershed(elev, markers) > 1


@dataclasses.dataclass(frozen=True)
class TrackConfig:
    """Tracking options. support_px: a warped mask survives within this distance of frame t's
    candidates; new_region_frac: an untracked candidate region this large (of H*W) triggers
    re-detection; prompts_per_region; seed; keep_seeded: the refiner's output keeps only its 8-connected
    regions that overlap the sure seeds (the tracked or detected mask less its background movers), so a
    colour match elsewhere in the frame (a red wall like the tracked shirt) does not start a new,
    untracked region that is then carried forward; check_added: on every frame after the first, pixels
    the refiner adds outside the sure seeds are dropped when, over the frame's own flow (t -> t+1), they
    move like the background around the refined mask and not like it (:func:`background_movers` at
    ``motion_k``): a neighbour of the object's colour that the band let in (a second camel, the fence
    behind it) is caught the frame it enters, before it is warped and tracked as the object. Off by
    default: for tracking from a prompt with no geometric cue (``davis_track.py``), where colour and
    motion are all the evidence; the pipeline's masks are bounded by the geometric cue, and there the
    check costs articulated and slow parts (docs/motion.md)."""

    support_px: int = 6
    grow: bool = True  # also seed with the candidate regions that overlap the tracked mask
    motion_split: bool = True  # seed pixels that move with the background around them are only probable
    motion_k: float = 3.0  # ... (:func:`background_movers` at k robust sigmas): the refiner decides by colour
    new_region_frac: float = 1e-3
    new_region_overlap: float = 0.2
    prompts_per_region: int = 8
    seed: int = 0
    keep_seeded: bool = True  # a refined mask keeps only its regions that hold a sure seed pixel
    check_added: bool = False  # pixels the refiner adds outside the sure seeds must not move like the background


def _affine_fit(uv, flow, iters: int = 5):
    """Robust affine motion model (2, 3) of flow (N, 2) at pixels uv (N, 2): IRLS with Cauchy weights
    at 2.385 x the residuals' robust scale. Returns (model, robust sigma of the inlier residual)."""
    X = np.concatenate([uv, np.ones((len(uv), 1))], 1)
    w = np.ones(len(uv))
    for _ in range(iters):
        A, *_ = np.linalg.lstsq(X * w[:, None], flow * w[:, None], rcond=None)
        r = np.linalg.norm(flow - X @ A, axis=1)
        sigma = max(1.4826 * np.median(r), 1e-3)
        w = 1.0 / np.sqrt(1.0 + (r / (2.385 * sigma)) ** 2)
    return A.T, sigma


def background_movers(mask: np.ndarray, flow: np.ndarray, k: float = 3.0, max_samples: int = 4000,
                      seed: int = 0) -> np.ndarray:
    """Pixels of ``mask`` (H, W) whose flow (H, W, 2) moves like the background around it, not like
    the object: a leak of the mask into the background (e.g. the area a mover uncovered).

    An affine motion model is fitted robustly to the flow on the mask and one on the ring around it
    (as wide as the object's radius); a mask pixel is a background mover when the ring's model
    explains it within ``k`` of its robust sigmas and better than the object's, where the two models
    predict motions more than ``k`` sigmas apart (where they agree, e.g. a camera following the
    object, the flow cannot tell).
    """
    mask = np.asarray(mask, bool)
    H, W = mask.shape
    area = int(mask.sum())
    out = np.zeros((H, W), bool)
    if area < 16:
        return out
    ring = _dilate(mask, max(2, int(np.sqrt(area / np.pi)))) & ~mask
    if ring.sum() < 16:
        return out
    rng = np.random.default_rng(seed)

    def fit(region):
        v, u = np.nonzero(region)
        idx = rng.choice(len(u), min(len(u), max_samples), replace=False)
        uv = np.stack([u[idx], v[idx]], 1).astype(np.float64)
        return _affine_fit(uv, flow[v[idx], u[idx]].astype(np.float64))

    (A_obj, _), (A_bg, s_bg) = fit(mask), fit(ring)
    v, u = np.nonzero(mask)
    X = np.stack([u, v, np.ones_like(u)], 1).astype(np.float64)
    f = flow[v, u].astype(np.float64)
    r_obj = np.linalg.norm(f - X @ A_obj.T, axis=1)
    r_bg = np.linalg.norm(f - X @ A_bg.T, axis=1)
    apart = np.linalg.norm(X @ (A_obj - A_bg).T, axis=1) > k * s_bg
    out[v, u] = (r_bg <= k * s_bg) & (r_bg < r_obj) & apart
    return out


def warp_mask(mask: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """Forward-warp a mask (H, W) of frame t to frame t+1 with the flow (H, W, 2): every set pixel is
    splatted to its rounded target (half to even) and the splat holes are closed (3x3 closing). The
    NumPy / OpenCV twin of :func:`cm3d.motion.warp_mask` (bitwise equal), with no program to compile."""
    import cv2

    mask = np.asarray(mask, bool)
    H, W = mask.shape
    v, u = np.nonzero(mask)
    f = np.asarray(flow, np.float32)[v, u]
    tu = np.round(u.astype(np.float32) + f[:, 0])
    tv = np.round(v.astype(np.float32) + f[:, 1])
    ok = (tu >= 0) & (tu < W) & (tv >= 0) & (tv < H)
    out = np.zeros((H, W), np.uint8)
    out[tv[ok].astype(np.intp), tu[ok].astype(np.intp)] = 1
    return cv2.morphologyEx(out, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)).astype(bool)


def new_motion(candidates: np.ndarray, tracked: np.ndarray, cfg: TrackConfig = TrackConfig()) -> np.ndarray:
    """Candidate regions (H, W) bool that the tracked mask does not explain: 8-connected regions of
    at least ``new_region_frac`` of the frame, less than ``new_region_overlap`` covered by it."""
    import cv2

    H, W = candidates.shape
    n, labels, stats, _ = cv2.connectedComponentsWithStats(candidates.astype(np.uint8), connectivity=8)
    out = np.zeros((H, W), bool)
    for k in range(1, n):
        if stats[k, cv2.CC_STAT_AREA] < cfg.new_region_frac * H * W:
            continue
        region = labels == k
        if (region & tracked).sum() < cfg.new_region_overlap * region.sum():
            out |= region
    return out


def overlapping(candidates: np.ndarray, tracked: np.ndarray) -> np.ndarray:
    """The 8-connected regions of ``candidates`` (H, W) that touch ``tracked`` (continuing objects)."""
    import cv2

    n, labels = cv2.connectedComponents(candidates.astype(np.uint8), connectivity=8)
    hit = np.zeros(n, bool)
    hit[np.unique(labels[tracked & candidates])] = True
    hit[0] = False
    return hit[labels]


class MaskTracker:
    """:func:`refine_and_track` one frame at a time, for callers that get the frames as they come (the
    pipeline refines each piece of a sequence while the device runs the next). Host state: the previous
    frame's refined mask. ``step`` over frames 0, 1, ... gives exactly :func:`refine_and_track`'s masks.
    GrabCut's colour models start from OpenCV's random generator, one per thread, whose state is whatever
    the thread's earlier OpenCV calls left: ``rng_seed`` (not None) seeds it (``cv2.setRNGSeed``) in the
    thread that runs the first step, so the masks do not depend on the process's history."""

    def __init__(self, refiner: MaskRefiner | None = None, cfg: TrackConfig = TrackConfig(),
                 rng_seed: int | None = None):
        self.refiner = refiner or GrabCutRefiner()
        self.cfg = cfg
        self.rng_seed = rng_seed
        self.prev = None

    def step(self, t: int, image: np.ndarray, candidate: np.ndarray, detect: Callable[[int], np.ndarray],
             flow_in: np.ndarray | None, flow_out: np.ndarray, hints: RefineHints = RefineHints()):
        """Frame ``t``: image (H, W, 3) uint8, candidate (H, W) bool, ``detect(t)`` its detection mask
        (called only when needed), flow_in (H, W, 2) t-1 -> t (unused on the first frame), flow_out t -> t+1
        (read by ``cfg.check_added`` only); ``hints``' depth / residual are passed to the refiner.
        Returns (refined mask (H, W) bool, detected)."""
        cfg, prev = self.cfg, self.prev
        if prev is None and self.rng_seed is not None:
            import cv2

            cv2.setRNGSeed(int(self.rng_seed))
        cand = np.asarray(candidate, bool)
        uncertain = None
        if prev is None:
            seed_mask = np.asarray(detect(t), bool)
            detected = True
        else:
            detected = False
            warped = warp_mask(prev, flow_in)
            if cfg.motion_split:
                movers = background_movers(prev, flow_in, cfg.motion_k, seed=cfg.seed + t)
                uncertain = warp_mask(movers, flow_in) if movers.any() else None
            tracked = warped & _dilate(cand, cfg.support_px)
            if cfg.grow:
                tracked = tracked | overlapping(cand, tracked)
            fresh = new_motion(cand, tracked, cfg)
            if fresh.any():
                detected = True
                seed_mask = tracked | (np.asarray(detect(t), bool) & fresh)
            else:
                seed_mask = tracked
        sure = seed_mask if uncertain is None else seed_mask & ~uncertain
        prompts, ids, _ = sample_prompts(sure, cfg.prompts_per_region, cfg.seed + t)
        hints = dataclasses.replace(hints, uncertain=uncertain)
        refined = np.asarray(self.refiner(image, seed_mask, prompts, ids, hints), bool)
        if cfg.keep_seeded:
            refined = overlapping(refined, sure)
        if cfg.check_added and prev is not None:  # the first frame is the detector's say
            added = refined & ~sure
            if added.any():
                refined &= ~(added & background_movers(refined, flow_out, cfg.motion_k, seed=cfg.seed + t))
                if cfg.keep_seeded:
                    refined = overlapping(refined, sure)
        self.prev = refined
        return refined, detected


def refine_and_track(images: np.ndarray, flows: np.ndarray, candidates: np.ndarray,
                     detect: Callable[[int], np.ndarray], refiner: MaskRefiner | None = None,
                     depth: np.ndarray | None = None, residual: np.ndarray | None = None,
                     cfg: TrackConfig = TrackConfig(), rng_seed: int | None = None):
    """Refined and tracked dynamic masks of frames 0..T-1 (T = len(flows)).

    images (>= T, H, W, 3) uint8; flows (T, H, W, 2) t -> t+1; candidates (T, H, W) bool; ``detect(t)``
    returns frame t's detection mask (called only when needed); depth / residual: optional hints;
    rng_seed: see :class:`MaskTracker` (None: OpenCV's generator as the calling thread left it).
    Returns (masks (T, H, W) bool, detected (T,) bool).
    """
    tracker = MaskTracker(refiner, cfg, rng_seed)
    T = len(flows)
    H, W = candidates.shape[1:]
    masks = np.zeros((T, H, W), bool)
    detected = np.zeros(T, bool)
    for t in range(T):
        hints = RefineHints(None if depth is None else depth[t], None if residual is None else residual[t])
        masks[t], detected[t] = tracker.step(t, images[t], candidates[t], detect, flows[t - 1] if t else None,
                                             flows[t], hints)
    return masks, detected


def refine_sequence(images: np.ndarray, flows: np.ndarray, masks: np.ndarray, refiner: MaskRefiner | None = None,
                    cfg: TrackConfig = TrackConfig(), rng_seed: int | None = 0) -> np.ndarray:
    """The motion cue's dynamic masks (S, H, W) bool of a sequence, refined and tracked
    (:func:`refine_and_track` with the masks as both the candidates and the detections).

    images (S, H, W, 3) uint8; flows (>= S-1, H, W, 2), flow t -> t+1 for t < S-1. A frame whose cue
    found nothing stays empty (a tracked mask needs the cue's support within ``cfg.support_px``), so a
    static scene's empty masks stay empty. ``rng_seed``: OpenCV's generator seeded at the first frame
    (:class:`MaskTracker`; default 0, the state of a fresh thread), so a sequence's masks do not depend on
    what ran before it in the process. Returns (S, H, W) bool.
    """
    masks, images = np.asarray(masks, bool), np.asarray(images)
    S = len(masks)
    if S == 0 or not masks.any():
        return masks.copy()
    flows = np.asarray(flows)
    if len(flows) < S - 1 or flows.shape[1:3] != masks.shape[1:] or images.shape[1:3] != masks.shape[1:]:
        raise ValueError(f"refine_sequence: images {images.shape}, flows {flows.shape} and masks {masks.shape} "
                         "must share (H, W), with a flow for each frame but the last")
    # flows[t - 1] warps frame t's seed; flows[t] is read only by ``cfg.check_added``: frame S-1's slot is zeros
    flows = np.concatenate([flows[:S - 1], np.zeros((1,) + flows.shape[1:], flows.dtype)])
    out, _ = refine_and_track(images, flows, masks, lambda t: masks[t], refiner, cfg=cfg, rng_seed=rng_seed)
    return out
