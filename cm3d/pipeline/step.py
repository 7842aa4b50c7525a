"""One frame of CogniMap3D (paper, Fig. 2) as a pure function, and its ``lax.scan`` over a sequence:
motion cues -> static landmarks -> (every ``keyframe_interval`` frames, in one ``lax.cond``) factor
graph, recall / verify / update, factor graph with memory. Fixed shapes, static config."""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from cm3d import memory
from cm3d.motion import motion_cues
from cm3d.ops import descriptors, se3
from cm3d.pipeline.config import PipelineConfig, bank_config
from cm3d.pipeline.landmarks import advance_landmarks, nearest_pixel, seed_landmarks
from cm3d.pipeline.memory_graph import MemoryStep, RecallReport, recall_verify_update
from cm3d.pipeline.prepare import Inputs
from cm3d.pipeline.state import Landmarks, MapState, MemoryCursor, Window, begin_sequence
from cm3d.pipeline.window import factor_graph, rescale_window


@struct.dataclass
class WindowResult:
    """One window's result: final poses (W, 4, 4), frame index (W,), valid (W,), the gate, graph
    counts, the :class:`RecallReport`, dropped tracks, the memory solution's use, χ² test and photometric
    test (grey errors of the memory-free and the memory solution, the sign test's p-value); the
    memory-free graph's final LM ``cost`` and its landmarks ``points`` (L, 3) at the prior depth's
    scale with ``point_valid`` (L,) (the tracks in the graph)."""

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
    inconsistent: Any
    memory_used: Any
    memory_stat: Any
    memory_threshold: Any
    photo_free: Any
    photo_memory: Any
    photo_p: Any
    cost: Any
    points: Any
    point_valid: Any

    @classmethod
    def empty(cls, cfg: PipelineConfig, top_k: int, num_landmarks: int) -> "WindowResult":
        """The result of a frame that ends no window."""
        W = cfg.window
        z = jnp.zeros((), jnp.int32)
        return cls(poses=jnp.broadcast_to(jnp.eye(4, dtype=jnp.float32), (W, 4, 4)), index=jnp.zeros(W, jnp.int32),
                   valid=jnp.zeros(W, bool), refined=jnp.zeros((), bool), gate_stat=jnp.zeros(()),
                   gate_threshold=jnp.zeros(()), observations=z, inliers=z, landmarks=z, memory_landmarks=z,
                   iterations=z, recall=RecallReport.empty(top_k), inconsistent=z,
                   memory_used=jnp.zeros((), bool), memory_stat=jnp.zeros(()), memory_threshold=jnp.zeros(()),
                   photo_free=jnp.zeros(()), photo_memory=jnp.zeros(()), photo_p=jnp.zeros(()), cost=jnp.zeros(()),
                   points=jnp.zeros((num_landmarks, 3), jnp.float32), point_valid=jnp.zeros(num_landmarks, bool))


@struct.dataclass
class StepOutputs:
    """Per frame: dynamic mask (h, w), initial pose (4, 4), window_end (``window`` holds a result), valid."""

    mask: Any
    init_pose: Any
    window_end: Any
    window: WindowResult
    valid: Any


def static_mask(inputs_t: Inputs, cfg: PipelineConfig):
    """Motion cues of frame t (pair with its partner): (dynamic mask (h, w), static (h, w))."""
    cues = motion_cues(inputs_t.frame, inputs_t.partner, inputs_t.flow, inputs_t.matches, cfg.motion,
                       flow_rev=inputs_t.flow_rev, second=inputs_t.second)
    dyn = cues.robust_mask
    return dyn, ~dyn & (inputs_t.frame.depth > 0)


def _put(a, i, v):
    return jax.lax.dynamic_update_index_in_dim(a, jnp.asarray(v, a.dtype), i, 0)


