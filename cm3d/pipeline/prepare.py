"""Host-side work before the compiled step: OpenCV flow, keypoints, ``1 / stride``, padding."""

from __future__ import annotations

import dataclasses
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


def _check_sequence(sequence, cfg: PipelineConfig) -> None:
    S, H, W = sequence.depth.shape
    if S < 2:
        raise ValueError(f"sequence: needs at least 2 frames, got {S}")
    s = cfg.stride
    if H // s < 2 * cfg.track.cell or W // s < 2 * cfg.track.cell:
        raise ValueError(f"sequence: images of {H}x{W} are too small for landmark cells of "
                         f"{cfg.track.cell * s} px")


def match_config(cfg: PipelineConfig):
    """The detector of the cue's matches with ``cfg.match_reduced`` (:func:`cm3d.ops.keypoints.detect_reduced`
    by ``cfg.stride``): ``cfg.keypoints`` at contrast ``match_contrast``."""
    kp = cfg.keypoints
    return dataclasses.replace(kp, contrast_threshold=kp.match_contrast or kp.contrast_threshold, match_contrast=None)


def prepare_chunks(sequence, cfg: PipelineConfig = PipelineConfig(), flow=None, progress=None,
                   size: int | None = None):
    """:func:`prepare` in pieces: yields ``(first frame, Inputs of size frames)`` for frames
    ``0, size, 2 size, ...`` of the padded sequence (``size``: default ``keyframe_interval``, which
    divides :func:`padded_length`), so that the caller can run one piece while the next is prepared.
    Each frame's OpenCV work is done once: its flow pair with its partner (t+1; the last frame reuses
    the pair before it, reversed), one keypoint detection for the matches of the pairs it is in and, on
    every ``cfg.feature_every``-th frame, one at full resolution for its memory features (the same one
    when the matches use full resolution). Concatenated, the pieces are :func:`prepare`'s arrays."""
    from cm3d.ops import flow as oflow
    from cm3d.ops import keypoints as okp

    _check_sequence(sequence, cfg)
    S = sequence.depth.shape[0]
    s = cfg.stride
    size = cfg.keyframe_interval if size is None else int(size)
    L = padded_length(S, cfg)
    if size < 1 or L % size:
        raise ValueError(f"size: must divide the padded length {L}, got {size}")
    images = np.asarray(sequence.images)
    partner = np.concatenate([np.arange(1, S), [S - 2]])
    K = scale_intrinsics(sequence.intrinsic, s).astype(np.float32)
    img_s = _shrink(images, s)
    depth = _shrink(np.asarray(sequence.depth, np.float32), s)
    conf = _shrink(np.asarray(sequence.depth_conf, np.float32), s)
    c2w = np.asarray(sequence.cam_to_world, np.float32)
    frame = FramePrior(image=img_s, depth=depth, depth_conf=conf, intrinsic=K, cam_to_world=c2w)
    kp = cfg.keypoints
    reduced = cfg.match_reduced and s > 1  # at stride 1 the full-resolution detection is the cue's resolution
    match_kp = match_config(cfg)
    dets, match_dets, pairs, per_frame = {}, {}, {}, {}
    no_features = okp.features_from(((), None), cfg.feature_capacity, kp)

    def detection(t):
        """Frame t's full-resolution detection (the memory's features; the cue's matches without ``reduced``)."""
        if t not in dets:
            dets[t] = okp.detect(images[t], kp)
        return dets[t]

    def match_detection(t):
        """Frame t's keypoints for the cue's matches."""
        if not reduced:
            return detection(t)
        if t not in match_dets:
            match_dets[t] = okp.detect_reduced(images[t], match_kp, s)
        return match_dets[t]

    def pair(t):
        """(flow, flow_rev) of frame t with its partner at reduced resolution."""
        if t not in pairs:
            p = partner[t]
            if p == t + 1:
                fwd = np.asarray(flow[t] if flow is not None else oflow.compute_flow(images[t], images[p], cfg.flow),
                                 np.float32)
                bwd = oflow.compute_flow(images[p], images[t], cfg.flow)
                pairs[t] = (_shrink(fwd[None], s)[0] / s, _shrink(bwd[None], s)[0] / s)
            else:  # the last frame's pair (S-1, S-2) is the pair (S-2, S-1) reversed
                pairs[t] = pair(p)[::-1]
        return pairs[t]

    for a in range(0, L, size):
        real = range(a, min(a + size, S))
        for t in real:
            m = okp.match_detections(match_detection(t), match_detection(partner[t]), match_kp if reduced else kp)
            f = okp.features_from(detection(t), cfg.feature_capacity, kp) if t % cfg.feature_every == 0 \
                else no_features
            fl, fr = pair(t)
            per_frame[t] = (fl, fr, m, f)
            if progress is not None:
                progress(t + 1, S)
        idx = np.minimum(np.arange(a, a + size), S - 1)
        prev = np.maximum(idx - 1, 0)
        flow_s = np.stack([per_frame[t][0] for t in idx]).astype(np.float32)
        back_s = np.stack([per_frame[t][1] for t in idx]).astype(np.float32)
        pick = lambda k, field: np.stack([getattr(per_frame[t][k], field) for t in idx])  # noqa: E731
        at = lambda i: jax.tree.map(lambda x: x[i], frame)  # noqa: E731
        second = SecondPair(partner=at(prev), flow=np.stack([pair(t)[1] for t in prev]).astype(np.float32),
                            flow_rev=np.stack([pair(t)[0] for t in prev]).astype(np.float32),
                            valid=(idx >= 1) & (idx < S - 1))
        keep = np.arange(a, a + size) < S
        yield a, Inputs(frame=at(idx), partner=at(partner[idx]), flow=flow_s, flow_rev=back_s, second=second,
                        matches=Matches(pick(2, "uv0") / s, pick(2, "uv1") / s, pick(2, "valid")),
                        features=Features(np.asarray(pick(3, "uv") / s, np.float32), pick(3, "desc"),
                                          pick(3, "valid")),
                        valid=keep, last=(idx == S - 1) & keep, index=idx.astype(np.int32))
        last_needed = min(a + size, S) - 1  # the next piece's first frame needs this one's pair
        for t in [t for t in per_frame if t < last_needed]:
            del per_frame[t]
        for t in [t for t in pairs if t < last_needed and t != S - 2]:
            del pairs[t]
        for cache in (dets, match_dets):
            for t in [t for t in cache if t < last_needed]:
                del cache[t]


