"""What an input can support, checked before any work (host, numpy): inputs the pipeline cannot
refine (random or featureless images, no usable depth, a camera that does not move), the frame count,
and sensor holes (pixels with no depth), which :func:`fill_depth_holes` fills for the motion cues and
the tracks while their confidence stays 0 (nothing is ever lifted from a filled depth).

The thresholds sit far from every real and synthetic input measured (docs/reliability.md): the
lag-1 correlation of neighbouring grey values is 0.44-0.99 on synthetic (48x64 and up), 7-Scenes,
DAVIS, TUM and KITTI frames and 0.00 +- 0.02 on noise; the share of pixels with a grey gradient
above 8 levels is 0.14-0.75 on them and 0 on a flat image.
"""

from __future__ import annotations

import dataclasses

import numpy as np

MIN_NEIGHBOUR_CORRELATION = 0.2  # median over frames; below: the images look like random noise
MIN_TEXTURED_SHARE = 0.01  # share of pixels with a grey gradient above TEXTURE_LEVELS; below: featureless
TEXTURE_LEVELS = 8.0  # grey levels (0-255)
ASSESSED_FRAMES = 16  # the image statistics' medians are taken over at most this many evenly spaced frames
MIN_USABLE_DEPTH_SHARE = 0.02  # share of pixels with depth > 0 and confidence > 0
STILL_TRANSLATION = 1e-3  # camera centres within this share of the median depth ...
STILL_ROTATION_DEG = 0.05  # ... and orientations within this angle: the camera does not move


def check_runnable(seq, source: str) -> None:
    """``ValueError`` naming ``source`` when the pipeline cannot run ``seq`` at all (fewer than 2 frames)."""
    if seq.num_frames < 2:
        raise ValueError(f"{source}: {seq.num_frames} frame; the pipeline needs at least 2 frames")


@dataclasses.dataclass(frozen=True)
class InputQuality:
    """Facts about an input: the correlation of neighbouring grey values and the share of textured
    pixels (medians over at most :data:`ASSESSED_FRAMES` evenly spaced frames), the share of pixels
    with usable depth, the prior camera's largest move (share of the median depth) and turn
    (degrees), the share of sensor holes; ``problems``: one sentence per reason the pipeline cannot
    refine this input (empty: it can)."""

    neighbour_correlation: float
    textured_share: float
    usable_depth_share: float
    camera_translation: float
    camera_rotation_deg: float
    hole_share: float
    problems: tuple = ()

    @property
    def degenerate(self) -> bool:
        return bool(self.problems)

    def to_json(self) -> dict:
        return {**{k: round(v, 6) for k, v in dataclasses.asdict(self).items() if k != "problems"},
                "problems": list(self.problems)}


def grey_levels(images) -> np.ndarray:
    """(..., H, W) float64 channel means of images (..., H, W, C). Of uint8 RGB images: the exact integer
    sum of the three channels over 3 (the same values as a float64 mean), one frame at a time (a reduction
    over a last axis of three is slow in NumPy, and no float64 copy of every channel: 6x faster at 480x640)."""
    images = np.asarray(images)
    if images.dtype != np.uint8 or images.shape[-1] != 3:
        return images.astype(np.float64).mean(-1)
    if images.ndim > 3:
        out = np.empty(images.shape[:-1], np.float64)
        for i in np.ndindex(images.shape[:-3]):
            out[i] = grey_levels(images[i])
        return out
    return (images[..., 0].astype(np.uint16) + images[..., 1] + images[..., 2]) / 3


def _frame_correlation(g: np.ndarray) -> float:
    def corr(a, b):
        a = a - a.mean()
        b = b - b.mean()
        d = np.sqrt((a * a).sum() * (b * b).sum())
        return (a * b).sum() / d if d > 0 else 1.0

    return 0.5 * (corr(g[:, :-1], g[:, 1:]) + corr(g[:-1], g[1:]))


def _frame_textured_share(g: np.ndarray) -> float:
    gx = np.diff(g, axis=1)[:-1]
    gy = np.diff(g, axis=0)[:, :-1]
    return (gx * gx + gy * gy > TEXTURE_LEVELS**2).mean()


def neighbour_correlation(grey: np.ndarray) -> np.ndarray:
    """Per frame (S,): the correlation of horizontally and of vertically neighbouring grey values,
    averaged (1 for a constant frame). One frame at a time (its temporaries stay in cache)."""
    return np.array([_frame_correlation(g) for g in grey], np.float64)


