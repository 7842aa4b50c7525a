"""What the pipeline carries from frame to frame: :class:`MapState`, one frozen pytree."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from cm3d import memory, trajectory
from cm3d.ops import descriptors
from cm3d.pipeline.config import PipelineConfig
from cm3d.pipeline.prepare import Inputs


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
    obs_valid (L, T) observations at slots ``seed + j``; points (L, 3) lifted at seeding; patches
    (:class:`cm3d.trajectory.SeedPatches`): each seed pixel's patch, for the re-alignment."""

    uv: Any
    alive: Any
    seed: Any
    obs_uv: Any
    obs_valid: Any
    points: Any
    patches: Any


@struct.dataclass
class MemoryCursor:
    """Where the sequence stands in the memory: ``recalled``, the map recalled from an earlier one (-1
    none) with ``transform`` (4, 4) sequence -> map; ``written``, the map this sequence stored (-1 none)."""

    recalled: Any
    transform: Any
    written: Any

    @classmethod
    def none(cls) -> "MemoryCursor":
        return cls(recalled=-jnp.ones((), jnp.int32), transform=jnp.eye(4, dtype=jnp.float32),
                   written=-jnp.ones((), jnp.int32))


@struct.dataclass
class MapState:
    """Everything the pipeline remembers: the memory bank (persists across sequences), the PRNG key,
    the window, the tracks, the previous flow, the anchor (refined and prior pose of slot 0), the
    memory cursor, the slot of the next frame and frames seen."""

    bank: memory.MemoryBank
    key: Any
    window: Window
    landmarks: Landmarks
    prev_flow: Any
    anchor_pose: Any
    anchor_prior: Any
    cursor: MemoryCursor
    slot: Any
    frames: Any


def empty_window(cfg: PipelineConfig, h: int, w: int, n: int, dk: int) -> Window:
    """A window with no filled slot: images h x w, n keypoint features of dimension dk per frame."""
    W = cfg.window
    eye = jnp.broadcast_to(jnp.eye(4, dtype=jnp.float32), (W, 4, 4))
    return Window(poses=eye, intrinsic=jnp.broadcast_to(jnp.eye(3, dtype=jnp.float32), (W, 3, 3)),
                  depth=jnp.zeros((W, h, w), jnp.float32), conf=jnp.zeros((W, h, w), jnp.float32),
                  image=jnp.zeros((W, h, w, 3), jnp.uint8), static=jnp.zeros((W, h, w), bool),
                  desc=jnp.zeros((W, descriptors.IMAGE_DIM), jnp.float32),
                  feat_uv=jnp.zeros((W, n, 2), jnp.float32), feat_desc=jnp.zeros((W, n, dk), jnp.float32),
                  feat_valid=jnp.zeros((W, n), bool), index=jnp.zeros(W, jnp.int32), valid=jnp.zeros(W, bool))


def empty_landmarks(cfg: PipelineConfig, h: int, w: int) -> Landmarks:
    """No live landmark; the seeding slot of every landmark (block b seeds at slot b κ)."""
    c = cfg.track.cell
    L = cfg.seed_blocks * (h // c) * (w // c)
    T = cfg.track.track_length
    return Landmarks(uv=jnp.zeros((L, 2), jnp.float32), alive=jnp.zeros(L, bool),
                     seed=jnp.repeat(jnp.arange(cfg.seed_blocks, dtype=jnp.int32) * cfg.track.keyframe_every,
                                     (h // c) * (w // c)),
                     obs_uv=jnp.zeros((L, T, 2), jnp.float32), obs_valid=jnp.zeros((L, T), bool),
                     points=jnp.zeros((L, 3), jnp.float32), patches=trajectory.SeedPatches.empty(L, cfg.track))


def init_state(inputs: Inputs, cfg: PipelineConfig = PipelineConfig(), bank: memory.MemoryBank | None = None,
               memory_cfg: memory.MemoryConfig | None = None) -> MapState:
    """A fresh state for sequences shaped like ``inputs`` (a new or the given memory bank)."""
    h, w = inputs.frame.depth.shape[-2:]
    n, dk = inputs.features.desc.shape[-2:]
    if bank is None:
        bank = memory.empty(memory_cfg or cfg.memory)
    return _fresh_state(bank, cfg, (h, w, n, dk))


def _fresh_state(bank: memory.MemoryBank, cfg: PipelineConfig, shape: tuple) -> MapState:
    h, w, n, dk = shape
    return MapState(
        bank=bank, key=jax.random.PRNGKey(cfg.seed), window=empty_window(cfg, h, w, n, dk),
        landmarks=empty_landmarks(cfg, h, w), prev_flow=jnp.zeros((h, w, 2), jnp.float32),
        anchor_pose=jnp.eye(4, dtype=jnp.float32), anchor_prior=jnp.eye(4, dtype=jnp.float32),
        cursor=MemoryCursor.none(), slot=jnp.zeros((), jnp.int32), frames=jnp.zeros((), jnp.int32))


#: ``fresh_state(bank, cfg, shape)``: :func:`init_state` as one compiled program around a given bank
#: (``shape`` = (h, w, features per frame, feature dimension)); the values are :func:`init_state`'s.
fresh_state = jax.jit(_fresh_state, static_argnames=("cfg", "shape"))


def empty_bank_host(cfg: memory.MemoryConfig) -> memory.MemoryBank:
    """:func:`cm3d.memory.empty` without one eager dispatch per field: NumPy zeros, and the hash
    planes computed as :func:`cm3d.memory.empty` does (bitwise the same bank)."""
    spec = jax.eval_shape(lambda: memory.empty(cfg))
    bank = jax.tree.map(lambda a: np.zeros(a.shape, a.dtype), spec)
    return bank.replace(planes=descriptors.hash_planes(cfg.image_dim, cfg.hash_bits, cfg.hash_seed).astype(jnp.float32))


def begin_sequence(state: MapState) -> MapState:
    """The state at the start of a new sequence: window, tracks and anchor cleared, bank and key kept."""
    fresh = jax.tree.map(jnp.zeros_like, state)
    eye = jnp.eye(4, dtype=jnp.float32)
    win = fresh.window.replace(poses=jnp.broadcast_to(eye, fresh.window.poses.shape),
                               intrinsic=jnp.broadcast_to(jnp.eye(3, dtype=jnp.float32), fresh.window.intrinsic.shape))
    return fresh.replace(bank=state.bank, key=state.key, anchor_pose=eye, anchor_prior=eye, window=win,
                         cursor=MemoryCursor.none(), landmarks=fresh.landmarks.replace(seed=state.landmarks.seed))
