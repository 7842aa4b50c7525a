"""The CogniMap3D pipeline as one pure step function (paper, Fig. 2).

Data flow: ``prepare`` (host: OpenCV flow, keypoint matches and features, resampling into fixed-shape
arrays) -> ``step`` (jit, ``lax.scan`` over frames) -> :func:`collect` (host: per-frame results)
-> :mod:`cm3d.outputs` writers. Per frame ``step`` runs, in the paper's order:

1. **motion cues** (:func:`cm3d.motion.motion_cues` on the pair (t, t+1); the last frame pairs
   with t-1): the dynamic mask, its complement is the static scene;
2. **static landmarks**: every ``track.keyframe_every`` window slots the most confident static
   pixel of each cell is seeded and lifted with the prior depth; live landmarks are followed by
   the flow into the current frame (:mod:`cm3d.trajectory`'s landmark rules, one frame at a time);
3. every ``keyframe_interval`` frames (and at the sequence end), inside one ``lax.cond``
   (:func:`window_end`): the **factor graph** over the window without memory
   (:func:`cm3d.trajectory.refine_trajectory`, gated); **recall / verify** the window's static cloud,
   keyframe descriptors and 3D keypoints, posed by those refined poses and merged with what the
   sequence stored so far, against the bank's *other* maps (:func:`cm3d.memory.identify`); the
   **factor graph with memory** from the memory-free optimum (landmarks within
   ``τ = max(τ_min, d_scene · α)`` of the recalled map's surface (an earlier sequence's map; the
   sequence's own stored map only with ``own_map_landmarks``) get a point-to-plane prior whose std
   is the larger of the configured one and the landmarks' measured spread about the surface;
   projection covariance scaled by ``α_mem``), kept only when it agrees with the window's own
   observations (a χ² test: memory never makes a window worse than the window alone can tell);
   **update** the bank with the final window (merge into the recalled map or the sequence's own,
   or store a new one; stray voxels dropped: ``map_min_support``).

Windows: window ``k`` holds ``keyframe_interval + 1`` pose slots; slot 0 is the *anchor*, the last
frame of the previous window with its refined pose (held by the graph's tight prior on pose 0),
so consecutive windows chain without a gap. Priors of later frames are carried into the refined
frame by the anchor: ``T_init(t) = T_ref(anchor) T_prior(anchor)^-1 T_prior(t)``.

Resolution: cues, landmarks, descriptors and the memory cloud run at ``1 / stride`` of the input
resolution (default 2: 192x256 for 384x512 input, 4x less work for the same mask IoU); intrinsics
are scaled to match, so poses and landmarks are unchanged and reprojection noise is ``σ / stride``.
Masks are upsampled back to the input resolution by :func:`collect`.

Everything in the step has fixed shapes (capacities and validity masks); shape-affecting options
are fields of the frozen :class:`PipelineConfig`, passed as a static argument, so a sequence of a
given (padded) length and image size compiles once and a second one reuses the program. Sequences
are padded to a multiple of ``keyframe_interval`` (invalid frames leave the state unchanged).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from cm3d import memory, trajectory
from cm3d.motion import FramePrior, MotionConfig, motion_cues, moving_tracks
from cm3d.ops import descriptors, robust, se3
from cm3d.ops.flow import FlowConfig
from cm3d.ops.gmm import GMMConfig
from cm3d.ops.keypoints import KeypointConfig, Matches
from cm3d.solvers import factors, lm

# ----------------------------------------------------------------------------------------------
# Configuration


@dataclasses.dataclass(frozen=True)
class TrackCheckConfig:
    """Landmark tracks checked against the prior geometry before the window's factor graph.

    A track's *transfer error* is the RMS distance between its tracked pixels and its seed pixel
    lifted with the prior depth and moved by the prior poses (reduced-resolution px). A track is
    dropped when that error exceeds ``max(min_px, median + n_mad · 1.4826 · MAD)`` of the window's
    tracks: with (near-)exact priors the tracks on moving objects that the estimated mask missed
    stand out (0.2–1 px against 0.03–0.1 px on static surfaces at 96x128); with noisy priors every
    track has a large transfer error and only the tail is dropped. enabled: run the check."""

    enabled: bool = True
    n_mad: float = 3.0
    min_px: float = 0.1

    def __post_init__(self):
        if not self.n_mad > 0 or not self.min_px >= 0:
            raise ValueError(f"TrackCheckConfig: n_mad > 0 and min_px >= 0 required, got {self.n_mad}, {self.min_px}")


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """All options of the pipeline (hashable, a static argument of the compiled step).

    keyframe_interval: frames per memory / factor-graph batch (paper: 20); stride: cues, landmarks
    and memory run at 1/stride resolution; motion: the motion-cue options (GMM with 10 EM
    iterations: the flow cue only feeds the ``union`` / ``intersection`` candidate modes);
    track: landmark cells and tracks (in reduced-resolution pixels); assoc: the memory association
    threshold; refine: the factor graph (pixel noise in reduced-resolution pixels; its gate is run by
    :func:`gate_refinement`); track_check: tracks checked against the prior geometry before the
    graph (:class:`TrackCheckConfig`); memory: bank
    capacities and recall thresholds (used for a new bank; a loaded bank brings its own);
    use_memory: recall / verify / update at all; own_map_landmarks: until a stored map is recalled, a
    window's memory landmarks come from the map its own sequence stored (:func:`window_end`). Off by
    default: that map is built from the same kind of prior depth as the window, so the window's χ²
    test cannot tell whether it helps, and measured at 384x512 it moved revisits either way (camera
    pose, scenes 1 / 2: ATE 0.00226 -> 0.00272 / 0.00229 -> 0.00223; first visits 1-4 % lower);
    without it a sequence that recalls nothing keeps exactly its memory-free poses;
    min_memory_landmarks: fewest landmarks on the remembered surface for the memory solution to be
    used (a handful hardly constrains six degrees of freedom per frame, and their spread is no
    measurement); memory_sigma_voxels: the point-to-plane priors' std is at least this many map
    voxels (:func:`memory_refinement`); map_min_support: a window stored or merged into the bank
    drops its voxels with fewer samples than this share of the median voxel's
    (:func:`cm3d.memory.build_entry`: stray points weigh as much as surface in a capacity-bound map;
    the query that identifies keeps them);
    keyframe_threshold: descriptor distance between
    memory keyframes; feature_capacity: 3D keypoints per frame offered to the memory;
    flow / keypoints: host-side OpenCV front end; seed: the RANSAC key.

    The solver's ``batching="native"``: under ``vmap`` (sweeps over sequences) the LM's sequential
    ``custom_vmap`` rule cannot sit inside the step's ``scan`` + ``cond`` (JAX 0.10 fails with an
    internal assertion), so the batch runs as one native while-loop.
    """

    keyframe_interval: int = 20
    stride: int = 2
    motion: MotionConfig = MotionConfig(gmm=GMMConfig(num_components=3, max_iters=10, tol=1e-3))
    track: trajectory.TrackConfig = trajectory.TrackConfig(cell=16, keyframe_every=4, track_length=8,
                                                           border=2, min_track=3)
    assoc: trajectory.AssociationConfig = trajectory.AssociationConfig()
    refine: trajectory.RefineConfig = trajectory.RefineConfig(
        graph=factors.GraphConfig(sigma_proj=0.5),
        solver=lm.LMOptions(backward="none", max_iterations=20, max_linear_solves=40, batching="native"),
        outliers=factors.OutlierConfig(tau_min_px=1.0))
    memory: memory.MemoryConfig = memory.MemoryConfig(max_maps=16, max_points=4096, max_keyframes=16)
    track_check: TrackCheckConfig = TrackCheckConfig()
    use_memory: bool = True
    own_map_landmarks: bool = False
    map_min_support: float = 0.2
    min_memory_landmarks: int = 12
    memory_sigma_voxels: float = 0.5
    keyframe_threshold: float = 0.25
    feature_capacity: int = 128
    flow: FlowConfig = FlowConfig()
    keypoints: KeypointConfig = KeypointConfig(max_matches=256)
    seed: int = 0

    def __post_init__(self):
        if self.keyframe_interval < 2:
            raise ValueError(f"PipelineConfig.keyframe_interval: must be >= 2, got {self.keyframe_interval}")
        if self.stride < 1:
            raise ValueError(f"PipelineConfig.stride: must be >= 1, got {self.stride}")
        if self.feature_capacity < 1:
            raise ValueError("PipelineConfig.feature_capacity: must be >= 1")
        if self.min_memory_landmarks < 1:
            raise ValueError(f"PipelineConfig.min_memory_landmarks: must be >= 1, got {self.min_memory_landmarks}")
        if not 0 <= self.map_min_support < 1:
            raise ValueError(f"PipelineConfig.map_min_support: must be in [0, 1), got {self.map_min_support}")
        if not self.memory_sigma_voxels >= 0:
            raise ValueError(f"PipelineConfig.memory_sigma_voxels: must be >= 0, got {self.memory_sigma_voxels}")

    @property
    def window(self) -> int:
        """Pose slots per window: the anchor plus ``keyframe_interval`` frames."""
        return self.keyframe_interval + 1

    @property
    def seed_blocks(self) -> int:
        """Landmark seeding slots per window (0, κ, 2κ, ... below ``keyframe_interval``)."""
        return -(-self.keyframe_interval // self.track.keyframe_every)


def small_config(**changes) -> PipelineConfig:
    """A config for tiny images (tests, ``--quick``): small cells, memory and capacities."""
    base = PipelineConfig(
        keyframe_interval=4, stride=1,
        track=trajectory.TrackConfig(cell=8, keyframe_every=2, track_length=4, border=2, min_track=2),
        memory=memory.MemoryConfig(max_maps=4, max_points=256, max_keyframes=4, max_keypoints=64,
                                   icp_points=64, ransac_hypotheses=64, min_inliers=20,
                                   # distinct 3D points (keypoint clusters): a 48x64 window has few
                                   min_keypoint_inliers=4),
        feature_capacity=32, keypoints=KeypointConfig(max_matches=64))
    return dataclasses.replace(base, **changes)


def config_for(height: int, width: int, **changes) -> PipelineConfig:
    """The default config for an image size: :func:`small_config` below 192 px on the short side
    (landmark cells would not fit at half resolution), :class:`PipelineConfig` otherwise."""
    if min(height, width) < 192:
        return small_config(**changes)
    return dataclasses.replace(PipelineConfig(), **changes)


# ----------------------------------------------------------------------------------------------
# Inputs (host side)


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
    (h, w, 2) and keypoint matches frame -> partner, memory features, valid (padding frames are
    False), last (the sequence's last real frame), index (frame number)."""

    frame: FramePrior
    partner: FramePrior
    flow: Any
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


