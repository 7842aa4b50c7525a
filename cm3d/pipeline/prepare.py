"""Host-side work before the compiled step: OpenCV flow, keypoints, ``1 / stride``, padding."""

from __future__ import annotations

from typing import Any

import jax
import numpy as np
from flax import struct

from cm3d.motion import FramePrior, SecondPair
from cm3d.ops.keypoints import Matches
from cm3d.pipeline.config import PipelineConfig


@struct.dataclass
class Features:
    """Detected keypoints of a frame for the memory: uv (n, 2) reduced-resolution pixels, desc
    (n, D) unit descriptors, valid (n,)."""

    uv: Any
    desc: Any
    valid: Any


@struct.dataclass
class Inputs:
    """Per-frame inputs, with a leading frame axis ``S`` for a sequence (everything at reduced
    resolution ``h x w``): frame and partner priors (partner = t+1, t-1 for the last frame), flow
    (h, w, 2) and keypoint matches frame -> partner, flow_rev (partner -> frame, the occlusion
    check), the second partner t-1 (:class:`~cm3d.motion.SecondPair`; invalid for the first and last
    frames), memory features, valid (padding frames are False), last (the sequence's last real
    frame), index (frame number)."""

    frame: FramePrior
    partner: FramePrior
    flow: Any
    flow_rev: Any
    second: SecondPair
    matches: Matches
    features: Features
    valid: Any
    last: Any
    index: Any

    @property
    def num_frames(self) -> int:
        return int(self.valid.shape[0])


def _shrink(img: np.ndarray, s: int) -> np.ndarray:
    """Every s-th pixel (keeps pixel centres aligned with ``K / s``)."""
    return img[:, ::s, ::s] if s > 1 else img


def scale_intrinsics(K: np.ndarray, s: int) -> np.ndarray:
    """Intrinsics of the every-``s``-th-pixel grid: pixel (u, v) there is (s u, s v) in full."""
    K = np.array(K, np.float64, copy=True)
    K[..., :2, :] /= s
    return K


def padded_length(num_frames: int, cfg: PipelineConfig) -> int:
    """Frames after padding to a whole number of windows (one compiled program per size)."""
    n = cfg.keyframe_interval
    return max(n, -(-num_frames // n) * n)


def _front_end(images: np.ndarray, partner: np.ndarray, cfg: PipelineConfig, flow=None, progress=None):
    """OpenCV flow (S, H, W, 2) of every frame to its partner and back, and keypoint matches."""
    from cm3d.ops import flow as oflow
    from cm3d.ops import keypoints as okp

    S, H, W = images.shape[:3]
    flows = np.zeros((S, H, W, 2), np.float32)
    back = np.zeros((S, H, W, 2), np.float32)
    uv0 = np.zeros((S, cfg.keypoints.max_matches, 2), np.float32)
    uv1 = np.zeros_like(uv0)
    mvalid = np.zeros((S, cfg.keypoints.max_matches), bool)
    for t in range(S):
        p = partner[t]
        if p == t + 1:  # the last frame's pair (S-1, S-2) is the pair (S-2, S-1) reversed
            flows[t] = flow[t] if flow is not None else oflow.compute_flow(images[t], images[p], cfg.flow)
            back[t] = oflow.compute_flow(images[p], images[t], cfg.flow)
        else:
            flows[t], back[t] = back[p], flows[p]
        m = okp.match_keypoints(images[t], images[p], cfg.keypoints)
        uv0[t], uv1[t], mvalid[t] = m.uv0, m.uv1, m.valid
        if progress is not None:
            progress(t + 1, S)
    return flows, back, Matches(uv0, uv1, mvalid)


def prepare(sequence, cfg: PipelineConfig = PipelineConfig(), flow=None, progress=None) -> Inputs:
    """Numpy :class:`Inputs` of a :class:`cm3d.data.Sequence`: flow and keypoint matches with each
    frame's partner, keypoint features, 1/stride, padding to :func:`padded_length`. ``flow``: optional
    precomputed forward flow (S-1, H, W, 2); ``progress``: optional ``(done, total)`` per frame."""
    from cm3d.ops import keypoints as okp

    S, H, W = sequence.depth.shape
    if S < 2:
        raise ValueError(f"sequence: needs at least 2 frames, got {S}")
    s = cfg.stride
    if H // s < 2 * cfg.track.cell or W // s < 2 * cfg.track.cell:
        raise ValueError(f"sequence: images of {H}x{W} are too small for landmark cells of "
                         f"{cfg.track.cell * s} px")
    images = np.asarray(sequence.images)
    partner = np.concatenate([np.arange(1, S), [S - 2]])
    flows, back, m = _front_end(images, partner, cfg, flow, progress)
    feats = okp.detect_sequence(images, None, cfg.feature_capacity, cfg.keypoints)

    K = scale_intrinsics(sequence.intrinsic, s).astype(np.float32)
    img_s = _shrink(images, s)
    depth = _shrink(np.asarray(sequence.depth, np.float32), s)
    conf = _shrink(np.asarray(sequence.depth_conf, np.float32), s)
    c2w = np.asarray(sequence.cam_to_world, np.float32)
    frame = FramePrior(image=img_s, depth=depth, depth_conf=conf, intrinsic=K, cam_to_world=c2w)
    part = FramePrior(image=img_s[partner], depth=depth[partner], depth_conf=conf[partner],
                      intrinsic=K[partner], cam_to_world=c2w[partner])
    features = Features(np.asarray(feats.uv / s, np.float32), np.asarray(feats.desc, np.float32), feats.valid)
    flow_s, back_s = _shrink(flows, s) / s, _shrink(back, s) / s
    prev = np.maximum(np.arange(S) - 1, 0)
    second = SecondPair(partner=jax.tree.map(lambda a: a[prev], frame), flow=back_s[prev], flow_rev=flow_s[prev],
                        valid=(np.arange(S) >= 1) & (np.arange(S) < S - 1))
    inputs = Inputs(frame=frame, partner=part, flow=flow_s, flow_rev=back_s, second=second,
                    matches=Matches(m.uv0 / s, m.uv1 / s, m.valid), features=features,
                    valid=np.ones(S, bool), last=np.arange(S) == S - 1, index=np.arange(S, dtype=np.int32))
    return pad_inputs(inputs, padded_length(S, cfg))


def pad_inputs(inputs: Inputs, length: int) -> Inputs:
    """Pad every per-frame array to ``length`` frames by repeating the last one (marked invalid)."""
    S = inputs.num_frames
    if length < S:
        raise ValueError(f"pad_inputs: length {length} < {S} frames")
    idx = np.minimum(np.arange(length), S - 1)
    out = jax.tree.map(lambda a: np.asarray(a)[idx], inputs)
    keep = np.arange(length) < S
    return out.replace(valid=out.valid & keep, last=out.last & keep)