def buffer_frame(win: Window, s, inputs_t: Inputs, init_pose, static, cfg: PipelineConfig) -> Window:
    """Frame t in slot ``s``: prior, static mask, image descriptor and keypoint features on static pixels."""
    f = inputs_t.frame
    desc = descriptors.image_descriptor(f.image, static, factor=max(1, 4 // cfg.stride))
    fuv = inputs_t.features.uv
    fr, fc = nearest_pixel(fuv, *static.shape)
    return win.replace(poses=_put(win.poses, s, init_pose), intrinsic=_put(win.intrinsic, s, f.intrinsic),
                       depth=_put(win.depth, s, f.depth), conf=_put(win.conf, s, f.depth_conf),
                       image=_put(win.image, s, f.image), static=_put(win.static, s, static),
                       desc=_put(win.desc, s, desc),
                       feat_uv=_put(win.feat_uv, s, fuv), feat_desc=_put(win.feat_desc, s, inputs_t.features.desc),
                       feat_valid=_put(win.feat_valid, s, inputs_t.features.valid & static[fr, fc]),
                       index=_put(win.index, s, inputs_t.index), valid=_put(win.valid, s, True))


def window_end(bank: memory.MemoryBank, cursor: MemoryCursor, key, win: Window, lm_: Landmarks,
               mem_cfg: memory.MemoryConfig, cfg: PipelineConfig):
    """The window ending at this frame: factor graph (:func:`~cm3d.pipeline.window.factor_graph`),
    then recall / verify / update around the graph with memory
    (:func:`~cm3d.pipeline.memory_graph.recall_verify_update`). Returns (bank, cursor, WindowResult)."""
    ref, poses, obs, n_bad = factor_graph(win, lm_, cfg)
    poses = poses.astype(jnp.float32)
    in_graph = obs.valid.reshape(lm_.obs_valid.shape)[:, 0]
    points = jnp.where(ref.refined, rescale_window(ref.poses, ref.points, win.poses, lm_.points, lm_.seed,
                                                   in_graph)[1], ref.points)
    if cfg.use_memory:
        bank, cursor, mem = recall_verify_update(bank, cursor, key, win, lm_, ref, poses, obs, mem_cfg, cfg)
    else:
        mem = MemoryStep.off(poses, mem_cfg.top_k)
    res = WindowResult(poses=mem.poses, index=win.index, valid=win.valid, refined=ref.refined,
                       gate_stat=ref.gate_stat.astype(jnp.float32),
                       gate_threshold=ref.gate_threshold.astype(jnp.float32),
                       observations=jnp.sum(obs.valid).astype(jnp.int32), inliers=jnp.sum(ref.inlier).astype(jnp.int32),
                       landmarks=jnp.sum(obs.valid.reshape(lm_.obs_valid.shape)[:, 0]).astype(jnp.int32),
                       memory_landmarks=mem.landmarks, iterations=ref.result.iterations.astype(jnp.int32),
                       recall=mem.report, inconsistent=n_bad.astype(jnp.int32), memory_used=mem.used,
                       memory_stat=mem.stat, memory_threshold=mem.threshold, photo_free=mem.photo_free,
                       photo_memory=mem.photo_memory, photo_p=mem.photo_p,
                       cost=ref.result.cost.astype(jnp.float32), points=points.astype(jnp.float32),
                       point_valid=in_graph)
    return bank, cursor, res


def _close_window(st: MapState, key, s, frame_prior, mem_cfg, cfg: PipelineConfig):
    """Window end: refine and remember it; this frame becomes slot 0 (the anchor) of a fresh window."""
    bank, cursor, res = window_end(st.bank, st.cursor, key, st.window, st.landmarks, mem_cfg, cfg)
    win = st.window
    pose_t = res.poses[s]
    nw = jax.tree.map(lambda a: _put(jnp.zeros_like(a), 0, a[s]), win)
    nw = nw.replace(poses=jnp.broadcast_to(pose_t, win.poses.shape),  # free slots: harmless copies
                    intrinsic=jnp.broadcast_to(win.intrinsic[s], win.intrinsic.shape))
    lms = st.landmarks
    fresh = lms.replace(alive=jnp.zeros_like(lms.alive), obs_valid=jnp.zeros_like(lms.obs_valid))
    return st.replace(bank=bank, cursor=cursor, window=nw, landmarks=fresh, anchor_pose=pose_t,
                      anchor_prior=frame_prior), res


def step(state: MapState, inputs_t: Inputs, cfg: PipelineConfig = PipelineConfig()):
    """One frame: motion cues -> static landmarks -> (every ``keyframe_interval`` frames) factor
    graph, recall / verify / update, factor graph with memory. Pure; ``cfg`` static.
    Returns (state, StepOutputs)."""
    mem_cfg = bank_config(state.bank, cfg)
    f = inputs_t.frame
    first = state.frames == 0
    st = state.replace(anchor_prior=jnp.where(first, f.cam_to_world, state.anchor_prior),
                       anchor_pose=jnp.where(first, f.cam_to_world, state.anchor_pose))
    init_pose = st.anchor_pose @ se3.inverse(st.anchor_prior) @ f.cam_to_world
    s = state.slot

    # 1. motion cues
    dynamic, static = static_mask(inputs_t, cfg)

    # 2. static landmarks: follow the live ones into this frame, buffer the frame
    follow = functools.partial(advance_landmarks, flow=state.prev_flow, static=static, slot=s, cfg=cfg,
                               image=f.image)
    lms = jax.lax.cond(s > 0, follow, lambda m: m, state.landmarks)
    st = st.replace(window=buffer_frame(st.window, s, inputs_t, init_pose, static, cfg), landmarks=lms)

    # 3. every keyframe_interval frames: factor graph, recall / verify / update, factor graph with memory
    end = (s == cfg.keyframe_interval) | inputs_t.last
    key, sub = jax.random.split(state.key)
    st, res = jax.lax.cond(end, functools.partial(_close_window, key=sub, s=s, frame_prior=f.cam_to_world,
                                                  mem_cfg=mem_cfg, cfg=cfg),
                           lambda m: (m, WindowResult.empty(cfg, mem_cfg.top_k, state.landmarks.points.shape[0])),
                           st)
    slot = jnp.where(end, 0, s)

    # seed landmarks at the seeding slots (slot 0 of a new window is this frame again)
    do_seed = (slot % cfg.track.keyframe_every == 0) & (slot < cfg.keyframe_interval)
    lms = jax.lax.cond(do_seed, lambda m: seed_landmarks(m, slot, f.image, f.depth, f.depth_conf, static, f.intrinsic,
                                                         st.window.poses[slot], cfg), lambda m: m, st.landmarks)
    new = st.replace(key=key, landmarks=lms, prev_flow=jnp.asarray(inputs_t.flow, jnp.float32), slot=slot + 1,
                     frames=state.frames + 1)
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


def _step_or_skip(state: MapState, inputs_t: Inputs, cfg: PipelineConfig):
    """:func:`step` on a real frame; a padding frame (``valid`` False) costs nothing: the state is
    kept and the outputs are zeros (what :func:`step` gives a padding frame, but for ``init_pose``
    and ``window``, which nothing reads where ``window_end`` is False)."""
    def skip(st, x):
        empty = WindowResult.empty(cfg, bank_config(st.bank, cfg).top_k, st.landmarks.points.shape[0])
        no = jnp.zeros((), bool)
        return st, StepOutputs(mask=jnp.zeros(x.frame.depth.shape, bool), init_pose=jnp.zeros((4, 4), jnp.float32),
                               window_end=no, window=empty, valid=no)

    return jax.lax.cond(inputs_t.valid, functools.partial(step, cfg=cfg), skip, state, inputs_t)


def _run_frames(state: MapState, inputs: Inputs, fresh, cfg: PipelineConfig):
    state = jax.tree.map(lambda a, b: jnp.where(fresh, a, b), begin_sequence(state), state)
    return jax.lax.scan(functools.partial(_step_or_skip, cfg=cfg), state, inputs)


#: ``run_frames(state, inputs, fresh, cfg)``: the next frames of a sequence in one compiled
#: ``lax.scan`` of :func:`step`, continuing ``state``; ``fresh`` (bool scalar, traced): these frames
#: start a new sequence (the reset of :func:`run_sequence` first). One program serves every piece of
#: every sequence length: :func:`cm3d.pipeline.prepare.prepare_chunks` cuts the padded sequence
#: into pieces of ``keyframe_interval`` frames; padding frames are skipped (:func:`_step_or_skip`).
run_frames = jax.jit(_run_frames, static_argnames="cfg")