def prepare(sequence, cfg: PipelineConfig = PipelineConfig(), flow=None, progress=None) -> Inputs:
    """Host-side work for a :class:`cm3d.data.Sequence`: OpenCV flow and keypoint matches between
    each frame and its partner, per-frame keypoint features for the memory, resampling to 1/stride,
    padding to :func:`padded_length`. ``flow``: optional precomputed forward flow (S-1, H, W, 2);
    ``progress``: optional callable ``(done, total)`` after each frame. Returns numpy :class:`Inputs`."""
    from cm3d.ops import flow as oflow
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
    flows = np.zeros((S, H, W, 2), np.float32)
    uv0 = np.zeros((S, cfg.keypoints.max_matches, 2), np.float32)
    uv1 = np.zeros_like(uv0)
    mvalid = np.zeros((S, cfg.keypoints.max_matches), bool)
    for t in range(S):
        p = partner[t]
        if flow is not None and p == t + 1:
            flows[t] = flow[t]
        else:
            flows[t] = oflow.compute_flow(images[t], images[p], cfg.flow)
        m = okp.match_keypoints(images[t], images[p], cfg.keypoints)
        uv0[t], uv1[t], mvalid[t] = m.uv0, m.uv1, m.valid
        if progress is not None:
            progress(t + 1, S)
    if hasattr(okp, "detect_sequence"):
        feats = okp.detect_sequence(images, None, cfg.feature_capacity, cfg.keypoints)
        fuv, fdesc, fvalid = feats.uv / s, feats.desc, feats.valid
    else:  # no feature detector: the memory recalls by descriptors and cloud only
        fuv = np.zeros((S, cfg.feature_capacity, 2), np.float32)
        fdesc = np.zeros((S, cfg.feature_capacity, cfg.memory.keypoint_dim), np.float32)
        fvalid = np.zeros((S, cfg.feature_capacity), bool)

    K = scale_intrinsics(sequence.intrinsic, s).astype(np.float32)
    img_s = _shrink(images, s)
    depth = _shrink(np.asarray(sequence.depth, np.float32), s)
    conf = _shrink(np.asarray(sequence.depth_conf, np.float32), s)
    c2w = np.asarray(sequence.cam_to_world, np.float32)
    frame = FramePrior(image=img_s, depth=depth, depth_conf=conf, intrinsic=K, cam_to_world=c2w)
    part = FramePrior(image=img_s[partner], depth=depth[partner], depth_conf=conf[partner],
                      intrinsic=K[partner], cam_to_world=c2w[partner])
    inputs = Inputs(frame=frame, partner=part, flow=_shrink(flows, s) / s,
                    matches=Matches(uv0 / s, uv1 / s, mvalid),
                    features=Features(np.asarray(fuv, np.float32), np.asarray(fdesc, np.float32), fvalid),
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


# ----------------------------------------------------------------------------------------------
# State


@struct.dataclass
class Window:
    """Buffers of the current window (``W = keyframe_interval + 1`` slots, reduced resolution)."""

    poses: Any  # (W, 4, 4) initial poses (priors carried into the refined frame)
    intrinsic: Any  # (W, 3, 3)
    depth: Any  # (W, h, w)
    conf: Any  # (W, h, w)
    image: Any  # (W, h, w, 3) uint8
    static: Any  # (W, h, w) bool
    desc: Any  # (W, D2) image descriptors of the static pixels
    feat_uv: Any  # (W, n, 2)
    feat_desc: Any  # (W, n, Dk)
    feat_valid: Any  # (W, n)
    index: Any  # (W,) frame numbers
    valid: Any  # (W,) filled slots


@struct.dataclass
class Landmarks:
    """Landmark tracks of the window: ``L = seed_blocks x cells``, ``T = track_length``.

    uv (L, 2) last tracked pixel; alive (L,); seed (L,) seeding slot; obs_uv (L, T, 2) and
    obs_valid (L, T) observations at slots ``seed + j``; points (L, 3) lifted at seeding."""

    uv: Any
    alive: Any
    seed: Any
    obs_uv: Any
    obs_valid: Any
    points: Any


@struct.dataclass
class MapState:
    """Everything the pipeline remembers: the memory bank (persists across sequences), the PRNG key,
    the current window (map buffers and pose window), the landmark tracks, the previous flow, the
    anchor (refined and prior pose of slot 0), the map this sequence recalled from an earlier one
    and its Sim(3) placement (sequence -> map), the map this sequence stored (``written``, -1 none),
    the slot of the next frame and frames seen."""

    bank: memory.MemoryBank
    key: Any
    window: Window
    landmarks: Landmarks
    prev_flow: Any
    anchor_pose: Any
    anchor_prior: Any
    recalled: Any
    recalled_transform: Any
    slot: Any
    frames: Any
    written: Any


def _zeros_window(cfg: PipelineConfig, h: int, w: int, n: int, dk: int) -> Window:
    W = cfg.window
    eye = jnp.broadcast_to(jnp.eye(4, dtype=jnp.float32), (W, 4, 4))
    return Window(poses=eye, intrinsic=jnp.broadcast_to(jnp.eye(3, dtype=jnp.float32), (W, 3, 3)),
                  depth=jnp.zeros((W, h, w), jnp.float32), conf=jnp.zeros((W, h, w), jnp.float32),
                  image=jnp.zeros((W, h, w, 3), jnp.uint8), static=jnp.zeros((W, h, w), bool),
                  desc=jnp.zeros((W, descriptors.IMAGE_DIM), jnp.float32),
                  feat_uv=jnp.zeros((W, n, 2), jnp.float32), feat_desc=jnp.zeros((W, n, dk), jnp.float32),
                  feat_valid=jnp.zeros((W, n), bool), index=jnp.zeros(W, jnp.int32), valid=jnp.zeros(W, bool))


def _zeros_landmarks(cfg: PipelineConfig, h: int, w: int) -> Landmarks:
    c = cfg.track.cell
    L = cfg.seed_blocks * (h // c) * (w // c)
    T = cfg.track.track_length
    return Landmarks(uv=jnp.zeros((L, 2), jnp.float32), alive=jnp.zeros(L, bool),
                     seed=jnp.repeat(jnp.arange(cfg.seed_blocks, dtype=jnp.int32) * cfg.track.keyframe_every,
                                     (h // c) * (w // c)),
                     obs_uv=jnp.zeros((L, T, 2), jnp.float32), obs_valid=jnp.zeros((L, T), bool),
                     points=jnp.zeros((L, 3), jnp.float32))


def init_state(inputs: Inputs, cfg: PipelineConfig = PipelineConfig(), bank: memory.MemoryBank | None = None,
               memory_cfg: memory.MemoryConfig | None = None) -> MapState:
    """A fresh state for sequences shaped like ``inputs`` (a new or the given memory bank)."""
    h, w = inputs.frame.depth.shape[-2:]
    n, dk = inputs.features.desc.shape[-2:]
    if bank is None:
        bank = memory.empty(memory_cfg or cfg.memory)
    st = MapState(bank=bank, key=jax.random.PRNGKey(cfg.seed), window=_zeros_window(cfg, h, w, n, dk),
                  landmarks=_zeros_landmarks(cfg, h, w), prev_flow=jnp.zeros((h, w, 2), jnp.float32),
                  anchor_pose=jnp.eye(4, dtype=jnp.float32), anchor_prior=jnp.eye(4, dtype=jnp.float32),
                  recalled=-jnp.ones((), jnp.int32), recalled_transform=jnp.eye(4, dtype=jnp.float32),
                  slot=jnp.zeros((), jnp.int32), frames=jnp.zeros((), jnp.int32), written=-jnp.ones((), jnp.int32))
    return st


def begin_sequence(state: MapState) -> MapState:
    """The state at the start of a new sequence: window, tracks and anchor cleared, bank and key kept."""
    fresh = jax.tree.map(jnp.zeros_like, state)
    eye = jnp.eye(4, dtype=jnp.float32)
    win = fresh.window.replace(poses=jnp.broadcast_to(eye, fresh.window.poses.shape),
                               intrinsic=jnp.broadcast_to(jnp.eye(3, dtype=jnp.float32), fresh.window.intrinsic.shape))
    return fresh.replace(bank=state.bank, key=state.key, anchor_pose=eye, anchor_prior=eye, window=win,
                         recalled=-jnp.ones((), jnp.int32), recalled_transform=eye, written=-jnp.ones((), jnp.int32),
                         landmarks=fresh.landmarks.replace(seed=state.landmarks.seed))


# ----------------------------------------------------------------------------------------------
# Outputs


@struct.dataclass
class RecallReport:
    """One window's memory decision (zeros when memory is off): candidates (top_k,) map ids
    (-1 none), votes (top_k,) and scores (top_k,) of the candidates, keypoint inliers (top_k,),
    accepted, recalled map id (-1 none), inlier_count and inlier_rmse of the verification,
    fitness, scale, transform (4, 4) query -> map (Sim(3)), map_id written (-1 bank full), created, and
    placement (4, 4): the Sim(3) sequence -> map the window actually used for its memory priors and its
    merge (the recalled map's placement after the re-fit to the landmarks; identity for the sequence's
    own map or a new one). ``transform`` is the verification's estimate alone."""

    candidates: Any
    votes: Any
    scores: Any
    keypoint_inliers: Any
    accepted: Any
    recalled: Any
    inlier_count: Any
    inlier_rmse: Any
    fitness: Any
    scale: Any
    transform: Any
    map_id: Any
    created: Any
    placement: Any = None


@struct.dataclass
class WindowResult:
    """Factor-graph result of one window: poses (W, 4, 4) refined (gated), index (W,) frame numbers,
    valid (W,), refined (gate passed), gate_stat / gate_threshold, observations and inliers, landmark
    count, memory landmarks, LM iterations, the :class:`RecallReport` and the number of tracks dropped as
    inconsistent with the prior geometry (:func:`prior_consistent_tracks`)."""

    poses: Any
    index: Any
    valid: Any
    refined: Any
    gate_stat: Any
    gate_threshold: Any
    observations: Any
    inliers: Any
    landmarks: Any
    memory_landmarks: Any
    iterations: Any
    recall: RecallReport
    inconsistent: Any = 0
    memory_used: Any = False
    memory_stat: Any = 0.0
    memory_threshold: Any = 0.0


@struct.dataclass
class StepOutputs:
    """Per-frame outputs: dynamic mask (h, w), initial pose (4, 4), window_end (a window was
    refined at this frame: ``window`` holds it), valid (a real frame)."""

    mask: Any
    init_pose: Any
    window_end: Any
    window: WindowResult
    valid: Any


# ----------------------------------------------------------------------------------------------
# Stages of the step


def static_mask(inputs_t: Inputs, cfg: PipelineConfig):
    """Motion cues of frame t (pair with its partner): (dynamic mask (h, w), static (h, w))."""
    cues = motion_cues(inputs_t.frame, inputs_t.partner, inputs_t.flow, inputs_t.matches, cfg.motion)
    dyn = cues.robust_mask
    return dyn, ~dyn & (inputs_t.frame.depth > 0)


def advance_landmarks(lm_: Landmarks, flow, static, slot, cfg: PipelineConfig) -> Landmarks:
    """Follow live landmarks from the previous frame into slot ``slot`` with the previous flow
    (chained bilinear flow, as :func:`cm3d.trajectory.chain_tracks`); record the observation."""
    h, w = static.shape
    T = cfg.track.track_length
    b = cfg.track.border * 0.5
    fl = trajectory.bilinear(flow[None], jnp.zeros(lm_.uv.shape[0], jnp.int32), lm_.uv)
    nxt = lm_.uv + fl
    inside = (nxt[:, 0] >= b) & (nxt[:, 0] <= w - 1 - b) & (nxt[:, 1] >= b) & (nxt[:, 1] <= h - 1 - b)
    r = jnp.clip(jnp.round(nxt[:, 1]).astype(jnp.int32), 0, h - 1)
    c = jnp.clip(jnp.round(nxt[:, 0]).astype(jnp.int32), 0, w - 1)
    j = slot - lm_.seed
    good = lm_.alive & inside & static[r, c] & (j >= 1) & (j < T)
    put = (jnp.arange(T)[None, :] == j[:, None]) & good[:, None]
    return lm_.replace(uv=jnp.where(good[:, None], nxt, lm_.uv), alive=good,
                       obs_uv=jnp.where(put[..., None], nxt[:, None, :], lm_.obs_uv),
                       obs_valid=lm_.obs_valid | put)


def seed_landmarks(lm_: Landmarks, slot, depth, conf, static, K, pose, cfg: PipelineConfig) -> Landmarks:
    """Seed the block of slot ``slot``: the most confident static pixel of each cell, lifted to
    the world with the prior depth and the slot's initial pose."""
    uv, ok = trajectory.select_landmark_pixels(depth, conf, static, cfg.track)
    C = uv.shape[0]
    h, w = depth.shape
    r = jnp.clip(jnp.round(uv[:, 1]).astype(jnp.int32), 0, h - 1)
    c = jnp.clip(jnp.round(uv[:, 0]).astype(jnp.int32), 0, w - 1)
    d = depth[r, c]
    ray = jnp.concatenate([uv, jnp.ones_like(uv[:, :1])], -1) @ jnp.linalg.inv(K).T
    pw = se3.transform_points(pose, ray * d[:, None])
    ok = ok & (d > 0)
    start = (slot // cfg.track.keyframe_every) * C
    T = cfg.track.track_length
    first = jnp.zeros((C, T, 2), uv.dtype).at[:, 0].set(uv)
    fvalid = jnp.zeros((C, T), bool).at[:, 0].set(ok)
    upd = lambda a, v: jax.lax.dynamic_update_slice_in_dim(a, v.astype(a.dtype), start, 0)  # noqa: E731
    return lm_.replace(uv=upd(lm_.uv, uv), alive=upd(lm_.alive, ok), obs_uv=upd(lm_.obs_uv, first),
                       obs_valid=upd(lm_.obs_valid, fvalid), points=upd(lm_.points, pw))


def landmark_observations(lm_: Landmarks, cfg: PipelineConfig) -> trajectory.Observations:
    """The window's projection observations (K = L x T), tracks shorter than ``min_track`` dropped."""
    valid = lm_.obs_valid & (jnp.sum(lm_.obs_valid, -1) >= cfg.track.min_track)[:, None]
    tracks = trajectory.Tracks(uv=lm_.obs_uv, valid=valid, frame=lm_.seed)
    return trajectory.track_observations(tracks)


def _sim3_inverse_apply(A, points):
    """Points moved by the inverse of the Sim(3) ``[s R, t]`` (map -> query)."""
    Ainv = jnp.linalg.inv(A[:3, :3])
    return (points - A[:3, 3]) @ Ainv.T


def window_entry(win: Window, mem_cfg: memory.MemoryConfig, cfg: PipelineConfig,
                 min_support: float = 0.0) -> memory.MapEntry:
    """The window as a memory entry (:func:`cm3d.memory.build_entry`): its static cloud, keyframe
    descriptors and 3D keypoints, posed by ``win.poses``; ``min_support``: drop voxels with fewer
    samples than this share of the median voxel's (the entry that goes into the bank)."""
    cloud_cfg = dataclasses.replace(mem_cfg, pixel_stride=max(1, mem_cfg.pixel_stride // cfg.stride))
    static = win.static & win.valid[:, None, None]
    cloud = memory.sequence_cloud(win.depth, win.conf, win.intrinsic, win.poses, win.image, static, cloud_cfg)
    idx, kv = memory.select_keyframes(win.desc, win.valid, cfg.keyframe_threshold, mem_cfg.max_keyframes)
    fvalid = win.feat_valid & win.valid[:, None]
    kp = memory.lift_keypoints(win.feat_uv, win.feat_desc, fvalid, win.depth, win.intrinsic, win.poses,
                               mem_cfg.max_keypoints)
    return memory.build_entry(cloud, win.desc[idx], kv, mem_cfg, keypoints=kp, min_support=min_support)


def _recall_report(ident: memory.Identification, map_id, transform, created, placement=None) -> RecallReport:
    rc, ver = ident.recall, ident.verification
    cand = rc.candidates
    safe = jnp.maximum(cand, 0)
    return RecallReport(
        candidates=cand.astype(jnp.int32), votes=jnp.where(cand >= 0, rc.votes[safe], 0.0).astype(jnp.float32),
        scores=jnp.where(cand >= 0, rc.scores[safe], 0.0).astype(jnp.float32),
        keypoint_inliers=ident.candidate_inliers.astype(jnp.int32),
        accepted=ident.map_id >= 0, recalled=ident.map_id.astype(jnp.int32),
        inlier_count=ver.inlier_count.astype(jnp.int32), inlier_rmse=ver.inlier_rmse.astype(jnp.float32),
        fitness=ver.fitness.astype(jnp.float32), scale=ver.scale.astype(jnp.float32),
        transform=jnp.asarray(transform, jnp.float32), map_id=jnp.asarray(map_id, jnp.int32),
        created=jnp.asarray(created, bool),
        placement=jnp.asarray(transform if placement is None else placement, jnp.float32))


def recall_verify_update(bank, key, win: Window, mem_cfg: memory.MemoryConfig, cfg: PipelineConfig):
    """Recall / verify / update in one call (:func:`cm3d.memory.remember`) for a window posed by
    ``win.poses``. Returns (bank, :class:`RecallReport`). (:func:`window_end` splits the three
    steps around the factor graph.)"""
    bank, rep = memory.remember(bank, window_entry(win, mem_cfg, cfg), mem_cfg, key)
    return bank, _recall_report(rep.identification, rep.map_id, rep.transform, rep.created)


def memory_surface(bank: memory.MemoryBank, map_id, transform, d_scene) -> trajectory.MemorySurface:
    """Map ``map_id`` moved into the sequence's frame (inverse of the Sim(3) ``transform``
    sequence -> map) as a :class:`cm3d.trajectory.MemorySurface` (empty when ``map_id < 0``)."""
    pts, valid = memory_landmarks(bank, map_id, transform)
    m = jnp.maximum(map_id, 0)
    A = transform[:3, :3].astype(jnp.float32)
    scale = jnp.cbrt(jnp.abs(jnp.linalg.det(A)))
    R = A / jnp.maximum(scale, 1e-12)
    normals = bank.normals[m] @ R  # map -> sequence: R^T n, as rows
    return trajectory.MemorySurface(points=pts, normals=normals, valid=valid,
                                    voxel=bank.voxel_size[m] / jnp.maximum(scale, 1e-12),
                                    d_scene=jnp.asarray(d_scene, jnp.float32))


def memory_landmarks(bank: memory.MemoryBank, map_id, transform):
    """Points (P, 3) of map ``map_id`` moved into the sequence's frame (inverse of the Sim(3)
    ``transform`` sequence -> map) and their validity (P,) (none when ``map_id < 0``)."""
    m = jnp.maximum(map_id, 0)
    pts = _sim3_inverse_apply(transform.astype(jnp.float32), bank.points[m])
    return pts, bank.point_valid[m] & (map_id >= 0)


def _empty_report(top_k: int) -> RecallReport:
    zi = jnp.zeros(top_k, jnp.int32)
    return RecallReport(candidates=zi - 1, votes=jnp.zeros(top_k), scores=jnp.zeros(top_k), keypoint_inliers=zi,
                        accepted=jnp.zeros((), bool), recalled=-jnp.ones((), jnp.int32),
                        inlier_count=jnp.zeros((), jnp.int32), inlier_rmse=jnp.zeros(()), fitness=jnp.zeros(()),
                        scale=jnp.ones(()), transform=jnp.eye(4, dtype=jnp.float32),
                        map_id=-jnp.ones((), jnp.int32), created=jnp.zeros((), bool),
                        placement=jnp.eye(4, dtype=jnp.float32))


def _frame_motion_residuals(r, uv, group, ok, num_groups: int, K, min_scale, rounds: int = 5):
    """Transfer residuals (K, 2) with each group's common image motion removed.

    A prior pose error moves every static point seen in a frame by nearly the same small image
    motion (rotation: a shift plus a turn about the principal point; translation: a depth-dependent
    shift, smaller): per group (observations of one frame from one seeding frame, which share both
    poses' errors) an affine field ``r ≈ a + B (uv − c) / f`` is fitted by iteratively reweighted
    least squares and subtracted. Cauchy weights at a robust scale (``1.4826`` x the median residual
    over all groups, at least ``min_scale`` px) keep tracks on moving objects from dragging the fit;
    groups with fewer than 8 observations are left as they are. r, uv: (K, 2); group: (K,) int in
    [0, num_groups); ok: (K,) bool; K: (K, 3, 3)."""
    f = K[:, 0, 0]
    phi = jnp.stack([jnp.ones_like(f), (uv[:, 0] - K[:, 0, 2]) / f, (uv[:, 1] - K[:, 1, 2]) / f], -1)  # (K, 3)
    r0 = jnp.where(ok[:, None], r, 0.0)
    count = jax.ops.segment_sum(ok.astype(jnp.int32), group, num_groups)
    w = ok.astype(r.dtype)
    eye = jnp.eye(3, dtype=r.dtype)
    res = r0
    for _ in range(rounds):
        A = jax.ops.segment_sum(w[:, None, None] * phi[:, :, None] * phi[:, None, :], group, num_groups)
        b = jax.ops.segment_sum(w[:, None, None] * phi[:, :, None] * r0[:, None, :], group, num_groups)
        tr = jnp.trace(A, axis1=-2, axis2=-1)
        coef = jnp.linalg.solve(A + 1e-6 * jnp.maximum(tr, 1e-12)[:, None, None] * eye, b)
        coef = jnp.where((count >= 8)[:, None, None] & jnp.all(jnp.isfinite(coef), (1, 2), keepdims=True), coef, 0.0)
        res = r0 - jnp.einsum("ki,kij->kj", phi, coef[group])
        e2 = jnp.sum(res * res, -1)
        scale = jnp.maximum(min_scale, 1.4826 * jnp.sqrt(robust.masked_median(e2, ok)))
        w = ok / (1.0 + e2 / scale ** 2)
    return res


def prior_consistent_tracks(win: Window, lm_: Landmarks, obs: trajectory.Observations, cfg: PipelineConfig):
    """Which landmark tracks agree with the prior geometry (:class:`TrackCheckConfig`): (L,) bool.

    The transfer error of an observation is its reprojection error at the initial variables (the
    window's prior poses, the landmark lifted with the prior depth at its seed pixel) after the
    image motion common to its frame and seeding frame is removed (:func:`_frame_motion_residuals`):
    that part is the prior's *pose* error, which the graph is there to fix. Without the removal a
    frame whose prior pose is worse than its neighbours' had all its tracks dropped (measured: the
    last frame of scene 1's first window kept 0 of 65 observations, so the graph could not correct
    it, and as the next window's anchor its 3° error rotated that whole window). A track's error is
    the RMS over its observations after the seed's (which is 0 by construction)."""
    L, T = lm_.obs_valid.shape
    ov = obs.valid.reshape(L, T)
    has = ov[:, 0]
    if not cfg.track_check.enabled:
        return has
    P = win.poses[obs.pose_idx]
    Kk = win.intrinsic[obs.pose_idx]
    pred, z = factors.project(P, lm_.points[obs.point_idx], Kk)
    r = pred - obs.uv
    j = jnp.tile(jnp.arange(T), L)
    ok = obs.valid & (z > factors.MIN_DEPTH) & jnp.all(jnp.isfinite(r), -1) & (j > 0)
    W = win.poses.shape[0]
    block = jnp.repeat(lm_.seed // cfg.track.keyframe_every, T)
    group = block * W + obs.pose_idx
    res = _frame_motion_residuals(r, obs.uv, group, ok, cfg.seed_blocks * W, Kk, cfg.track_check.min_px)
    err = jnp.where(ok, jnp.linalg.norm(res, axis=-1), jnp.where(obs.valid & (j > 0), 1e6, 0.0)).reshape(L, T)
    n = jnp.sum(ov, -1)
    sq = jnp.sum(jnp.where(ov, err ** 2, 0.0), -1)
    rms = jnp.sqrt(sq / jnp.maximum(n - 1, 1))
    med = robust.masked_median(rms, has)
    mad = robust.masked_median(jnp.abs(rms - med), has)
    tau = jnp.maximum(cfg.track_check.min_px, med + cfg.track_check.n_mad * 1.4826 * mad)
    return has & (rms <= tau)


def structure_only_cost(graph: factors.FactorGraph, poses, points, iterations: int = 15, min_observations: int = 2):
    """The factor graph's objective with the poses held and every landmark re-estimated (the gate's
    null hypothesis). With the poses fixed the landmarks decouple, so each takes damped Gauss-Newton
    steps on its own 3x3 system (Huber reweighting as the solver does; a step is kept only when it
    lowers that landmark's cost) instead of a second LM in the compiled program. Observations of
    landmarks with fewer than ``min_observations`` weighted observations are ignored, as
    :func:`cm3d.solvers.lm.solve` ignores them. Returns (cost, points (M, 3))."""
    f = graph.projection
    M = points.shape[0]
    k = jnp.asarray(graph.huber_k, points.dtype)
    counts = jax.ops.segment_sum((f.weight > 0).astype(jnp.int32), f.point_idx, M)
    active = (f.weight > 0) & (counts >= min_observations)[f.point_idx]
    w0 = jnp.where(active, f.weight, 0.0)

    pp = graph.point_prior
    wl = jnp.zeros(M, points.dtype) if pp is None else jnp.where(counts >= min_observations, pp.weight, 0.0)

    def prior_terms(pts):  # landmark priors (memory): per-landmark cost, Gauss-Newton block and gradient
        if pp is None:
            return jnp.zeros(M, pts.dtype), 0.0, 0.0
        r = factors.point_prior_residual(graph, pts)
        S = pp.sqrt_info.astype(pts.dtype)
        return (0.5 * wl * jnp.sum(r * r, -1), wl[:, None, None] * jnp.einsum("mij,mil->mjl", S, S),
                wl[:, None] * jnp.einsum("mij,mi->mj", S, r))

    def per_point_cost(pts):
        e, _ = factors.projection_residual(graph, factors.Variables(poses, pts))
        return jax.ops.segment_sum(w0 * factors.huber_loss(jnp.sum(e * e, -1), k), f.point_idx, M) + prior_terms(pts)[0]

    def body(_, carry):
        pts, lam = carry
        e, _, B, _ = factors.projection_linearize(graph, factors.Variables(poses, pts))
        w = w0 * factors.huber_weight(jnp.sum(e * e, -1), k)
        H = jax.ops.segment_sum(w[:, None, None] * jnp.einsum("kij,kil->kjl", B, B), f.point_idx, M)
        g = jax.ops.segment_sum(w[:, None] * jnp.einsum("kij,ki->kj", B, e), f.point_idx, M)
        _, Hl, gl = prior_terms(pts)
        H, g = H + Hl, g + gl
        diag = jnp.diagonal(H, axis1=-2, axis2=-1)
        Hd = H + (lam[:, None] * jnp.maximum(diag, 1e-12))[:, :, None] * jnp.eye(3, dtype=H.dtype)
        step = -jnp.linalg.solve(Hd, g[..., None])[..., 0]
        step = jnp.where(jnp.isfinite(step), step, 0.0)
        new = pts + step
        better = per_point_cost(new) < per_point_cost(pts)
        return jnp.where(better[:, None], new, pts), jnp.where(better, lam * 0.1, lam * 10.0)

    pts, _ = jax.lax.fori_loop(0, iterations, body, (points, jnp.full(M, 1e-4, points.dtype)))
    cost = factors.total_cost(graph, factors.Variables(poses, pts), active)
    if pp is not None:  # total_cost counts every landmark prior; count those of estimable landmarks only
        cost = cost - factors.point_prior_cost(graph, pts) + jnp.sum(prior_terms(pts)[0])
    return cost, pts


def gate_refinement(win: Window, points0, obs: trajectory.Observations, ref: trajectory.Refinement,
                    cfg: PipelineConfig) -> trajectory.Refinement:
    """The significance gate of :class:`cm3d.trajectory.RefineConfig` on an ungated refinement: a
    likelihood-ratio test of "the prior poses are right" (poses held at the prior, landmarks
    re-estimated *from their lifted positions* ``points0`` on the refinement's inlier observations)
    against the refined poses, ``2 ΔC > χ²_q(6 (n − 1))``. Re-estimating from the lifted positions
    (not from the refined ones, which may sit far from the prior poses' optimum) keeps the
    null-hypothesis solve converged: started from the refined landmarks it could stop at a cost
    10^3 times too high and accept a refinement of exact priors."""
    rc = cfg.refine
    if not rc.gate:
        return ref.replace(refined=jnp.ones((), bool))
    g = factors.build_graph(win.poses, win.intrinsic, obs.pose_idx, obs.point_idx, obs.uv, ref.inlier,
                            ref.graph.projection.memory if ref.graph is not None else obs.memory, win.valid, rc.graph)
    if ref.graph is not None and ref.graph.point_prior is not None:  # both hypotheses see the remembered surface
        g = g.replace(point_prior=ref.graph.point_prior)
    cost0, points_fixed = structure_only_cost(g, win.poses, points0, min_observations=rc.solver.min_observations)
    dt = win.poses.dtype
    stat = (2.0 * (cost0 - ref.result.cost)).astype(dt)
    seen = jnp.zeros(win.poses.shape[0], jnp.int32).at[obs.pose_idx].max(ref.inlier.astype(jnp.int32))
    thr = robust.chi2_quantile(rc.gate_quantile, 6.0 * jnp.maximum(jnp.sum(seen) - 1, 1).astype(dt))
    use = stat > thr
    return ref.replace(poses=jnp.where(use, ref.refined_poses, win.poses),
                       points=jnp.where(use, ref.result.params.points, points_fixed),
                       refined=use, gate_stat=stat, gate_threshold=thr)


def factor_graph(win: Window, lm_: Landmarks, surface: trajectory.MemorySurface | None, cfg: PipelineConfig,
                 realign=False):
    """Tracks checked against the prior geometry, then the windowed factor graph with its
    significance gate. ``surface``: the recalled map in the window's frame (or None): after the
    first solve the landmarks within ``τ = max(τ_min, d_scene α)`` of its tangent planes are held on
    it (point-to-plane priors, projection covariance scaled by ``α_mem``;
    :func:`cm3d.trajectory.refine_trajectory`; ``realign``: its placement is first re-fitted to the
    landmarks). Returns (Refinement, poses, observations, memory landmarks, dropped tracks)."""
    obs = landmark_observations(lm_, cfg)
    T = cfg.track.track_length
    obs_all_first = obs.valid.reshape(lm_.obs_valid.shape)[:, 0]
    first = prior_consistent_tracks(win, lm_, obs, cfg)
    # slow movers the per-frame motion cue misses: tracks a robust rigid fit of their group leaves moving
    first = first & ~moving_tracks(lm_.points, win.poses, win.intrinsic, obs.pose_idx, obs.uv, obs.valid,
                                   lm_.seed // cfg.track.keyframe_every, cfg.seed_blocks, cfg.motion)
    obs = obs.replace(valid=obs.valid & jnp.repeat(first, T))
    ungated = dataclasses.replace(cfg.refine, gate=False)
    ref = trajectory.refine_trajectory(win.poses, win.intrinsic, lm_.points, obs, ungated, pose_valid=win.valid,
                                       memory=surface, assoc=cfg.assoc, realign=realign)
    ref = gate_refinement(win, lm_.points, obs, ref, cfg)
    n_bad = jnp.sum(obs_all_first & ~first)
    n_mem = jnp.sum(ref.memory)
    # the scale fix belongs to refined poses only: when the gate keeps the prior, so does the scale
    fixed = restore_depth_scale(ref.poses, win.poses, ref.points, lm_.points, lm_.seed, first)
    poses = jnp.where(ref.refined, fixed, ref.poses)
    poses = jnp.where(win.valid[:, None, None], poses, win.poses)
    return ref, poses, obs, n_mem, n_bad


def restore_depth_scale(poses, init_poses, points, init_points, seed, valid):
    """Fix the window's scale gauge to the prior depth's scale.

    Reprojection and relative-motion factors leave the scale of a window nearly free (a short
    window under rotation can shrink by 3x at almost no cost). The prior depth fixes it: the median
    ratio ``r`` of each landmark's distance to its seeding camera, refined over initial, measures
    how far the graph moved the scale, and camera centres are rescaled about the anchor (slot 0,
    held by the prior) by ``1 / r``. poses, init_poses (W, 4, 4); points, init_points (L, 3);
    seed (L,) slot; valid (L,)."""
    return rescale_window(poses, points, init_poses, init_points, seed, valid)[0]


def rescale_window(poses, points, init_poses, init_points, seed, valid):
    """:func:`restore_depth_scale` of the camera centres *and* the landmarks (L, 3) about the anchor:
    (poses, points), the graph's solution with the prior depth's scale."""
    d_ref = jnp.linalg.norm(points - poses[seed, :3, 3], axis=-1)
    d_init = jnp.linalg.norm(init_points - init_poses[seed, :3, 3], axis=-1)
    ok = valid & (d_init > 0) & jnp.isfinite(d_ref)
    r = robust.masked_median(d_ref / jnp.where(ok, d_init, 1.0), ok)
    r = jnp.where((jnp.sum(ok) >= 3) & jnp.isfinite(r) & (r > 0), jnp.clip(r, 0.2, 5.0), 1.0)
    c0 = poses[0, :3, 3]
    return poses.at[:, :3, 3].set(c0 + (poses[:, :3, 3] - c0) / r), c0 + (points - c0) / r


def sequence_query(bank: memory.MemoryBank, written, entry: memory.MapEntry, mem_cfg: memory.MemoryConfig):
    """The query of a window's identification: the window's entry merged with the map its sequence
    stored so far (``written``, in the sequence's frame: its earlier windows, refined), i.e. the whole
    sequence up to this window (more keyframes vote, more 3D keypoints can match an earlier visit's
    map that the window alone overlaps little); the window's entry alone when ``written < 0``."""
    m = jnp.maximum(written, 0)

    def merged(entry):
        b = memory.update_map(bank, m, entry, jnp.eye(4, dtype=jnp.float32), mem_cfg)
        kp = memory.Keypoints(b.kp_points[m], b.kp_desc[m], b.kp_valid[m])
        return entry.replace(points=b.points[m], normals=b.normals[m], conf=b.conf[m], colors=b.colors[m],
                             point_valid=b.point_valid[m], kf_desc=b.kf_desc[m], kf_valid=b.kf_valid[m],
                             cloud_desc=b.cloud_desc[m], voxel_size=b.voxel_size[m],
                             keypoints=kp)  # both at the bank's keypoint capacity (_bank_config)

    return jax.lax.cond(written >= 0, merged, lambda e: e, entry)


def memory_refinement(win: Window, lm_: Landmarks, ref0: trajectory.Refinement, obs: trajectory.Observations,
                      first, surface: trajectory.MemorySurface, cfg: PipelineConfig, realign=False):
    """The window's factor graph again, with the remembered surface, from the memory-free optimum
    ``ref0`` (its graph after outlier rejection, its landmarks and poses).

    The landmarks within ``τ = max(τ_min, d_scene α)`` of the surface's tangent planes get
    point-to-plane priors and their projection covariance is scaled by ``α_mem``
    (:func:`cm3d.trajectory.memory_point_prior`; ``realign``: the surface's placement is first
    re-fitted to the landmarks, :func:`cm3d.trajectory.align_to_surface`), and the LM solves once.

    **Consistency test** (memory never hurts, issue #7): the memory pulls the poses away from the
    window's own optimum; ``stat = 2 (C_own(poses_mem) − C_own(poses_free))``, with ``C_own`` the
    window's own objective (no memory terms) after re-estimating the landmarks with the poses held
    (:func:`structure_only_cost`), is χ²-distributed when the surface agrees with the window's
    observations and large when it does not (a wrong placement, a map that drifted, biased depth).
    The memory solution is used only when ``stat <= χ²_q(6 (n − 1))`` (the gate's quantile) and at
    least ``cfg.min_memory_landmarks`` landmarks are on the surface. The priors' std is the largest of
    ``plane_sigma_ratio · d_scene``, the landmarks' robust spread about the surface at the memory-free
    optimum and ``cfg.memory_sigma_voxels`` map voxels.
    Returns (poses (W, 4, 4) depth-scale restored, accept (the memory solution passes the test and has
    memory landmarks), alignment (4, 4), memory landmarks (L,) bool, stat, threshold)."""
    rc = cfg.refine
    L = lm_.points.shape[0]
    g0 = ref0.graph
    # the memory-free optimum at the prior depth's scale (the graph leaves the scale nearly free: a
    # collapsed window's landmarks would lie far from the remembered surface)
    x0 = ref0.result.params
    x0 = factors.Variables(*rescale_window(x0.poses, x0.points, win.poses, lm_.points, lm_.seed, first))
    f = g0.projection
    pvalid = jnp.zeros(L, bool).at[f.point_idx].max(f.weight > 0)
    eye = jnp.eye(4, dtype=x0.points.dtype)
    A = jax.lax.cond(realign, lambda: trajectory.align_to_surface(x0.points, pvalid, surface, cfg.assoc), lambda: eye)
    placed = trajectory.move_surface(surface, A)
    # the prior's std: the configured one or, when larger, the spread of the landmarks about the surface at
    # the memory-free optimum (a map less accurate than the window, or placed less accurately, holds less),
    # and at least a share of the map's voxel (its points are voxel means, its planes fitted at that scale)
    _, near, plane = trajectory.associate_surface(x0.points, pvalid, placed, cfg.assoc)
    spread = 1.4826 * robust.masked_median(plane, near)
    sigma = jnp.maximum(cfg.assoc.plane_sigma_ratio * surface.d_scene,
                        jnp.where(jnp.sum(near) >= cfg.min_memory_landmarks, spread, 0.0))
    sigma = jnp.maximum(sigma, cfg.memory_sigma_voxels * placed.voxel)
    g1, matched = trajectory.memory_point_prior(g0, x0.points, pvalid, placed, cfg.assoc, sigma=sigma)
    res = lm.solve(g1, x0, rc.solver)
    poses1 = factors.orthonormalize_poses(res.params.poses)
    cost_own, _ = structure_only_cost(g0, poses1, res.params.points, min_observations=rc.solver.min_observations)
    stat = (2.0 * (cost_own - ref0.result.cost)).astype(win.poses.dtype)
    seen = jnp.zeros(win.poses.shape[0], jnp.int32).at[obs.pose_idx].max(ref0.inlier.astype(jnp.int32))
    thr = robust.chi2_quantile(rc.gate_quantile, 6.0 * jnp.maximum(jnp.sum(seen) - 1, 1).astype(win.poses.dtype))
    fixed = restore_depth_scale(poses1, win.poses, res.params.points, lm_.points, lm_.seed, first)
    fixed = jnp.where(win.valid[:, None, None], fixed, win.poses)
    accept = (jnp.sum(matched) >= cfg.min_memory_landmarks) & (stat <= thr) & jnp.all(jnp.isfinite(fixed))
    return fixed, accept, A, matched, stat, thr


def window_end(bank, key, recalled, recalled_T, win: Window, lm_: Landmarks, mem_cfg: memory.MemoryConfig,
               cfg: PipelineConfig, written=-1):
    """The window that ends at this frame (one branch of the step's ``lax.cond``):

    1. **factor graph** without memory (:func:`factor_graph`: tracks checked against the prior, LM,
       outlier rejection, LM, significance gate, depth-scale gauge): exactly the memory-free result;
    2. **identify**: recall + verify the window's static cloud, keyframe descriptors and 3D keypoints,
       posed by those *refined* poses and merged with the map the sequence stored so far
       (:func:`sequence_query`), against the bank *without the map this
       sequence stored itself* (``written``: its keyframes are the nearest descriptors of every later
       window of the sequence and would take all the votes, so an earlier visit's map was never a
       candidate after the first window) (:func:`cm3d.memory.identify`);
    3. **factor graph with memory** (:func:`memory_refinement`) from the memory-free optimum, with the
       surface of the map this sequence recalled from an earlier sequence (``recalled`` with the
       Sim(3) ``recalled_T`` sequence -> map, which keeps its placement), or of the earlier map this
       window verified (placed by the verification, re-fitted to the landmarks), else (only with
       ``cfg.own_map_landmarks``, off by default) of the map the sequence stored (the previous
       windows' refined surface, in the sequence's frame); none: the memory-free poses stay. Its
       poses replace the memory-free ones only when the memory-free refinement passed the gate and
       the memory is *consistent* with the window's own observations (the χ² test of
       :func:`memory_refinement`): the memory never makes a window worse than the window alone can
       tell;
    4. **update** the bank with the window posed by its final poses: merged into that map
       (:func:`cm3d.memory.update_map`), else into the map this sequence stored, else stored as a
       new map.

    Returns (bank, WindowResult, recalled, recalled_T, written)."""
    ref, poses, obs, _, n_bad = factor_graph(win, lm_, None, cfg)
    poses = poses.astype(jnp.float32)
    n_mem = jnp.zeros((), jnp.int32)
    mem_stat = mem_thr = jnp.zeros((), jnp.float32)
    used = jnp.zeros((), bool)
    if cfg.use_memory:
        entry0 = sequence_query(bank, written, window_entry(win.replace(poses=poses), mem_cfg, cfg), mem_cfg)
        M = bank.map_valid.shape[0]
        others = bank.replace(map_valid=bank.map_valid & (jnp.arange(M) != written))
        ident = memory.identify(others, entry0, mem_cfg, key)
        hit = ident.map_id >= 0
        new_map = hit & (ident.map_id != recalled)
        use_map = jnp.where(new_map, ident.map_id, recalled).astype(jnp.int32)
        use_T = jnp.where(new_map, ident.verification.transform, recalled_T).astype(jnp.float32)
        d_scene = trajectory.scene_scale(win.depth, win.static & win.valid[:, None, None])
        # without a recalled map: the surface the sequence's earlier windows stored (its own frame)
        own = cfg.own_map_landmarks & (use_map < 0) & (written >= 0)
        src = jnp.where(own, written, use_map)
        surface = memory_surface(bank, src, jnp.where(own, jnp.eye(4), use_T), d_scene)
        first = obs.valid.reshape(lm_.obs_valid.shape)[:, 0]  # tracks that passed the prior check
        pm, ok, A, matched, mem_stat, mem_thr = memory_refinement(win, lm_, ref, obs, first, surface, cfg, new_map)
        n_mem = jnp.sum(matched)
        used = (src >= 0) & ref.refined & ok
        poses = jnp.where(used, pm.astype(jnp.float32), poses)
        use_T = (use_T @ A.astype(jnp.float32)).astype(jnp.float32)
        entry = window_entry(win.replace(poses=poses), mem_cfg, cfg, cfg.map_min_support)
        # else the sequence's own map, whose frame is the sequence's (identity: exact, no ICP noise)
        target = jnp.where(use_map >= 0, use_map, written).astype(jnp.int32)
        target_T = jnp.where(use_map >= 0, use_T, jnp.eye(4)).astype(jnp.float32)
        known = target >= 0

        def merge(b):
            return memory.update_map(b, jnp.maximum(target, 0), entry, target_T, mem_cfg), target

        bank, map_id = jax.lax.cond(known, merge, lambda b: memory.insert_map(b, entry), bank)
        created = ~known & (map_id >= 0)
        written = jnp.where(created, map_id, written).astype(jnp.int32)
        recalled = use_map
        recalled_T = use_T
        report = _recall_report(ident, map_id, jnp.where(hit, ident.verification.transform, jnp.eye(4)), created,
                                target_T)
    else:
        report = _empty_report(mem_cfg.top_k)
    res = WindowResult(poses=poses, index=win.index, valid=win.valid, refined=ref.refined,
                       gate_stat=ref.gate_stat.astype(jnp.float32),
                       gate_threshold=ref.gate_threshold.astype(jnp.float32),
                       observations=jnp.sum(obs.valid).astype(jnp.int32), inliers=jnp.sum(ref.inlier).astype(jnp.int32),
                       landmarks=jnp.sum(obs.valid.reshape(lm_.obs_valid.shape)[:, 0]).astype(jnp.int32),
                       memory_landmarks=n_mem.astype(jnp.int32), iterations=ref.result.iterations.astype(jnp.int32),
                       recall=report, inconsistent=n_bad.astype(jnp.int32), memory_used=used,
                       memory_stat=mem_stat.astype(jnp.float32), memory_threshold=mem_thr.astype(jnp.float32))
    return bank, res, recalled, recalled_T, written


def _empty_result(cfg: PipelineConfig, mem_cfg: memory.MemoryConfig) -> WindowResult:
    W = cfg.window
    z = jnp.zeros((), jnp.int32)
    return WindowResult(poses=jnp.broadcast_to(jnp.eye(4, dtype=jnp.float32), (W, 4, 4)), index=jnp.zeros(W, jnp.int32),
                        valid=jnp.zeros(W, bool), refined=jnp.zeros((), bool), gate_stat=jnp.zeros(()),
                        gate_threshold=jnp.zeros(()), observations=z, inliers=z, landmarks=z, memory_landmarks=z,
                        iterations=z, recall=_empty_report(mem_cfg.top_k), inconsistent=z,
                        memory_used=jnp.zeros((), bool), memory_stat=jnp.zeros(()), memory_threshold=jnp.zeros(()))


def _bank_config(bank: memory.MemoryBank, cfg: PipelineConfig) -> memory.MemoryConfig:
    """The memory config matching the bank's capacities (a loaded bank may differ from cfg.memory)."""
    M, P, _ = bank.points.shape
    K = bank.kf_desc.shape[1]
    mc = cfg.memory
    if (M, P, K) != (mc.max_maps, mc.max_points, mc.max_keyframes):
        mc = dataclasses.replace(mc, max_maps=M, max_points=P, max_keyframes=K)
    kp = getattr(bank, "kp_points", None)
    if kp is not None and kp.shape[1] != mc.max_keypoints:
        mc = dataclasses.replace(mc, max_keypoints=kp.shape[1])
    fkp = getattr(bank, "floor_kp_points", None)
    if fkp is not None and fkp.shape[1] != mc.max_floor_keypoints:
        mc = dataclasses.replace(mc, max_floor_keypoints=fkp.shape[1])
    return mc


# ----------------------------------------------------------------------------------------------
# The step


def _put(a, i, v):
    return jax.lax.dynamic_update_index_in_dim(a, jnp.asarray(v, a.dtype), i, 0)


def step(state: MapState, inputs_t: Inputs, cfg: PipelineConfig = PipelineConfig()):
    """One frame: motion cues -> static landmarks -> (every ``keyframe_interval`` frames)
    recall / verify / update -> factor graph. Pure; ``cfg`` static. Returns (state, StepOutputs)."""
    mem_cfg = _bank_config(state.bank, cfg)
    f = inputs_t.frame
    first = state.frames == 0
    anchor_prior = jnp.where(first, f.cam_to_world, state.anchor_prior)
    anchor_pose = jnp.where(first, f.cam_to_world, state.anchor_pose)
    init_pose = anchor_pose @ se3.inverse(anchor_prior) @ f.cam_to_world
    s = state.slot

    # 1. motion cues
    dynamic, static = static_mask(inputs_t, cfg)

    # 2. static landmarks: follow the live ones into this frame, buffer the frame
    lms = jax.lax.cond(s > 0, lambda m: advance_landmarks(m, state.prev_flow, static, s, cfg), lambda m: m,
                       state.landmarks)
    desc = descriptors.image_descriptor(f.image, static, factor=max(1, 4 // cfg.stride))
    fuv = inputs_t.features.uv
    h, w = static.shape
    fr = jnp.clip(jnp.round(fuv[:, 1]).astype(jnp.int32), 0, h - 1)
    fc = jnp.clip(jnp.round(fuv[:, 0]).astype(jnp.int32), 0, w - 1)
    win = state.window
    win = win.replace(poses=_put(win.poses, s, init_pose), intrinsic=_put(win.intrinsic, s, f.intrinsic),
                      depth=_put(win.depth, s, f.depth), conf=_put(win.conf, s, f.depth_conf),
                      image=_put(win.image, s, f.image), static=_put(win.static, s, static),
                      desc=_put(win.desc, s, desc),
                      feat_uv=_put(win.feat_uv, s, fuv), feat_desc=_put(win.feat_desc, s, inputs_t.features.desc),
                      feat_valid=_put(win.feat_valid, s, inputs_t.features.valid & static[fr, fc]),
                      index=_put(win.index, s, inputs_t.index), valid=_put(win.valid, s, True))

    # 3. every keyframe_interval frames: recall / verify / update and the factor graph
    end = (s == cfg.keyframe_interval) | inputs_t.last
    key, sub = jax.random.split(state.key)

    def on_end(args):
        bank, win, lms, rec, rec_T, wr = args
        bank, res, rec, rec_T, wr = window_end(bank, sub, rec, rec_T, win, lms, mem_cfg, cfg, wr)
        pose_t = res.poses[s]
        # the new window: this frame becomes the anchor (slot 0)
        nw = jax.tree.map(lambda a: _put(jnp.zeros_like(a), 0, a[s]), win)
        nw = nw.replace(poses=jnp.broadcast_to(pose_t, win.poses.shape),  # free slots: harmless copies
                        intrinsic=jnp.broadcast_to(win.intrinsic[s], win.intrinsic.shape))
        fresh = lms.replace(alive=jnp.zeros_like(lms.alive), obs_valid=jnp.zeros_like(lms.obs_valid))
        return bank, nw, fresh, res, pose_t, f.cam_to_world, rec, rec_T, wr

    def on_continue(args):
        bank, win, lms, rec, rec_T, wr = args
        return bank, win, lms, _empty_result(cfg, mem_cfg), anchor_pose, anchor_prior, rec, rec_T, wr

    bank, win, lms, res, anchor_pose, anchor_prior, recalled, recalled_T, written = jax.lax.cond(
        end, on_end, on_continue, (state.bank, win, lms, state.recalled, state.recalled_transform, state.written))
    slot = jnp.where(end, 0, s)

    # seed landmarks at the seeding slots (slot 0 of a new window is this frame again)
    do_seed = (slot % cfg.track.keyframe_every == 0) & (slot < cfg.keyframe_interval)
    lms = jax.lax.cond(do_seed, lambda m: seed_landmarks(m, slot, f.depth, f.depth_conf, static, f.intrinsic,
                                                         win.poses[slot], cfg), lambda m: m, lms)
    new = MapState(bank=bank, key=key, window=win, landmarks=lms, prev_flow=jnp.asarray(inputs_t.flow, jnp.float32),
                   anchor_pose=anchor_pose, anchor_prior=anchor_prior, recalled=recalled,
                   recalled_transform=recalled_T, slot=slot + 1, frames=state.frames + 1, written=written)
    ok = inputs_t.valid
    new = jax.tree.map(lambda a, b: jnp.where(ok, a, b), new, state)
    out = StepOutputs(mask=dynamic & ok, init_pose=init_pose, window_end=end & ok, window=res, valid=ok)
    return new, out


def _run_sequence(state: MapState, inputs: Inputs, cfg: PipelineConfig):
    state = begin_sequence(state)
    return jax.lax.scan(functools.partial(step, cfg=cfg), state, inputs)


#: ``run_sequence(state, inputs, cfg)``: the whole sequence in one compiled ``lax.scan`` of :func:`step`
#: (the window, tracks and anchor are reset first; the memory bank carries over).
run_sequence = jax.jit(_run_sequence, static_argnames="cfg")
step_jit = jax.jit(step, static_argnames="cfg")


# ----------------------------------------------------------------------------------------------
# Host side: per-frame results and the one-call API


@dataclasses.dataclass(frozen=True, eq=False)
class WindowRecord:
    """One window's facts on the host (what ``recall.json`` lists per window).

    frames: (first, last) frame numbers; memory: the memory was on; candidates, votes, scores,
    keypoint_inliers: the recall's candidate maps (ids >= 0 only) and their evidence; accepted,
    recalled_map: the verification's decision; inlier_count, rmse, fitness, scale: its ICP facts;
    transform (4, 4): its Sim(3) window -> recalled map; placement (4, 4): the Sim(3) the memory
    priors and the merge used; map_id: the map written (-1 bank full), created_map; refined,
    gate_stat, gate_threshold: the significance gate; landmarks, memory_landmarks, memory_used,
    memory_stat, memory_threshold: the memory solve and its χ² test; inconsistent_tracks,
    observations, inliers, lm_iterations: the factor graph; chunk: the chunk of a long video
    (None for a single sequence)."""

    frames: tuple
    memory: bool
    candidates: tuple
    votes: tuple
    scores: tuple
    keypoint_inliers: tuple
    accepted: bool
    recalled_map: int
    inlier_count: int
    rmse: float
    fitness: float
    scale: float
    transform: np.ndarray
    placement: np.ndarray
    map_id: int
    created_map: bool
    refined: bool
    gate_stat: float
    gate_threshold: float
    landmarks: int
    memory_landmarks: int
    memory_used: bool
    memory_stat: float
    memory_threshold: float
    inconsistent_tracks: int
    observations: int
    inliers: int
    lm_iterations: int
    chunk: int | None = None

    @classmethod
    def from_result(cls, w: WindowResult, memory_on: bool) -> "WindowRecord":
        """The record of one window's :class:`WindowResult` (numpy, one window: no frame axis)."""
        ok = np.asarray(w.valid, bool)
        r = w.recall
        cand = [int(c) for c in r.candidates]
        keep = lambda vals, kind: tuple(kind(v) for c, v in zip(cand, vals) if c >= 0)  # noqa: E731
        return cls(
            frames=(int(w.index[ok].min()), int(w.index[ok].max())), memory=memory_on,
            candidates=tuple(c for c in cand if c >= 0), votes=keep(r.votes, float), scores=keep(r.scores, float),
            keypoint_inliers=keep(r.keypoint_inliers, int), accepted=bool(r.accepted), recalled_map=int(r.recalled),
            inlier_count=int(r.inlier_count), rmse=float(r.inlier_rmse), fitness=float(r.fitness),
            scale=float(r.scale), transform=np.asarray(r.transform, np.float64),
            placement=np.asarray(r.placement, np.float64), map_id=int(r.map_id), created_map=bool(r.created),
            refined=bool(w.refined), gate_stat=float(w.gate_stat), gate_threshold=float(w.gate_threshold),
            landmarks=int(w.landmarks), memory_landmarks=int(w.memory_landmarks), memory_used=bool(w.memory_used),
            memory_stat=float(w.memory_stat), memory_threshold=float(w.memory_threshold),
            inconsistent_tracks=int(w.inconsistent), observations=int(w.observations), inliers=int(w.inliers),
            lm_iterations=int(w.iterations))

    def to_json(self) -> dict:
        """A JSON-ready dict (lists, Python numbers; transforms rounded to 6 decimals); ``chunk`` only
        when set."""
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name == "chunk" and v is None:
                continue
            if isinstance(v, np.ndarray):
                v = v.round(6).tolist()
            elif isinstance(v, tuple):
                v = list(v)
            out[f.name] = v
        return out


def recalled_earlier_map(windows) -> bool:
    """Whether a window accepted a map that an earlier sequence stored (not one this sequence created)."""
    created = {w.map_id for w in windows if w.created_map}
    return any(w.accepted and w.recalled_map >= 0 and w.recalled_map not in created for w in windows)


@dataclasses.dataclass
class SequenceResult:
    """What the pipeline found in one sequence (numpy, input resolution).

    poses: (S, 4, 4) refined cam_to_world; prior: (S, 4, 4) the input prior; masks: (S, H, W) bool
    dynamic masks; windows: one :class:`WindowRecord` per window;
    sequence: the input :class:`cm3d.data.Sequence`."""

    poses: np.ndarray
    prior: np.ndarray
    masks: np.ndarray
    windows: list
    sequence: Any


def _upsample(mask: np.ndarray, s: int, H: int, W: int) -> np.ndarray:
    if s == 1:
        return mask[:, :H, :W]
    return np.repeat(np.repeat(mask, s, axis=1), s, axis=2)[:, :H, :W]


def collect(outputs: StepOutputs, sequence, cfg: PipelineConfig = PipelineConfig()) -> SequenceResult:
    """Per-frame results from the stacked step outputs (host): the refined pose of every frame
    (from the window that refined it), full-resolution masks and one :class:`WindowRecord` per window."""
    out = jax.tree.map(np.asarray, outputs)
    S, H, W = sequence.depth.shape
    poses = np.array(out.init_pose[:S], np.float64)
    windows = []
    for t in np.flatnonzero(out.window_end):
        w = jax.tree.map(lambda a: a[t], out.window)
        ok = w.valid.astype(bool)
        poses[w.index[ok]] = w.poses[ok]
        windows.append(WindowRecord.from_result(w, bool(cfg.use_memory)))
    masks = _upsample(out.mask[:S].astype(bool), cfg.stride, H, W)
    return SequenceResult(poses=poses, prior=np.asarray(sequence.cam_to_world, np.float64), masks=masks,
                          windows=windows, sequence=sequence)


def _device(inputs: Inputs) -> Inputs:
    return jax.tree.map(jnp.asarray, inputs)


def run(sequences, cfg: PipelineConfig = PipelineConfig(), bank: memory.MemoryBank | None = None,
        progress=None) -> tuple[memory.MemoryBank, list[SequenceResult]]:
    """The whole pipeline on one or several visits (:class:`cm3d.data.Sequence` or paths any
    loader reads), threading one state: the memory bank persists across visits.

    ``bank``: a memory bank to start from (e.g. :func:`cm3d.memory.load`); ``progress``: optional
    callable ``(stage, done, total)``. Returns (the updated bank, one :class:`SequenceResult` per visit).
    """
    from cm3d.data.loaders import load_input

    if not isinstance(sequences, (list, tuple)):
        sequences = [sequences]
    state = None
    results = []
    for i, seq in enumerate(sequences):
        if not hasattr(seq, "depth"):
            seq = load_input(seq)
        cb = None if progress is None else (lambda d, n, i=i: progress(f"visit {i}: flow", d, n))
        inputs = _device(prepare(seq, cfg, progress=cb))
        if state is None:
            state = init_state(inputs, cfg, bank)
        elif state.window.depth.shape[1:] != inputs.frame.depth.shape[1:]:
            state = init_state(inputs, cfg, state.bank)  # another image size: new buffers, same bank
        if progress is not None:
            progress(f"visit {i}: back end", 0, 1)
        state, out = run_sequence(state, inputs, cfg)
        jax.block_until_ready(out)
        if progress is not None:
            progress(f"visit {i}: back end", 1, 1)
        results.append(collect(out, seq, cfg))
    return (state.bank if state is not None else bank), results