def textured_share(grey: np.ndarray) -> np.ndarray:
    """Per frame (S,): share of pixels whose grey gradient (forward differences) exceeds TEXTURE_LEVELS
    (compared squared: no square root per pixel). One frame at a time (10x faster than on the stack at
    480x640: the differences stay in cache)."""
    return np.array([_frame_textured_share(g) for g in grey], np.float64)


def depth_holes(seq) -> np.ndarray:
    """(S, H, W) bool: pixels with no depth measurement (depth 0, negative or non-finite)."""
    d = np.asarray(seq.depth)
    return ~(np.isfinite(d) & (d > 0))


def camera_motion(cam_to_world, depth) -> tuple[float, float]:
    """The prior camera's largest distance from its first centre (share of the median positive depth)
    and its largest turn from the first orientation (degrees)."""
    T = np.asarray(cam_to_world, np.float64)
    d = np.asarray(depth)
    scale = float(np.median(d[np.isfinite(d) & (d > 0)])) if np.any(d > 0) else 1.0
    move = float(np.linalg.norm(T[:, :3, 3] - T[:1, :3, 3], axis=-1).max()) / max(scale, 1e-12)
    R = np.einsum("ji,njk->nik", T[0, :3, :3], T[:, :3, :3])
    cos = np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return move, float(np.degrees(np.arccos(cos)).max())


def assess_input(seq) -> InputQuality:
    """:class:`InputQuality` of a sequence: is there anything to refine?"""
    stats = []
    images = np.asarray(seq.images)
    # a median over evenly spaced frames (a 120-frame 480x640 input: 1.9 s for every frame, beside the hole
    # filling; a degenerate input is so in most of its frames, and these are medians)
    picked = np.unique(np.linspace(0, len(images) - 1, min(len(images), ASSESSED_FRAMES)).round().astype(int))
    for image in images[picked]:  # a frame's grey values at a time (in cache; no float64 stack)
        g = grey_levels(image)
        stats.append((_frame_correlation(g), _frame_textured_share(g)))
    r, tex = (float(np.median(x)) for x in zip(*stats))
    d, c = np.asarray(seq.depth), np.asarray(seq.depth_conf)
    usable = float(np.mean(np.isfinite(d) & (d > 0) & (c > 0)))
    move, turn = camera_motion(seq.cam_to_world, d)
    problems = []
    if tex < MIN_TEXTURED_SHARE:
        problems.append(f"featureless images: {100 * tex:.2f} % of pixels have any texture "
                        f"(grey gradient > {TEXTURE_LEVELS:g}; at least {100 * MIN_TEXTURED_SHARE:g} % needed)")
    elif r < MIN_NEIGHBOUR_CORRELATION:
        problems.append(f"the images look like random noise: neighbouring pixels correlate r = {r:.3f} "
                        f"(real and rendered frames: 0.44-0.99; at least {MIN_NEIGHBOUR_CORRELATION:g} needed)")
    if usable < MIN_USABLE_DEPTH_SHARE:
        problems.append(f"no usable depth: {100 * usable:.2f} % of pixels have depth > 0 and confidence > 0 "
                        f"(at least {100 * MIN_USABLE_DEPTH_SHARE:g} % needed)")
    if move < STILL_TRANSLATION and turn < STILL_ROTATION_DEG:
        problems.append(f"the camera does not move: its prior poses stay within {move:.2g} of the median depth "
                        f"and {turn:.3f} deg of the first frame")
    return InputQuality(neighbour_correlation=r, textured_share=tex, usable_depth_share=usable,
                        camera_translation=move, camera_rotation_deg=turn,
                        hole_share=float(depth_holes(seq).mean()), problems=tuple(problems))


def fill_depth_holes(seq):
    """``seq`` with every hole (:func:`depth_holes`) given the depth of its nearest measured pixel in the
    same frame and confidence 0 (the sequence itself when it has no hole). The motion cues and the
    tracks then see a continuous depth; seeds and map points need confidence > 0, so none comes
    from a filled pixel."""
    from scipy import ndimage

    holes = depth_holes(seq)
    if not holes.any():
        return seq
    d = np.array(seq.depth, np.float32)
    for t in np.flatnonzero(holes.reshape(len(d), -1).any(1)):
        idx = ndimage.distance_transform_edt(holes[t], return_distances=False, return_indices=True)
        h = holes[t]  # only the holes change: gathered there alone (2.2x faster at 480x640)
        d[t][h] = d[t][idx[0][h], idx[1][h]]
    conf = np.where(holes, 0.0, np.asarray(seq.depth_conf)).astype(np.asarray(seq.depth_conf).dtype)
    return seq.replace(depth=d, depth_conf=conf)