def piece_spec(sequence, cfg: PipelineConfig = PipelineConfig(), size: int | None = None) -> Inputs:
    """The shapes and dtypes (``jax.ShapeDtypeStruct``) of one :func:`prepare_chunks` piece of
    ``sequence`` as device arrays, known before any OpenCV work (to load its program meanwhile)."""
    from cm3d.ops.keypoints import DESCRIPTOR_DIM

    n = cfg.keyframe_interval if size is None else int(size)
    _, H, W = sequence.depth.shape
    s = cfg.stride
    h, w = -(-H // s), -(-W // s)
    img = np.asarray(sequence.images)
    sd = jax.ShapeDtypeStruct
    f32 = np.dtype(np.float32)
    fp = FramePrior(image=sd((n, h, w) + img.shape[3:], img.dtype), depth=sd((n, h, w), f32),
                    depth_conf=sd((n, h, w), f32), intrinsic=sd((n, 3, 3), f32), cam_to_world=sd((n, 4, 4), f32))
    flow = sd((n, h, w, 2), f32)
    M, C, D = cfg.keypoints.max_matches, cfg.feature_capacity, DESCRIPTOR_DIM[cfg.keypoints.detector]
    b = np.dtype(bool)
    return Inputs(frame=fp, partner=fp, flow=flow, flow_rev=flow,
                  second=SecondPair(partner=fp, flow=flow, flow_rev=flow, valid=sd((n,), b)),
                  matches=Matches(sd((n, M, 2), f32), sd((n, M, 2), f32), sd((n, M), b)),
                  features=Features(sd((n, C, 2), f32), sd((n, C, D), f32), sd((n, C), b)),
                  valid=sd((n,), b), last=sd((n,), b), index=sd((n,), np.dtype(np.int32)))


def prepare(sequence, cfg: PipelineConfig = PipelineConfig(), flow=None, progress=None) -> Inputs:
    """Numpy :class:`Inputs` of a :class:`cm3d.data.Sequence`: flow and keypoint matches with each
    frame's partner, keypoint features, 1/stride, padding to :func:`padded_length`. ``flow``: optional
    precomputed forward flow (S-1, H, W, 2); ``progress``: optional ``(done, total)`` per frame."""
    pieces = [x for _, x in prepare_chunks(sequence, cfg, flow, progress)]
    return jax.tree.map(lambda *a: np.concatenate(a), *pieces)


def pad_inputs(inputs: Inputs, length: int) -> Inputs:
    """Pad every per-frame array to ``length`` frames by repeating the last one (marked invalid)."""
    S = inputs.num_frames
    if length < S:
        raise ValueError(f"pad_inputs: length {length} < {S} frames")
    idx = np.minimum(np.arange(length), S - 1)
    out = jax.tree.map(lambda a: np.asarray(a)[idx], inputs)
    keep = np.arange(length) < S
    return out.replace(valid=out.valid & keep, last=out.last & keep)
