"""Long videos: stitch overlapping, separately normalised chunks into one trajectory.

VGGT runs out of memory beyond a few dozen frames, so a long video is run in overlapping chunks.
Each chunk comes back in its own frame (its first camera is the identity) and its own scale (unit
mean point distance). :func:`naive_stitch`, the common approach, places each chunk rigidly on the
previous chunk's pose of their first shared frame and ignores the scale: one noisy frame and a
scale jump per boundary, compounding along the video. :func:`stitch_chunks`:

1. **align** each pair of consecutive chunks by a Sim(3) ``A_k`` (chunk k -> chunk k-1): robust
   Umeyama (:func:`cm3d.solvers.align.umeyama`) on the shared frames' camera centres plus a grid of
   the same pixels lifted to 3D with each chunk's depth, intrinsics and pose (the same pixel of the
   same frame: no matching needed), Cauchy-reweighted (IRLS, MAD scale) against depth noise;
2. **chain** ``G_k = G_{k-1} A_k`` into chunk 0's frame and scale; chunk k's poses become
   ``G_k ∘ P`` (rotation ``R_G R``, translation ``s_k R_G t + t_G``) and its depths ``s_k d``;
3. **fuse**: one entry per frame; a shared frame blends both chunks' poses (weighted translation,
   chordal rotation mean), depths, confidences and intrinsics with weights ramping across the
   overlap, so the trajectory has no step at a boundary;
4. **refine** the whole merged trajectory (:func:`refine_frames`): one pose graph over every frame
   (:func:`frame_graph`, a :class:`cm3d.solvers.factors.FactorGraph`), a prior per frame at its
   stitched pose and a relative-motion factor per consecutive frame pair measured from the images
   (:func:`measure_frame_pairs`: optical flow + both frames' depth -> robust Sim(3)), across chunk
   boundaries alike; noise levels by robust variance component estimation, poor or implausible
   pairs dropped, solved by Levenberg–Marquardt with an O(S) block-tridiagonal solve
   (:func:`solve_frame_graph`), kept only when it stays within the noise the overlaps measured.
   (``refine="landmarks"``: the landmark factor graph instead, :func:`refine_checked`; it has no
   depth factor and its monocular scale drifts over a long video.)

5. (:func:`stitch_with_memory`) the chunks run through the pipeline threading one memory bank; a
   chunk that revisits an earlier chunk's place recalls its map, each such recall is a Sim(3) loop
   constraint (optionally re-measured frame to frame, :func:`measure_loop`), a Sim(3) pose graph
   over the chunk transforms (overlap + loop constraints, :func:`sim3_pose_graph`) places the
   chunks' priors, and step 4 refines the whole trajectory.

API (stable: ``cm3d run`` calls it when given several inputs)::

    chunks = load_chunks(["c0.npz", "c1.npz", ...])   # or load_chunks("all.npz") with a `chunk` key
    res = stitch_chunks(chunks, overlap=None, config=StitchConfig(), static=None, refine=True)
    res.sequence       # merged Sequence: one entry per frame, chunk 0's frame and scale (refined poses)
    res.poses_aligned  # the stitched priors
    res.boundaries     # per boundary: relative scale, rotation, overlap residuals, inlier share
    res.summary()      # flat JSON-ready dict
    base = naive_stitch(chunks, overlap=None)            # the baseline, also a StitchResult
    mem = stitch_with_memory(chunks, bank=None)          # memory recall across chunks + Sim(3) pose graph

Costs: alignment and fusion take about a second for 200 frames after compilation; ``refine=True``
adds one optical flow and one robust fit per consecutive frame pair and four small pose-graph
solves (~3-4 s for 200 frames at 96x128 on 2 cores after a ~5 s compilation). ``static`` (the
motion cue's ``1 − M_dyn`` of the merged frames) restricts the refinement to static pixels.

Chunk layout: chunks are given in temporal order and chunk k's first ``o_k`` frames are chunk k-1's
last ``o_k`` frames. ``overlap`` is one int for every boundary, or None to infer each ``o_k`` from
timestamps (the leading timestamps of chunk k that chunk k-1's last ``o_k`` timestamps repeat, to a
quarter of the frame interval). Constraints: ``1 <= o_k < len(chunk k)`` and ``o_k + o_{k+1} <=
len(chunk k)`` (no frame in three chunks); every chunk has the same image size. The merged
timestamps are the chunks' when they agree on the shared frames, else frame indices 0..S-1.
A single chunk is valid: it is returned as it is (identity transform, no boundaries), refined when
``refine`` is set. Problems raise :class:`StitchError` (a ``ValueError``) naming the chunk and field;
a malformed chunk raises :class:`cm3d.data.io.SequenceFormatError` naming ``chunks[k]`` and the key.

One file holding every chunk (:func:`save_chunks`, read by :func:`load_chunks`): the chunks'
frames concatenated in order (shared frames repeated) in the sequence format
(:mod:`cm3d.data.io`) plus a ``chunk`` key, (S_total,) int, the chunk index of each frame
(0, 1, ... in non-decreasing order). ``gt_flow`` pairs that straddle two chunks are zeros; the
file's meta is ``{"chunks": [meta of chunk 0, meta of chunk 1, ...]}``.

The numerics (alignment, chaining, fusion, refinement) are pure, jitted JAX with shapes fixed per
chunk size; only the chunk bookkeeping, flow (OpenCV) and file I/O run on the host.
Poses are cam_to_world 4x4 (:mod:`cm3d.ops.se3`).
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from cm3d import trajectory
from cm3d.data import io
from cm3d.data.atomic import atomic_write
from cm3d.data.sequence import GroundTruth, Sequence
from cm3d.eval.metrics import ate
from cm3d.ops import flow as oflow
from cm3d.ops import se3
from cm3d.solvers import factors, lm
from cm3d.solvers.align import umeyama_transform
from cm3d.ops.robust import masked_median

__all__ = ["Boundary", "FrameGraphConfig", "LoopClosure", "PoseGraphConfig", "StitchConfig", "StitchError",
           "StitchResult", "align_overlap", "chunk_layout", "concat_chunks", "frame_graph",
           "frame_pair_points", "fuse_frames", "lift_pixels", "load_chunks", "loop_to_prior_frames",
           "measure_frame_pairs", "measure_loop", "memory_config_for_chunks", "memory_sequence_result",
           "naive_stitch", "place_chunks", "place_poses", "recall_loops", "refine_checked", "refine_frames",
           "refine_poses", "robust_sim3", "save_chunks", "sim3_pose_graph", "solve_frame_graph", "split_chunks",
           "stitch_chunks",
           "stitch_with_memory", "window_frame_change"]


class StitchError(ValueError):
    """Chunks that cannot be stitched (layout, sizes, overlap); the message names chunk and field."""


@dataclasses.dataclass(frozen=True)
class StitchConfig:
    """Options of :func:`stitch_chunks` (all static).

    grid: (rows, cols) pixels sampled on every shared frame for the Sim(3) fit; centre_weight: the
    camera centres' total weight relative to the sampled points'; robust_iterations, robust_k: IRLS
    rounds and the Cauchy scale in robust sigmas (1.4826 MAD of the point residuals);
    inlier_sigmas: residuals within this many robust sigmas count as inliers in the diagnostics.
    track: landmark tracking of the refinement (None: cell ``max(8, W // 20)`` px, keyframes every
    3 frames, tracks of 10 frames); refinement: the factor graph's options; flow: OpenCV flow;
    backward_flow: also compute backward flow for a forward-backward track check;
    max_scale_change: a refinement that needs a larger scale factor (or smaller than its inverse)
    to match the stitched trajectory's scale has collapsed and is refused; max_deviation: a
    refinement that moves the trajectory by more than this many times the per-frame centre noise
    measured on the overlaps is refused (see :func:`refine_checked`).
    """

    grid: tuple[int, int] = (12, 16)
    centre_weight: float = 1.0
    robust_iterations: int = 8
    robust_k: float = 2.0
    inlier_sigmas: float = 3.0
    track: trajectory.TrackConfig | None = None
    refinement: trajectory.RefineConfig = trajectory.RefineConfig(
        solver=lm.LMOptions(backward="none", max_iterations=50))
    flow: oflow.FlowConfig = oflow.FlowConfig()
    backward_flow: bool = True
    max_scale_change: float = 3.0
    max_deviation: float = 2.0

    def __post_init__(self):
        if len(self.grid) != 2 or min(self.grid) < 1:
            raise ValueError(f"StitchConfig.grid: expected (rows, cols) >= 1, got {self.grid}")
        if not self.max_scale_change > 1:
            raise ValueError(f"StitchConfig.max_scale_change: must be > 1, got {self.max_scale_change}")
        if not self.max_deviation > 0:
            raise ValueError(f"StitchConfig.max_deviation: must be > 0, got {self.max_deviation}")
        for name in ("centre_weight", "robust_k", "inlier_sigmas"):
            if not getattr(self, name) >= 0 or (name != "centre_weight" and getattr(self, name) == 0):
                raise ValueError(f"StitchConfig.{name}: must be > 0, got {getattr(self, name)}")
        if self.robust_iterations < 0:
            raise ValueError(f"StitchConfig.robust_iterations: must be >= 0, got {self.robust_iterations}")

    def track_config(self, width: int) -> trajectory.TrackConfig:
        """The tracking options for images ``width`` pixels wide."""
        if self.track is not None:
            return self.track
        return trajectory.TrackConfig(cell=max(8, width // 20), keyframe_every=3, track_length=10)


@dataclasses.dataclass(frozen=True)
class Boundary:
    """Diagnostics of the boundary between chunks ``chunk - 1`` and ``chunk``.

    frames: global [start, stop) of the shared frames; scale: the previous chunk's units per unit of
    this chunk (the scale of ``A_k``; 1 for naive stitching); cumulative_scale: common units per unit
    of ``chunk``; rotation_deg: the rotation of ``A_k``; rmse_points / rmse_centres: residuals of
    the inlier lifted pixels / of the camera centres after alignment, common units; rel_rmse_points:
    rmse_points over the shared pixels' median distance to their camera (unitless); inlier_fraction: share of
    the valid lifted pixels within ``inlier_sigmas`` robust sigmas; num_points: valid lifted pixels.
    """

    chunk: int
    frames: tuple[int, int]
    scale: float
    cumulative_scale: float
    rotation_deg: float
    rmse_points: float
    rmse_centres: float
    rel_rmse_points: float
    inlier_fraction: float
    num_points: int


@dataclasses.dataclass(frozen=True)
class StitchResult:
    """A stitched long video.

    sequence: merged :class:`Sequence` (S frames, chunk 0's frame and scale; ``cam_to_world`` the
    refined poses when refined, else the aligned ones; fused depth, confidence and intrinsics;
    ground truth merged when every chunk has it); poses_aligned (S, 4, 4): after align + chain +
    fuse (the stitched priors); poses_refined (S, 4, 4) or None: the whole-trajectory refinement's
    output (:func:`refine_frames`: refined when kept, else the stitched priors; with
    ``refine="landmarks"`` the factor graph's poses whatever its gate decided);
    chunk_transforms (K, 4, 4): ``G_k`` chunk k -> common (``[s R, t]``); ranges: global [start, stop)
    per chunk; frame_chunk (S,): the chunk each frame's image and ground truth come from;
    boundaries: one :class:`Boundary` per boundary; refined: the gate kept the refinement;
    refinement: facts of the refinement (observations, inliers, gate statistic, seconds, ...);
    method: "cm3d", "naive" or "cm3d-memory" (:func:`stitch_with_memory`; then ``poses_aligned`` is
    the chained alignment before the pose graph, ``loops`` the :class:`LoopClosure` list, ``bank``
    the memory bank after every chunk and ``results`` the pipeline's per-chunk results).
    """

    sequence: Sequence
    poses_aligned: np.ndarray
    poses_refined: np.ndarray | None
    chunk_transforms: np.ndarray
    ranges: tuple[tuple[int, int], ...]
    frame_chunk: np.ndarray
    boundaries: tuple[Boundary, ...]
    refined: bool
    refinement: dict
    method: str
    loops: tuple = ()
    bank: object = None
    results: tuple = ()

    def summary(self) -> dict:
        """Flat, JSON-ready facts: chunk count, frames, per-boundary scales and residuals, refinement."""
        out = {"method": self.method, "num_chunks": len(self.ranges), "num_frames": self.sequence.num_frames,
               "refined": bool(self.refined)}
        for b in self.boundaries:
            for k in ("scale", "rotation_deg", "rmse_points", "rmse_centres", "rel_rmse_points", "inlier_fraction"):
                out[f"boundary{b.chunk}_{k}"] = float(getattr(b, k))
        out.update({f"refine_{k}": v for k, v in self.refinement.items()
                    if not isinstance(v, (list, tuple, dict, np.ndarray))})
        return out


# ----------------------------------------------------------------------------------------------
# Layout and validation (host)


def _check_chunks(chunks) -> list[Sequence]:
    if isinstance(chunks, Sequence) or not isinstance(chunks, (list, tuple)):
        raise StitchError(f"chunks: expected a list of Sequence, got {type(chunks).__name__}")
    if len(chunks) == 0:
        raise StitchError("chunks: empty list, need at least one chunk")
    for k, c in enumerate(chunks):
        if not isinstance(c, Sequence):
            raise StitchError(f"chunks[{k}]: expected a Sequence, got {type(c).__name__}")
        io.validate_sequence(c, source=f"chunks[{k}]")
    hw = chunks[0].image_size
    for k, c in enumerate(chunks[1:], 1):
        if c.image_size != hw:
            raise StitchError(f"chunks[{k}]: images are {c.image_size[0]}x{c.image_size[1]}, chunk 0's "
                              f"{hw[0]}x{hw[1]}: every chunk must have the same image size (intrinsics "
                              "and depth maps are per pixel)")
    return list(chunks)


def _frame_interval(chunks) -> float:
    d = np.concatenate([np.diff(np.asarray(c.timestamps, np.float64)) for c in chunks])
    d = d[d > 0]
    return float(np.median(d)) if d.size else 1.0


def chunk_layout(chunks, overlap: int | None = None):
    """Global frame ranges of the chunks and the overlap of each boundary.

    overlap: one int for every boundary, or None to infer each from timestamps (see the module
    docstring). Returns (ranges: tuple of (start, stop), overlaps: tuple of K-1 ints, timestamps
    (S,) float64 merged: the chunks' when consistent, else 0..S-1). Raises :class:`StitchError`.
    """
    chunks = _check_chunks(chunks)
    K = len(chunks)
    n = [c.num_frames for c in chunks]
    tol = 0.25 * _frame_interval(chunks)
    if overlap is not None:
        if isinstance(overlap, bool) or not isinstance(overlap, (int, np.integer)):
            raise StitchError(f"overlap: expected an int or None, got {type(overlap).__name__}")
        overlaps = [int(overlap)] * (K - 1)
    else:
        overlaps = []
        for k in range(1, K):
            ta, tb = np.asarray(chunks[k - 1].timestamps, np.float64), np.asarray(chunks[k].timestamps, np.float64)
            o = int(np.sum(tb <= ta[-1] + tol))
            if o == 0:
                raise StitchError(f"chunks[{k}]: does not overlap chunks[{k - 1}] (its first timestamp "
                                  f"{tb[0]:g} is after the previous chunk's last {ta[-1]:g}); consecutive "
                                  "chunks must share at least one frame")
            if o >= n[k] or o > n[k - 1] or np.any(np.abs(tb[:o] - ta[-o:]) > tol):
                raise StitchError(f"chunks[{k}]: timestamps ({tb[0]:g} .. {tb[-1]:g}) do not continue "
                                  f"chunks[{k - 1}]'s ({ta[0]:g} .. {ta[-1]:g}) with shared frames: per-chunk "
                                  "frame indices? pass overlap= explicitly")
            overlaps.append(o)
    for k, o in enumerate(overlaps, 1):
        if o < 1:
            raise StitchError(f"overlap: chunks[{k - 1}] and chunks[{k}] share {o} frames; need at least 1")
        if o >= n[k] or o > n[k - 1]:
            raise StitchError(f"overlap: {o} shared frames between chunks[{k - 1}] ({n[k - 1]} frames) and "
                              f"chunks[{k}] ({n[k]} frames): chunk {k} must add at least one new frame")
    for k in range(1, K - 1):
        if overlaps[k - 1] + overlaps[k] > n[k]:
            raise StitchError(f"overlap: chunks[{k}] ({n[k]} frames) shares {overlaps[k - 1]} frames with "
                              f"the previous chunk and {overlaps[k]} with the next: a frame would be in "
                              "three chunks")
    ranges, start = [], 0
    for k in range(K):
        if k:
            start = ranges[-1][1] - overlaps[k - 1]
        ranges.append((start, start + n[k]))
    S = ranges[-1][1]
    ts = np.arange(S, dtype=np.float64)
    consistent = all(
        np.all(np.abs(np.asarray(chunks[k].timestamps[:o]) - np.asarray(chunks[k - 1].timestamps[-o:])) <= tol)
        for k, o in enumerate(overlaps, 1))
    if consistent:
        for (a, b), c in zip(ranges, chunks):
            ts[a:b] = c.timestamps
        consistent = bool(np.all(np.diff(ts) > 0))
    if not consistent:
        ts = np.arange(S, dtype=np.float64)
    return tuple(ranges), tuple(overlaps), ts


def _blend_weights(ranges, overlaps) -> list[np.ndarray]:
    """Per chunk, per frame fusion weights: 1 inside, ramping across each overlap (sum 1 per frame)."""
    K = len(ranges)
    out = []
    for k, (a, b) in enumerate(ranges):
        w = np.ones(b - a)
        if k > 0:
            o = overlaps[k - 1]
            w[:o] = (np.arange(o) + 0.5) / o
        if k < K - 1:
            o = overlaps[k]
            w[b - a - o:] = 1.0 - (np.arange(o) + 0.5) / o
        out.append(w)
    return out


# ----------------------------------------------------------------------------------------------
# Alignment, chaining, fusion (jnp)


def _sample_grid(H: int, W: int, grid):
    rows = ((np.arange(grid[0]) + 0.5) * H / grid[0]).astype(np.int32)
    cols = ((np.arange(grid[1]) + 0.5) * W / grid[1]).astype(np.int32)
    return rows, cols


def lift_pixels(depth, intrinsic, cam_to_world, rows, cols):
    """Pixels ``rows x cols`` of frames (O, H, W) lifted to world points -> ((O * P, 3), valid (O * P,)).

    depth (O, H, W) camera z; intrinsic (O, 3, 3); cam_to_world (O, 4, 4); rows (R,), cols (C,) int.
    """
    d = depth[:, rows[:, None], cols[None, :]].reshape(depth.shape[0], -1)  # (O, P)
    v, u = jnp.meshgrid(rows, cols, indexing="ij")
    uv1 = jnp.stack([u.ravel(), v.ravel(), jnp.ones(u.size, jnp.int32)], -1).astype(cam_to_world.dtype)
    rays = jnp.einsum("oij,pj->opi", jnp.linalg.inv(intrinsic), uv1)
    ok = jnp.isfinite(d) & (d > 0)
    pc = rays * jnp.where(ok, d, 0.0)[..., None]
    pw = jnp.einsum("oij,opj->opi", cam_to_world[:, :3, :3], pc) + cam_to_world[:, None, :3, 3]
    return pw.reshape(-1, 3), ok.reshape(-1)


_lift_jit = jax.jit(lift_pixels)


def _apply_sim3(A, x):
    return x @ A[:3, :3].T + A[:3, 3]


def _scale_of(A):
    return jnp.cbrt(jnp.linalg.det(A[..., :3, :3]))


def _overlap_correspondences(prev, nxt, rows, cols, centre_weight):
    """src (chunk k) and dst (chunk k-1) points: lifted pixels then camera centres; base weights."""
    pa, oka = lift_pixels(prev[0], prev[1], prev[2], rows, cols)
    pb, okb = lift_pixels(nxt[0], nxt[1], nxt[2], rows, cols)
    ok = oka & okb
    O = prev[2].shape[0]
    npts = jnp.sum(ok)
    wc = jnp.where(npts > 0, centre_weight * npts / O, 1.0)
    src = jnp.concatenate([pb, nxt[2][:, :3, 3]])
    dst = jnp.concatenate([pa, prev[2][:, :3, 3]])
    w0 = jnp.concatenate([ok.astype(src.dtype), jnp.full((O,), wc, src.dtype)])
    is_pt = jnp.concatenate([ok, jnp.zeros(O, bool)])
    centres = jnp.repeat(prev[2][:, :3, 3], rows.size * cols.size, 0)
    depth_a = jnp.where(oka, jnp.linalg.norm(pa - centres, axis=-1), 0.0)  # distance to the camera
    return src, dst, w0, is_pt, masked_median(depth_a, oka)


def _residual_stats(A, src, dst, is_pt):
    """Residual norms (N,) of ``A src - dst`` and the robust sigma of the point residuals (> 0)."""
    r = jnp.linalg.norm(_apply_sim3(A, src) - dst, axis=-1)
    spread = jnp.sqrt(jnp.mean(jnp.sum((dst - jnp.mean(dst, 0)) ** 2, -1)))
    sigma = jnp.maximum(1.4826 * masked_median(r, is_pt), 1e-9 * spread + 1e-300)
    return r, sigma


def _irls_sim3(src, dst, w0, resid, iterations: int, k: float):
    """Weighted Umeyama Sim(3) ``dst ≈ A src``, then ``iterations`` IRLS rounds with Cauchy weights
    ``w0 / (1 + (r / (k σ))^2)``; ``resid(A)`` -> (residual norms, robust σ)."""
    A = umeyama_transform(src, dst, w0, with_scale=True)

    def irls(A, _):
        r, sigma = resid(A)
        An = umeyama_transform(src, dst, w0 / (1.0 + (r / (k * sigma)) ** 2), with_scale=True)
        return jnp.where(jnp.all(jnp.isfinite(An)), An, A), None

    return jax.lax.scan(irls, A, None, length=iterations)[0]


@functools.partial(jax.jit, static_argnames=("cfg", "fit"))
def align_overlap(prev, nxt, A0=None, cfg: StitchConfig = StitchConfig(), fit: bool = True):
    """Sim(3) ``A`` (4x4, ``[s R, t]``) mapping chunk k's frame to chunk k-1's, from their shared frames.

    prev, nxt: (depth (O, H, W), intrinsic (O, 3, 3), cam_to_world (O, 4, 4)) of the O shared frames
    in chunk k-1 and chunk k. Correspondences: the ``cfg.grid`` pixels of every shared frame lifted
    with each chunk's own depth and pose (valid where both depths are positive), plus the camera
    centres (total weight ``centre_weight`` x the points'). Weighted Umeyama, then
    ``robust_iterations`` IRLS rounds with Cauchy weights ``1 / (1 + (r / (k σ))^2)``, ``σ`` = 1.4826
    x the median point residual. With ``fit=False`` only the diagnostics of the given ``A0`` are
    computed. Returns (A, dict of scalars: scale, rotation_deg, rmse_points, rmse_centres,
    inlier_fraction, num_points, median_depth; lengths in chunk k-1's units).
    """
    H, W = prev[0].shape[1:]
    rows, cols = (jnp.asarray(a) for a in _sample_grid(H, W, cfg.grid))
    src, dst, w0, is_pt, med_depth = _overlap_correspondences(prev, nxt, rows, cols, cfg.centre_weight)
    n_pt = jnp.sum(is_pt)
    if fit:
        A = _irls_sim3(src, dst, w0, lambda A: _residual_stats(A, src, dst, is_pt), cfg.robust_iterations,
                       cfg.robust_k)
    else:
        A = jnp.asarray(A0, src.dtype)
    r, sigma = _residual_stats(A, src, dst, is_pt)
    inl = is_pt & (r <= cfg.inlier_sigmas * sigma)
    n_in = jnp.sum(inl)
    cen = jnp.arange(src.shape[0]) >= src.shape[0] - prev[2].shape[0]
    s = _scale_of(A)
    diag = {
        "scale": s,
        "rotation_deg": jnp.rad2deg(se3.rotation_angle(A[:3, :3] / s)),
        "rmse_points": jnp.sqrt(jnp.sum(jnp.where(inl, r * r, 0.0)) / jnp.maximum(n_in, 1)),
        "rmse_centres": jnp.sqrt(jnp.sum(jnp.where(cen, r * r, 0.0)) / jnp.maximum(jnp.sum(cen), 1)),
        "inlier_fraction": n_in / jnp.maximum(n_pt, 1),
        "num_points": n_pt,
        "median_depth": med_depth,
    }
    return A, diag


@jax.jit
def place_poses(G, poses):
    """Poses (N, 4, 4) of a chunk moved by the similarity ``G`` (4x4 ``[s R, t]``): rigid poses
    ``[R R_i, s R t_i + t]`` in G's target frame and units."""
    sR = G[:3, :3]
    R = sR / _scale_of(G)
    return se3.make_pose(jnp.einsum("ij,njk->nik", R, poses[:, :3, :3]), poses[:, :3, 3] @ sR.T + G[:3, 3])


@functools.partial(jax.jit, static_argnames=("num_frames",))
def fuse_frames(frame, weight, poses, depth, conf, intrinsic, *, num_frames: int):
    """Fuse per-chunk copies of frames into one per frame.

    frame (N,) int global frame of each copy; weight (N,) >= 0 summing to 1 per frame; poses
    (N, 4, 4) in the common frame; depth (N, H, W) common units, conf (N, H, W), intrinsic
    (N, 3, 3). Poses: weighted translation and chordal rotation mean (SVD projection of the
    weighted sum); depth: weighted mean over the copies with positive depth (0 when none);
    confidence and intrinsics: weighted means. -> (poses, depth, conf, intrinsic) of (num_frames, ...).
    """
    seg = functools.partial(jax.ops.segment_sum, segment_ids=frame, num_segments=num_frames)
    t = seg(weight[:, None] * poses[:, :3, 3])
    R = se3.orthonormalize(seg(weight[:, None, None] * poses[:, :3, :3]))
    wm = weight.astype(depth.dtype)[:, None, None]  # maps stay in their (float32) dtype
    wd = wm * (depth > 0)
    den = seg(wd)
    d = jnp.where(den > 0, seg(wd * depth) / jnp.where(den > 0, den, 1.0), 0.0)
    c = seg(wm * conf)
    K = seg(weight[:, None, None] * intrinsic)
    return se3.make_pose(R, t), d, c, K


# ----------------------------------------------------------------------------------------------
# Merging (host bookkeeping around the jitted numerics)


def _f(a):
    return jnp.asarray(a, jnp.float64)


def _merge(chunks, ranges, overlaps, ts, G, method: str, weights=None):
    """Merged Sequence from the chunks placed by the similarities G (K, 4, 4)."""
    S = ranges[-1][1]
    weights = _blend_weights(ranges, overlaps) if weights is None else weights
    frame = np.concatenate([np.arange(a, b) for a, b in ranges])
    w = np.concatenate(weights)
    placed = np.concatenate([np.asarray(place_poses(_f(G[k]), _f(c.cam_to_world))) for k, c in enumerate(chunks)])
    scales = [float(np.cbrt(np.linalg.det(G[k][:3, :3]))) for k in range(len(chunks))]
    depth = np.concatenate([(c.depth * scales[k]).astype(np.float32) for k, c in enumerate(chunks)])
    conf = np.concatenate([c.depth_conf for c in chunks]).astype(np.float32)
    K = np.concatenate([c.intrinsic for c in chunks])
    poses, d, cf, Kf = fuse_frames(jnp.asarray(frame), _f(w), _f(placed), jnp.asarray(depth), jnp.asarray(conf),
                                   _f(K), num_frames=S)
    # images and ground truth: from the copy of largest weight (the earlier chunk on ties)
    primary = np.full(S, -1)
    best = np.full(S, -1.0)
    for i, (f, wi) in enumerate(zip(frame, w)):
        if wi > best[f] + 1e-12:
            best[f], primary[f] = wi, i
    frame_chunk = np.searchsorted(np.cumsum([b - a for a, b in ranges]), primary, side="right")
    images = np.concatenate([c.images for c in chunks])[primary]
    gt = _merge_gt(chunks, ranges, primary)
    meta = {k: v for k, v in chunks[0].meta.items() if k not in ("chunk", "chunk_start", "chunk_stop")}
    meta["stitched"] = {"method": method, "num_chunks": len(chunks), "ranges": [list(r) for r in ranges],
                        "overlaps": list(overlaps), "chunk_scales": scales}
    seq = Sequence(images=images, depth=np.asarray(d, np.float32), depth_conf=np.asarray(cf, np.float32),
                   intrinsic=np.asarray(Kf, np.float64), cam_to_world=np.asarray(poses, np.float64),
                   timestamps=ts, gt=gt, meta=meta)
    return seq, frame_chunk


def _merge_gt(chunks, ranges, primary):
    if any(c.gt is None for c in chunks):
        return None
    gts = [c.gt for c in chunks]
    cat = lambda name: np.concatenate([getattr(g, name) for g in gts])  # noqa: E731
    dyn = None if any(g.dynamic_mask is None for g in gts) else cat("dynamic_mask")[primary]
    flow = None
    if all(g.flow is not None for g in gts):
        S = ranges[-1][1]
        flow = np.zeros((S - 1,) + gts[0].flow.shape[1:], np.float32)
        for (a, b), g in zip(ranges, gts):  # later chunks overwrite shared pairs: identical ground truth
            flow[a:b - 1] = g.flow
    return GroundTruth(cam_to_world=cat("cam_to_world")[primary], depth=cat("depth")[primary],
                       intrinsic=cat("intrinsic")[primary], dynamic_mask=dyn, flow=flow)


def _shared(chunk: Sequence, sl: slice):
    return (_f(chunk.depth[sl]), _f(chunk.intrinsic[sl]), _f(chunk.cam_to_world[sl]))


def _boundaries(chunks, ranges, overlaps, G, A, cfg: StitchConfig, fit: bool):
    """Fit (or evaluate) every boundary's A_k; returns (A (K, 4, 4), G chained, Boundary list)."""
    out = []
    A = [np.eye(4)] + [None] * (len(chunks) - 1) if A is None else list(A)
    G = [np.eye(4)]
    for k in range(1, len(chunks)):
        o = overlaps[k - 1]
        prev, nxt = _shared(chunks[k - 1], slice(-o, None)), _shared(chunks[k], slice(0, o))
        Ak, diag = align_overlap(prev, nxt, None if fit else _f(A[k]), cfg=cfg, fit=fit)
        A[k] = np.asarray(Ak)
        G.append(G[-1] @ A[k])
        unit = float(np.cbrt(np.linalg.det(G[k - 1][:3, :3])))  # common units per unit of chunk k-1
        dg = {n: float(v) for n, v in diag.items()}
        out.append(Boundary(chunk=k, frames=(ranges[k][0], ranges[k][0] + o), scale=dg["scale"],
                            cumulative_scale=float(np.cbrt(np.linalg.det(G[k][:3, :3]))),
                            rotation_deg=dg["rotation_deg"], rmse_points=dg["rmse_points"] * unit,
                            rmse_centres=dg["rmse_centres"] * unit,
                            rel_rmse_points=dg["rmse_points"] / max(dg["median_depth"], 1e-300),
                            inlier_fraction=dg["inlier_fraction"], num_points=int(dg["num_points"])))
    return np.stack(A), np.stack(G), tuple(out)


# ----------------------------------------------------------------------------------------------
# Refinement


@functools.lru_cache(maxsize=8)
def _refine_runner(track_cfg: trajectory.TrackConfig, refine_cfg: trajectory.RefineConfig):
    @jax.jit
    def run(depth, conf, static, K, poses, fw, bw, pose_valid):
        pts, obs, _, _ = trajectory.prepare_landmarks(depth, conf, static, K, poses, fw, bw, track_cfg)
        return obs, trajectory.refine_trajectory(poses, K, pts, obs, refine_cfg, pose_valid)

    return run


def _pad(a, n: int, mode: str):
    """Pad the leading axis of ``a`` to ``n``: with zeros, or by repeating the last entry."""
    extra = n - a.shape[0]
    if extra <= 0:
        return a
    fill = np.zeros((extra,) + a.shape[1:], a.dtype) if mode == "zeros" else np.repeat(a[-1:], extra, 0)
    return np.concatenate([a, fill])


def refine_poses(seq: Sequence, static=None, cfg: StitchConfig = StitchConfig(), pad_to: int | None = None):
    """The factor graph (:func:`cm3d.trajectory.refine_trajectory`) over a sequence's poses, with
    landmarks from its depth and flow tracks (OpenCV) over all its frames.

    static: optional (S, H, W) bool, True on static pixels (``1 − M_dyn``, e.g. from the motion
    cue); None: every pixel, and moving objects enter the graph (the Huber loss and the outlier
    rejection absorb a few, not a large moving object: give a mask). pad_to: pad the problem to
    this many frames (padded frames carry nothing) so chunks of different lengths share one compiled
    program. Returns (refined poses (S, 4, 4) whatever the gate decided, gate decision, facts).
    """
    S, (H, W) = seq.num_frames, seq.image_size
    if S < 2:
        return np.asarray(seq.cam_to_world), False, {"observations": 0}
    static = np.ones((S, H, W), bool) if static is None else np.asarray(static, bool)
    if static.shape != (S, H, W):
        raise StitchError(f"static: expected shape {(S, H, W)} (frames, H, W), got {static.shape}")
    P = max(S, pad_to or S)
    t0 = time.perf_counter()
    fw = oflow.sequence_flow(seq.images, cfg.flow)
    bw = None
    if cfg.backward_flow:
        bw = _pad(np.stack([oflow.compute_flow(seq.images[i + 1], seq.images[i], cfg.flow) for i in range(S - 1)]),
                  P - 1, "zeros")
    t_flow = time.perf_counter() - t0
    track_cfg = cfg.track_config(W)
    with jax.enable_x64(True):
        run = _refine_runner(track_cfg, cfg.refinement)
        obs, ref = run(_f(_pad(seq.depth, P, "zeros")), _f(_pad(seq.depth_conf, P, "zeros")),
                       jnp.asarray(_pad(static, P, "zeros")), _f(_pad(seq.intrinsic, P, "edge")),
                       _f(_pad(seq.cam_to_world, P, "edge")), _f(_pad(fw, P - 1, "zeros")),
                       None if bw is None else _f(bw), jnp.arange(P) < S)
        jax.block_until_ready(ref)
        facts = {"observations": int(obs.valid.sum()), "inliers": int(ref.inlier.sum()),
                 "gate_stat": float(ref.gate_stat), "gate_threshold": float(ref.gate_threshold),
                 "iterations": int(ref.result.iterations), "flow_s": t_flow,
                 "seconds": time.perf_counter() - t0}
        return np.asarray(ref.refined_poses)[:S], bool(ref.refined), facts


@jax.jit
def prior_scale(refined, prior):
    """Scale ``s`` (least squares) with ``t_i - t_0 ≈ s (t'_i - t'_0)``: refined centres t' (N, 4, 4)
    against the prior's t, both about the first camera (which the graph's gauge prior holds)."""
    a = refined[:, :3, 3] - refined[:1, :3, 3]
    b = prior[:, :3, 3] - prior[:1, :3, 3]
    den = jnp.sum(a * a)
    return jnp.where(den > 0, jnp.sum(a * b) / jnp.where(den > 0, den, 1.0), 1.0)


@jax.jit
def restore_scale(poses, s):
    """Poses (N, 4, 4) with their translations scaled by ``s`` about the first camera (which the
    graph's gauge prior holds at the prior): ``t_i <- t_0 + s (t_i - t_0)``, rotations unchanged."""
    t0 = poses[:1, :3, 3]
    return poses.at[:, :3, 3].set(t0 + s * (poses[:, :3, 3] - t0))


_ate = jax.jit(ate)


def refine_checked(seq: Sequence, static=None, cfg: StitchConfig = StitchConfig(), noise: float | None = None,
                   pad_to: int | None = None):
    """:func:`refine_poses`, brought back to the prior's scale (:func:`prior_scale`,
    :func:`restore_scale`), then checked. The refinement is kept only when (1) the gate accepts it,
    (2) the restored scale is within ``cfg.max_scale_change`` (a collapsed solution is refused) and
    (3) when ``noise`` (per-frame camera-centre noise, sequence units) is given, the refined
    trajectory stays within ``cfg.max_deviation x noise`` (Sim(3)-aligned RMS) of the input: the
    graph has no depth factor, so over a long video its monocular scale can drift, which this
    catches. Returns (poses (S, 4, 4): refined if kept, else the input; refined poses whatever was
    decided; kept; facts)."""
    refined, use, facts = refine_poses(seq, static, cfg, pad_to)
    prior = np.asarray(seq.cam_to_world)
    with jax.enable_x64(True):
        s = float(prior_scale(_f(refined), _f(prior)))
        refined = np.asarray(restore_scale(_f(refined), s))
        dev = float(_ate(_f(refined), _f(prior)))
    scale_ok = bool(np.isfinite(s) and 1.0 / cfg.max_scale_change <= s <= cfg.max_scale_change)
    dev_ok = noise is None or dev <= cfg.max_deviation * noise
    keep = bool(use and scale_ok and dev_ok)
    facts = {**facts, "gate": bool(use), "scale_restored": s, "deviation": dev,
             "deviation_limit": float("nan") if noise is None else cfg.max_deviation * noise, "kept": keep}
    return (refined if keep else prior), refined, keep, facts


# ----------------------------------------------------------------------------------------------
# Whole-trajectory refinement: a frame-level pose graph with image-measured relative motions


@dataclasses.dataclass(frozen=True)
class FrameGraphConfig:
    """Options of :func:`refine_frames` (all static).

    Frame pairs are consecutive frames ``(i, i + 1)`` (the graph is block-tridiagonal: O(S) solves;
    longer offsets measured worse on the synthetic video, and their errors are correlated with the
    consecutive ones', which fools the variance estimation); grid_step: every ``grid_step``-th
    pixel of frame i is a correspondence candidate; robust_iterations, robust_k: IRLS rounds and the
    Cauchy scale (robust sigmas) of each pair's Sim(3) fit; min_inlier_fraction, min_points,
    max_residual: a pair whose fit keeps fewer inliers / valid points, or whose robust residual
    sigma exceeds ``max_residual`` x the median point distance (good pairs: ~1-2 % at 1 % depth
    noise; meaningless flow: tens of %), is not used; vce_iterations: rounds of variance
    component estimation (the four sigmas: prior / motion x translation / rotation, robust: the
    median of ``r² / (1 − h)``); outlier_quantile: a motion factor whose whitened squared residual exceeds
    ``χ²_6(q)`` after a round is dropped; max_deviation: the result is refused when it moves the
    trajectory (Sim(3)-aligned RMS) by more than this many times the per-frame centre noise;
    iterations: Levenberg–Marquardt steps (:func:`solve_frame_graph`); pad_frames: the graph is
    padded to a multiple of this many frames (padded frames carry only a prior) so videos of
    different lengths share one compiled program; flow: OpenCV flow.
    """

    grid_step: int = 2
    robust_iterations: int = 8
    robust_k: float = 2.0
    min_inlier_fraction: float = 0.5
    min_points: int = 50
    max_residual: float = 0.05
    vce_iterations: int = 3
    outlier_quantile: float = 0.999
    max_deviation: float = 2.0
    iterations: int = 10
    pad_frames: int = 64
    flow: oflow.FlowConfig = oflow.FlowConfig()

    def __post_init__(self):
        if (self.grid_step < 1 or self.robust_iterations < 0 or self.vce_iterations < 0 or self.min_points < 3
                or self.iterations < 1 or self.pad_frames < 1):
            raise ValueError("FrameGraphConfig: grid_step >= 1, robust_iterations >= 0, vce_iterations >= 0, "
                             f"min_points >= 3 and iterations >= 1 required, got {self}")
        if not (0 <= self.min_inlier_fraction <= 1 and 0 < self.outlier_quantile < 1 and self.max_deviation > 0
                and self.robust_k > 0 and self.max_residual > 0):
            raise ValueError("FrameGraphConfig: min_inlier_fraction in [0, 1], outlier_quantile in (0, 1), "
                             f"max_deviation, max_residual and robust_k > 0 required, got {self}")


def frame_pair_points(seq: Sequence, i: int, j: int, flow, step: int = 2, static=None):
    """3D-3D correspondences between frames i and j of a sequence (host, numpy).

    Every ``step``-th pixel ``p`` of frame i, lifted with frame i's depth and intrinsics into camera
    i, and its flow target ``q = p + flow[p]`` (``flow`` (H, W, 2), i -> j) lifted with frame j's
    depth at the nearest pixel into camera j. Returns (src (P, 3) camera-j points, dst (P, 3)
    camera-i points, ok (P,) bool: both depths valid, q inside the image, static in both frames when
    ``static`` (S, H, W) is given). ``dst ≈ T src`` with ``T`` the Sim(3) cam j -> cam i."""
    H, W = seq.image_size
    v, u = np.mgrid[step // 2:H:step, step // 2:W:step]
    u, v = u.ravel(), v.ravel()
    u2, v2 = u + flow[v, u, 0].astype(np.float64), v + flow[v, u, 1].astype(np.float64)
    ui, vi = np.rint(u2).astype(np.int64), np.rint(v2).astype(np.int64)
    inside = (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
    ui, vi = np.clip(ui, 0, W - 1), np.clip(vi, 0, H - 1)
    di = np.asarray(seq.depth[i], np.float64)[v, u]
    dj = np.asarray(seq.depth[j], np.float64)[vi, ui]
    ok = inside & np.isfinite(di) & np.isfinite(dj) & (di > 0) & (dj > 0)
    if static is not None:
        ok &= np.asarray(static[i], bool)[v, u] & np.asarray(static[j], bool)[vi, ui]
    ray = lambda K, a, b: np.stack([a, b, np.ones_like(a)], -1) @ np.linalg.inv(K).T  # noqa: E731
    dst = ray(np.asarray(seq.intrinsic[i], np.float64), u.astype(np.float64), v.astype(np.float64))
    src = ray(np.asarray(seq.intrinsic[j], np.float64), u2, v2)
    return src * np.where(ok, dj, 0.0)[:, None], dst * np.where(ok, di, 0.0)[:, None], ok


@functools.partial(jax.jit, static_argnames=("iterations", "k"))
def robust_sim3(src, dst, ok, iterations: int = 8, k: float = 2.0):
    """Robust Sim(3) ``dst ≈ A src`` of padded correspondences (P, 3) with validity ``ok`` (P,):
    weighted Umeyama, then ``iterations`` IRLS rounds with Cauchy weights at ``k`` robust sigmas
    (1.4826 MAD). Returns (A (4, 4), inlier fraction (within 3 robust sigmas), valid count, robust
    residual sigma over the median distance of ``dst`` from the origin). ``vmap`` over pairs."""
    def resid(A):
        r = jnp.linalg.norm(_apply_sim3(A, src) - dst, axis=-1)
        return r, jnp.maximum(1.4826 * masked_median(r, ok), 1e-12)

    A = _irls_sim3(src, dst, ok.astype(src.dtype), resid, iterations, k)
    r, sigma = resid(A)
    n = jnp.sum(ok)
    rel = sigma / jnp.maximum(masked_median(jnp.linalg.norm(dst, axis=-1), ok), 1e-12)
    return A, jnp.sum(ok & (r <= 3.0 * sigma)) / jnp.maximum(n, 1), n, rel


def measure_frame_pairs(seq: Sequence, pairs, static=None, cfg: FrameGraphConfig = FrameGraphConfig(),
                        other: Sequence | None = None, pad_to: int | None = None):
    """Relative Sim(3)s of frame pairs from the images (optical flow) and the depth maps.

    pairs (E, 2) int: ``(i, j)``, frame i of ``seq`` and frame j of ``other`` (default ``seq``).
    Returns (M (E, 4, 4): Sim(3) cam j -> cam i, i.e. the measured ``T_i^{-1} T_j`` with the
    depth-scale ratio as its scale; inlier_fraction (E,); points (E,); residual (E,): robust
    residual sigma over the median depth). Host flow (OpenCV), then
    one jitted, vmapped robust fit (:func:`robust_sim3`) over the pairs (``pad_to``: padded to this
    many pairs so that problems of different lengths share one compiled program)."""
    other = seq if other is None else other
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    if pairs.shape[0] == 0:
        return np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0, np.int64), np.zeros(0)
    src, dst, ok = [], [], []
    for i, j in pairs:
        F = oflow.compute_flow(seq.images[i], other.images[j], cfg.flow)
        s, d, o = _pair_points_two(seq, other, int(i), int(j), F, cfg.grid_step, static)
        src.append(s), dst.append(d), ok.append(o)
    E = len(src)
    pad = lambda a, mode="zeros": _pad(np.stack(a), max(E, pad_to or 0), mode)  # noqa: E731
    with jax.enable_x64(True):
        A, frac, n, rel = _fit_pairs(_f(pad(src)), _f(pad(dst)), jnp.asarray(pad(ok)), cfg.robust_iterations,
                                     cfg.robust_k)
        return (np.asarray(A, np.float64)[:E], np.asarray(frac, np.float64)[:E], np.asarray(n, np.int64)[:E],
                np.asarray(rel, np.float64)[:E])


@functools.partial(jax.jit, static_argnames=("iterations", "k"))
def _fit_pairs(src, dst, ok, iterations: int, k: float):
    return jax.vmap(functools.partial(robust_sim3, iterations=iterations, k=k))(src, dst, ok)


def _pair_points_two(seq, other, i, j, F, step, static):
    if other is seq:
        return frame_pair_points(seq, i, j, F, step, static)
    # frame i of seq, frame j of other: a two-frame sequence view (static masks apply to seq only)
    two = Sequence(images=np.stack([seq.images[i], other.images[j]]), depth=np.stack([seq.depth[i], other.depth[j]]),
                   depth_conf=np.stack([seq.depth_conf[i], other.depth_conf[j]]),
                   intrinsic=np.stack([seq.intrinsic[i], other.intrinsic[j]]),
                   cam_to_world=np.stack([seq.cam_to_world[i], other.cam_to_world[j]]),
                   timestamps=np.arange(2, dtype=np.float64))
    return frame_pair_points(two, 0, 1, F, step, None)


def _rigid(M):
    """Sim(3)s (..., 4, 4) -> (rigid parts with the scale divided out, scales)."""
    M = np.asarray(M, np.float64)
    s = np.cbrt(np.linalg.det(M[..., :3, :3]))
    out = M.copy()
    out[..., :3, :3] = M[..., :3, :3] / s[..., None, None]
    return out, s


def frame_graph(poses, idx_a, idx_b, measured, sigma_motion, sigma_prior, weight=None) -> factors.FactorGraph:
    """The whole-trajectory pose graph as a :class:`cm3d.solvers.factors.FactorGraph`: one prior
    per frame at ``poses`` (N, 4, 4) (the stitched priors, sigma (N, 6) or (6,), translation first)
    and one motion factor per measured pair ``T_a^{-1} T_b ≈ measured`` (Q, 4, 4) rigid, sigma
    (Q, 6) or (6,), weight (Q,) (0 = dropped); no landmarks (one zero-weight projection slot).
    :func:`solve_frame_graph` needs every weighted pair consecutive (``idx_b = idx_a + 1``)."""
    poses = _f(poses)
    N, Q = poses.shape[0], int(np.shape(idx_a)[0])
    wt = np.ones(Q) if weight is None else np.asarray(weight)
    if np.any((np.asarray(idx_b) != np.asarray(idx_a) + 1) & (wt > 0)):
        raise StitchError("frame_graph: motion factors must join consecutive frames (idx_b = idx_a + 1)")
    weight = jnp.ones(Q) if weight is None else _f(weight)
    return factors.FactorGraph(
        intrinsics=jnp.tile(jnp.eye(3, dtype=poses.dtype), (N, 1, 1)),
        projection=factors.ProjectionFactors(pose_idx=jnp.zeros(1, jnp.int32), point_idx=jnp.zeros(1, jnp.int32),
                                             z=jnp.zeros((1, 2), poses.dtype), sigma=jnp.ones(1, poses.dtype),
                                             weight=jnp.zeros(1, poses.dtype), memory=jnp.zeros(1, bool)),
        prior=factors.PriorFactors(pose_idx=jnp.arange(N, dtype=jnp.int32), target=poses,
                                   sigma=jnp.broadcast_to(_f(sigma_prior), (N, 6)), weight=jnp.ones(N, poses.dtype)),
        motion=factors.MotionFactors(idx_a=jnp.asarray(idx_a, jnp.int32), idx_b=jnp.asarray(idx_b, jnp.int32),
                                     measured=_f(measured), sigma=jnp.broadcast_to(_f(sigma_motion), (Q, 6)),
                                     weight=weight),
        huber_k=jnp.asarray(np.inf, poses.dtype), memory_alpha=jnp.asarray(0.5, poses.dtype),
        pose_fixed=jnp.zeros(N, bool))


def _frame_normal_equations(graph: factors.FactorGraph, poses):
    """Block-tridiagonal normal equations of a :func:`frame_graph` at ``poses`` (motion factors
    between consecutive frames only): (D (N, 6, 6) diagonal blocks, B (N-1, 6, 6) blocks
    ``H[i, i+1]``, g (N, 6), cost, Jacobians). Residuals exact
    (:func:`cm3d.solvers.factors.pose_residuals`); Jacobians to first order in the residual
    (``J_r^{-1}(log E) ≈ I``: the factors' errors are a few degrees, so this changes a step by ~1 %,
    not the optimum): ``I / σ`` for a pose's own perturbation, ``−Ad((T_a^{-1} T_b)^{-1}) / σ`` for
    ``T_a``'s."""
    N = poses.shape[0]
    ep, em = factors.pose_residuals(graph, poses)
    X = se3.inverse(poses[graph.motion.idx_a]) @ poses[graph.motion.idx_b]
    eye6 = jnp.eye(6, dtype=poses.dtype)
    Jp = eye6 / graph.prior.sigma[:, :, None]
    Jb = eye6 / graph.motion.sigma[:, :, None]
    Ja = -factors.mm(Jb, factors.adjoint(se3.inverse(X)))
    wp, wm = graph.prior.weight, graph.motion.weight
    ip, ia, ib = graph.prior.pose_idx, graph.motion.idx_a, graph.motion.idx_b
    JtJ = lambda A, C, w: w[:, None, None] * jnp.einsum("fki,fkj->fij", A, C)  # noqa: E731
    D = jnp.zeros((N, 6, 6), poses.dtype).at[ip].add(JtJ(Jp, Jp, wp))
    D = D.at[ia].add(JtJ(Ja, Ja, wm)).at[ib].add(JtJ(Jb, Jb, wm))
    B = jnp.zeros((max(N - 1, 1), 6, 6), poses.dtype).at[jnp.minimum(ia, N - 2)].add(JtJ(Ja, Jb, wm))
    Jtr = lambda A, e, w: w[:, None] * jnp.einsum("fki,fk->fi", A, e)  # noqa: E731
    g = jnp.zeros((N, 6), poses.dtype).at[ip].add(Jtr(Jp, ep, wp))
    g = g.at[ia].add(Jtr(Ja, em, wm)).at[ib].add(Jtr(Jb, em, wm))
    cost = 0.5 * (jnp.sum(wp * jnp.sum(ep * ep, -1)) + jnp.sum(wm * jnp.sum(em * em, -1)))
    return D, B, g, cost, (ep, Jp, em, Ja, Jb)


def _block_tridiagonal(D, B, g):
    """Solve ``H x = g`` for symmetric positive definite block-tridiagonal ``H`` (diagonal blocks D
    (N, 6, 6), upper blocks B (N-1, 6, 6)) and return (x (N, 6), the diagonal blocks (N, 6, 6) and
    upper blocks (N-1, 6, 6) of ``H^{-1}``): forward Schur complements, back substitution, and
    the covariance recursion of a Rauch–Tung–Striebel smoother. O(N) in one ``lax.scan`` each way."""
    N = D.shape[0]
    Bp = jnp.concatenate([jnp.zeros_like(D[:1]), B[:N - 1]])  # Bp[i] = H[i-1, i]

    def fwd(carry, x):
        Si_prev, y_prev = carry
        Di, Bi, gi = x
        K = Bi.T @ Si_prev  # B_{i-1}^T S_{i-1}^{-1}
        S = Di - K @ Bi
        Si = jnp.linalg.inv(S)
        y = gi - K @ y_prev
        return (Si, y), (Si, y)

    zero = jnp.zeros((6, 6), D.dtype)
    _, (Sinv, y) = jax.lax.scan(fwd, (zero, jnp.zeros(6, D.dtype)), (D, Bp, g))
    Bn = jnp.concatenate([B[:N - 1], jnp.zeros_like(D[:1])])  # Bn[i] = H[i, i+1] (0 for the last)

    def bwd(carry, x):
        x_next, P_next = carry
        Si, yi, Bi = x
        xi = Si @ (yi - Bi @ x_next)
        C = -Si @ Bi @ P_next  # H^{-1}[i, i+1]
        Pi = Si - C @ Bi.T @ Si
        return (xi, Pi), (xi, Pi, C)

    _, (xs, Pd, C) = jax.lax.scan(bwd, (jnp.zeros(6, D.dtype), zero), (Sinv, y, Bn), reverse=True)
    return xs, Pd, C[:N - 1]


@functools.partial(jax.jit, static_argnames=("iterations",))
def solve_frame_graph(graph: factors.FactorGraph, poses, iterations: int = 10):
    """Levenberg–Marquardt (Marquardt damping) on a :func:`frame_graph` from ``poses`` (N, 4, 4),
    right perturbations ``T exp(ξ)`` as the factor graph's solver, each step an O(N)
    block-tridiagonal solve (motion factors between consecutive frames only); then each factor
    component's whitened residual and leverage ``h = diag(J (JᵀJ)⁻¹ Jᵀ)`` at the optimum (its
    redundancy is ``1 − h``: variance component estimation). Returns (poses, e_prior (P, 6),
    h_prior (P, 6), e_motion (Q, 6), h_motion (Q, 6), initial cost, cost)."""
    N = poses.shape[0]

    def step(carry, _):
        # evaluate the candidate; keep it when it lowers the cost; propose the next from the best
        # (one evaluation of the normal equations per step: one copy in the compiled program)
        cand, best, lam, cost0 = carry
        ne = _frame_normal_equations(graph, cand)
        better = jnp.isfinite(ne[3]) & (ne[3] < best[4])
        best = jax.tree_util.tree_map(lambda a, b: jnp.where(better, a, b), (cand,) + ne, best)
        lam = jnp.where(better, lam / 10.0, lam * 10.0)
        cost0 = jnp.where(jnp.isinf(cost0), ne[3], cost0)
        D, B, g = best[1], best[2], best[3]
        damp = lam * (jnp.diagonal(D, axis1=-2, axis2=-1) + 1e-9)
        d, _, _ = _block_tridiagonal(D + jax.vmap(jnp.diag)(damp), B, -g)
        return (best[0] @ jax.vmap(se3.exp)(d), best, lam, cost0), None

    shapes = jax.eval_shape(lambda T: _frame_normal_equations(graph, T), poses)
    empty = jax.tree_util.tree_map(lambda x: jnp.zeros(x.shape, x.dtype), shapes)
    inf = jnp.asarray(jnp.inf, poses.dtype)
    best0 = (poses, empty[0], empty[1], empty[2], inf, empty[4])
    (_, best, _, cost0), _ = jax.lax.scan(step, (poses, best0, jnp.asarray(1e-4, poses.dtype), inf), None,
                                          length=iterations + 1)
    T, D, B, g, cost, (ep, Jp, em, Ja, Jb) = best
    _, Pd, C = _block_tridiagonal(D, B, g)
    ip, ia, ib = graph.prior.pose_idx, graph.motion.idx_a, graph.motion.idx_b
    quad = lambda A, M, Bm: jnp.einsum("fki,fij,fkj->fk", A, M, Bm)  # noqa: E731  diag(A M Bᵀ)
    Cab = C[jnp.minimum(ia, N - 2)]
    hp = graph.prior.weight[:, None] * quad(Jp, Pd[ip], Jp)
    hm = graph.motion.weight[:, None] * (quad(Ja, Pd[ia], Ja) + quad(Jb, Pd[ib], Jb) + quad(Ja, Cab, Jb)
                                         + quad(Jb, jnp.swapaxes(Cab, -1, -2), Ja))
    return T, ep, hp, em, hm, cost0, cost


def _rotation_noise(chunks, ranges, overlaps, G) -> float:
    """Per-axis rotation noise (rad) of a frame's prior, from the shared frames: two chunks' placed
    rotations of a frame differ by sqrt(2) x the per-frame noise."""
    d = []
    for k in range(1, len(chunks)):
        o = overlaps[k - 1]
        with jax.enable_x64(True):
            pa = np.asarray(place_poses(_f(G[k - 1]), _f(chunks[k - 1].cam_to_world[-o:])))
            pb = np.asarray(place_poses(_f(G[k]), _f(chunks[k].cam_to_world[:o])))
            d.extend(np.asarray(se3.rotation_angle(_f(np.swapaxes(pa[:, :3, :3], 1, 2) @ pb[:, :3, :3]))).tolist())
    return float(np.sqrt(np.mean(np.square(d))) / np.sqrt(2.0) / np.sqrt(3.0)) if d else float("nan")


def refine_frames(seq: Sequence, static=None, cfg: FrameGraphConfig = FrameGraphConfig(), noise: float | None = None,
                  rot_noise: float | None = None):
    """Refine a whole (stitched) trajectory in one pose graph over every frame.

    Factors: a prior per frame at its stitched pose, and a relative-motion factor per measured frame
    pair (:func:`measure_frame_pairs`: optical flow + both frames' depth -> robust Sim(3); at 96x128
    a consecutive pair's rotation is measured to ~0.14° against the prior's ~2.6°), across chunk
    boundaries alike. The four noise levels (prior / motion x translation / rotation) are estimated
    from the data by robust variance component estimation (leverages of the pose graph's Jacobian,
    no ground truth); pairs whose fit is poor (inlier fraction, points, residual) or whose factor
    residual is implausible (``χ²_6``) are dropped. The graph is a
    :class:`cm3d.solvers.factors.FactorGraph` (:func:`frame_graph`: pose priors and motion factors,
    no landmarks), solved by a dense Levenberg–Marquardt on its analytic Jacobians
    (:func:`solve_frame_graph`; one small compiled program, (6S)² memory: ~0.1 s per step at 200
    frames). The result is refused when it moves the trajectory by more than
    ``cfg.max_deviation`` x the per-frame centre noise (``noise``, e.g. measured on the overlaps;
    None: the estimated prior noise).

    noise / rot_noise: per-frame centre noise (sequence units) and per-axis rotation noise (rad)
    of the priors, the variance estimation's starting point (None: 1 % of the median depth, 1°).
    Returns (poses (S, 4, 4): refined if kept, else the input; facts dict with ``kept``).
    """
    t0 = time.perf_counter()
    P = np.asarray(seq.cam_to_world, np.float64)
    S = P.shape[0]
    facts = {"frames": S, "kept": False}
    if S < 2:
        return P, {**facts, "reason": "fewer than 2 frames"}
    if static is not None:
        static = np.asarray(static, bool)
        if static.shape != seq.depth.shape:
            raise StitchError(f"static: expected shape {seq.depth.shape} (frames, H, W), got {static.shape}")
    pairs = np.stack([np.arange(S - 1), np.arange(1, S)], 1)
    # padded to a multiple of cfg.pad_frames frames (and the pairs of as many): one compiled program
    N = -(-S // cfg.pad_frames) * cfg.pad_frames
    E = N - 1
    M, frac, npts, rel = measure_frame_pairs(seq, pairs, static, cfg, pad_to=E)
    Mr, _ = _rigid(M)
    usable = ((frac >= cfg.min_inlier_fraction) & (npts >= cfg.min_points) & (rel <= cfg.max_residual)
              & np.all(np.isfinite(Mr), (1, 2)))
    t_measure = time.perf_counter() - t0
    if noise is None or not np.isfinite(noise) or noise <= 0:
        d = np.asarray(seq.depth, np.float64)
        noise = 0.01 * float(np.median(d[d > 0])) if np.any(d > 0) else 0.01
    rot_noise = np.deg2rad(1.0) if rot_noise is None or not np.isfinite(rot_noise) or rot_noise <= 0 else rot_noise
    sp = np.array([noise / np.sqrt(3.0)] * 3 + [rot_noise] * 3)
    sm = sp / 3.0
    Q = len(pairs)
    ia, ib = _pad(pairs[:, 0], E, "zeros"), _pad(pairs[:, 1], E, "zeros")
    meas, w = _pad(Mr, E, "last"), _pad(usable.astype(np.float64), E, "zeros")
    Pp = _pad(P, N, "last")  # padded frames: only their prior
    limit = _chi2_ppf(cfg.outlier_quantile, 6)
    rounds = cfg.vce_iterations
    with jax.enable_x64(True):
        for it in range(rounds + 1):
            graph = frame_graph(Pp, ia, ib, meas, sm, sp, w)
            R, rp, hp, rm, hm, cost0, cost = solve_frame_graph(graph, _f(Pp), iterations=cfg.iterations)
            if it == rounds:
                break
            rp, hp, rm, hm = (np.asarray(x) for x in (rp, hp, rm, hm))
            sm_old = sm.copy()
            for arr, hh, sig, ww in ((rp, hp, sp, np.arange(N) < S), (rm, hm, sm, w)):
                for sl in (slice(0, 3), slice(3, 6)):  # translation, rotation
                    used = (ww > 0)[:, None] & (hh[:, sl] < 1.0 - 1e-6)
                    if np.sum(used) > 3:  # robust: median of r² / (1 − h) against χ²_1's median
                        v = (arr[:, sl] ** 2 / np.maximum(1.0 - hh[:, sl], 1e-6))[used]
                        sig[sl] *= np.sqrt(float(np.median(v)) / _CHI2_1_MEDIAN)
            # drop implausible motion factors (residuals whitened by the updated sigmas)
            w = np.where(np.sum((rm * sm_old / sm) ** 2, 1) > limit, 0.0, w)
        refined = np.asarray(R, np.float64)[:S]
        dev = float(_ate(_f(refined), _f(P)))
    ok = bool(np.all(np.isfinite(refined)))
    dev_limit = cfg.max_deviation * noise
    keep = ok and dev <= dev_limit
    if not keep:
        facts["reason"] = ("non-finite result" if not ok else
                           f"moves the trajectory by {dev:.3g} > {dev_limit:.3g} (max_deviation x the prior noise)")
    facts.update({"kept": keep, "pairs": Q, "pairs_used": int(np.sum(w > 0)),
                  "pairs_poor_fit": int(np.sum(~usable)),
                  "inlier_fraction_median": float(np.median(frac)) if len(frac) else float("nan"),
                  "residual_median": float(np.median(rel)) if len(rel) else float("nan"),
                  "sigma_prior_trans": float(sp[0]), "sigma_prior_rot_deg": float(np.rad2deg(sp[3])),
                  "sigma_motion_trans": float(sm[0]), "sigma_motion_rot_deg": float(np.rad2deg(sm[3])),
                  "deviation": dev, "deviation_limit": dev_limit, "rounds": rounds,
                  "cost_initial": float(cost0), "cost": float(cost), "measure_s": t_measure,
                  "seconds": time.perf_counter() - t0})
    return (refined if keep else P), facts


_CHI2_1_MEDIAN = 0.45493642311957283  # median of χ²_1


def _chi2_ppf(q: float, dof: int) -> float:
    from scipy.stats import chi2

    return float(chi2.ppf(q, dof))


# ----------------------------------------------------------------------------------------------
# Public entry points


def stitch_chunks(chunks, overlap: int | None = None, config: StitchConfig = StitchConfig(), static=None,
                  refine: bool | str = True, frame_config: FrameGraphConfig = FrameGraphConfig()) -> StitchResult:
    """Stitch overlapping chunks (each in its own frame and scale) into one sequence: a Sim(3) per
    boundary, chained into chunk 0's frame and scale, fused, then (``refine``) the whole trajectory
    refined in one pose graph over every frame with image-measured relative motions
    (:func:`refine_frames`, ``refine=True`` or ``"frames"``), or with the landmark factor graph
    (``refine="landmarks"``: :func:`refine_checked`; at 96x128 its monocular scale drifts and the
    self-check refuses it). See the module docstring for the layout, the steps and the errors.

    chunks: list of :class:`Sequence` in temporal order; overlap: shared frames per boundary (None:
    from timestamps); static: optional (S, H, W) bool mask of static pixels of the *merged* frames
    (``1 − M_dyn``) for the refinement's correspondences. Returns :class:`StitchResult`
    (``poses_aligned``: the stitched priors; ``sequence.cam_to_world``: refined when kept).
    """
    if refine not in (True, False, "frames", "landmarks"):
        raise StitchError(f"refine: expected True, False, 'frames' or 'landmarks', got {refine!r}")
    chunks = _check_chunks(chunks)
    ranges, overlaps, ts = chunk_layout(chunks, overlap)
    S, (H, W) = ranges[-1][1], chunks[0].image_size
    if static is not None:
        static = np.asarray(static, bool)
        if static.shape != (S, H, W):
            raise StitchError(f"static: expected shape {(S, H, W)} (merged frames, H, W), got {static.shape}")
    with jax.enable_x64(True):
        _, G, bounds = _boundaries(chunks, ranges, overlaps, None, None, config, fit=True)
        seq, frame_chunk = _merge(chunks, ranges, overlaps, ts, G, "cm3d")
    aligned, refined_poses, facts, use = seq.cam_to_world, None, {}, False
    if refine:
        # per-frame centre noise: two chunks' independent estimates of a shared frame differ by sqrt(2) σ
        noise = float(np.sqrt(np.mean([b.rmse_centres ** 2 for b in bounds])) / np.sqrt(2.0)) if bounds else None
        if refine == "landmarks":
            poses, refined_poses, use, facts = refine_checked(seq, static, config, noise)
        else:
            poses, facts = refine_frames(seq, static, frame_config, noise,
                                         _rotation_noise(chunks, ranges, overlaps, G))
            refined_poses, use = poses, facts["kept"]
        seq = seq.replace(cam_to_world=poses)
    seq = seq.replace(meta={**seq.meta, "stitched": {**seq.meta["stitched"], "refined": bool(use)}})
    return StitchResult(sequence=seq, poses_aligned=aligned, poses_refined=refined_poses, chunk_transforms=G,
                        ranges=ranges, frame_chunk=frame_chunk, boundaries=bounds, refined=use,
                        refinement=facts, method="cm3d")


def naive_stitch(chunks, overlap: int | None = None, config: StitchConfig = StitchConfig()) -> StitchResult:
    """The common naive stitching: chunk k is placed rigidly (SE(3), no scale) so that its first
    shared frame coincides with chunk k-1's placed pose of that frame; a shared frame keeps the
    earlier chunk's pose and depth; depths are not rescaled. The boundaries' diagnostics measure
    the same overlap residuals as :func:`stitch_chunks` (scale 1)."""
    chunks = _check_chunks(chunks)
    ranges, overlaps, ts = chunk_layout(chunks, overlap)
    with jax.enable_x64(True):
        M = [np.eye(4)]
        for k in range(1, len(chunks)):
            prev_placed = np.asarray(place_poses(_f(M[-1]), _f(chunks[k - 1].cam_to_world)))
            first = prev_placed[-overlaps[k - 1]]
            M.append(first @ np.asarray(se3.inverse(_f(chunks[k].cam_to_world[0]))))
        A = [np.eye(4)] + [np.linalg.inv(M[k - 1]) @ M[k] for k in range(1, len(chunks))]
        _, _, bounds = _boundaries(chunks, ranges, overlaps, None, A, config, fit=False)
        weights = []
        for k, (a, b) in enumerate(ranges):
            w = np.ones(b - a)
            if k > 0:
                w[:overlaps[k - 1]] = 0.0
            weights.append(w)
        seq, frame_chunk = _merge(chunks, ranges, overlaps, ts, np.stack(M), "naive", weights)
    return StitchResult(sequence=seq, poses_aligned=seq.cam_to_world, poses_refined=None,
                        chunk_transforms=np.stack(M), ranges=ranges, frame_chunk=frame_chunk,
                        boundaries=bounds, refined=False, refinement={}, method="naive")


# ----------------------------------------------------------------------------------------------
# Memory recall across chunks and the Sim(3) pose graph over the chunks


@dataclasses.dataclass(frozen=True)
class PoseGraphConfig:
    """The Sim(3) pose graph over chunk transforms (:func:`sim3_pose_graph`).

    sigma_rot (rad), sigma_trans (chunk 0's units), sigma_scale (log scale): noise of a consecutive
    overlap constraint; loop_factor: loop constraints (memory recalls) get sigmas this many times
    larger: one window's cloud registration (a voxel map, 64-256 ICP points, clouds posed by the
    pipeline's refined window poses) against a whole overlap's pixels. Measured on the loop video
    at 96x128 (docs/long_video.md): a recall is off by 5-7°, 0.23 m, 7.5 % in scale, i.e. 0.1-0.12
    per chart component, ~10 overlap sigmas; 20 is twice that, so a recall this coarse barely
    moves the chain (with 2 it made ATE 2x worse); max_steps: LM steps;
    loop_quantile: a loop constraint is kept only when its discrepancy with the chain of overlap
    constraints is plausible, ``|r|² <= χ²_q(7)`` with ``r`` whitened by the chain's accumulated
    noise plus the loop's own (the usual loop-closure consistency check; 1 keeps every loop)."""

    sigma_rot: float = 0.01
    sigma_trans: float = 0.01
    sigma_scale: float = 0.01
    loop_factor: float = 20.0
    max_steps: int = 100
    loop_quantile: float = 0.99

    def __post_init__(self):
        for name in ("sigma_rot", "sigma_trans", "sigma_scale", "loop_factor"):
            if not getattr(self, name) > 0:
                raise ValueError(f"PoseGraphConfig.{name}: must be > 0, got {getattr(self, name)}")
        if self.max_steps < 1:
            raise ValueError(f"PoseGraphConfig.max_steps: must be >= 1, got {self.max_steps}")


@dataclasses.dataclass(frozen=True)
class LoopClosure:
    """A memory recall across chunks: a window of ``chunk`` (its frames, chunk-local) recalled a map
    that a window of ``other`` (``other_frames``) created; ``transform`` (4, 4) is the Sim(3) from
    ``chunk``'s frame into ``other``'s; inliers / rmse: the verification's ICP facts. ``measured``:
    the memory's own transform (between the two windows' *refined* frames) when ``transform`` was
    re-expressed between the chunks' prior frames (:func:`loop_to_prior_frames`), else None.
    sigma: (7,) std of ``transform`` in the pose graph's chart ``[ω, t, log s]`` when measured
    (:func:`measure_loop`), else None (the pose graph's ``loop_factor`` x its overlap sigmas);
    pairs: frame pairs the measurement used (0: the memory's registration)."""

    chunk: int
    other: int
    frames: tuple[int, int]
    transform: np.ndarray
    inliers: int
    rmse: float
    other_frames: tuple[int, int] | None = None
    measured: np.ndarray | None = None
    sigma: np.ndarray | None = None
    pairs: int = 0


def _sim3_exp(p):
    """(7,) [rotation vector, translation, log scale] -> 4x4 ``[s R, t]``."""
    R = jaxlie.SO3.exp(p[:3]).as_matrix()
    top = jnp.concatenate([jnp.exp(p[6]) * R, p[3:6, None]], 1)
    return jnp.concatenate([top, jnp.array([[0.0, 0.0, 0.0, 1.0]], p.dtype)], 0)


def _sim3_log(E):
    """4x4 ``[s R, t]`` -> (7,) [rotation vector, translation, log scale] (the chart of :func:`_sim3_exp`)."""
    s = jnp.cbrt(jnp.linalg.det(E[:3, :3]))
    w = jaxlie.SO3.from_matrix(E[:3, :3] / s).log()
    return jnp.concatenate([w, E[:3, 3], jnp.log(s)[None]])


def _sim3_inv(G):
    s = jnp.cbrt(jnp.linalg.det(G[..., :3, :3]))
    R = G[..., :3, :3] / s[..., None, None]
    Ri = jnp.swapaxes(R, -1, -2) / s[..., None, None]
    t = -jnp.einsum("...ij,...j->...i", Ri, G[..., :3, 3])
    top = jnp.concatenate([Ri, t[..., None]], -1)
    bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0], G.dtype), G.shape[:-2] + (1, 4))
    return jnp.concatenate([top, bottom], -2)


def pose_graph_residuals(delta, G0, idx_a, idx_b, measured, sigma):
    """Whitened residuals (E, 7) of Sim(3) constraints ``G_a^{-1} G_b ≈ measured`` with
    ``G_k = G0_k Exp(δ_k)`` (δ_0 = 0: chunk 0 is the gauge). delta (K-1, 7); G0 (K, 4, 4);
    idx_a, idx_b (E,); measured (E, 4, 4); sigma (E, 7)."""
    d = jnp.concatenate([jnp.zeros((1, 7), delta.dtype), delta])
    G = G0 @ jax.vmap(_sim3_exp)(d)
    E = jnp.einsum("eij,ejk->eik", _sim3_inv(measured), _sim3_inv(G[idx_a]) @ G[idx_b])
    return jax.vmap(_sim3_log)(E) / sigma


_residuals = jax.jit(pose_graph_residuals)


@functools.partial(jax.jit, static_argnames=("max_steps",))
def _solve_pose_graph(G0, idx_a, idx_b, measured, sigma, max_steps: int):
    """Levenberg–Marquardt (optimistix, dense: 7 (K-1) unknowns) on the chart increments δ
    (``G_k = G0_k Exp(δ_k)``). Returns (G (K, 4, 4), cost, steps)."""
    import optimistix as optx

    fn = lambda y, args: pose_graph_residuals(y, G0, idx_a, idx_b, measured, sigma)  # noqa: E731
    sol = optx.least_squares(fn, optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10),
                             jnp.zeros((G0.shape[0] - 1, 7), G0.dtype), max_steps=max_steps, throw=False)
    d = jnp.concatenate([jnp.zeros((1, 7), G0.dtype), sol.value])
    r = pose_graph_residuals(sol.value, G0, idx_a, idx_b, measured, sigma)
    return G0 @ jax.vmap(_sim3_exp)(d), 0.5 * jnp.sum(r * r), sol.stats["num_steps"]


def sim3_pose_graph(G0, A, loops=(), cfg: PoseGraphConfig = PoseGraphConfig()):
    """Refine the chunk transforms ``G_k`` (chunk k -> common frame, Sim(3), ``G_0 = I``) with every
    consecutive overlap constraint ``G_{k-1}^{-1} G_k ≈ A_k`` and every loop closure
    ``G_other^{-1} G_chunk ≈ transform``: Levenberg–Marquardt (:func:`_solve_pose_graph`) on the Sim(3) chart
    ``[ω, t, log s]``, so scale is a variable and a loop corrects the scale drift of the chain.

    G0 (K, 4, 4) the initial transforms (e.g. the chain of A); A (K, 4, 4) with A[k] chunk k -> chunk
    k-1 (A[0] unused); loops: :class:`LoopClosure` list. A loop whose discrepancy with the chain of A
    is implausible (``cfg.loop_quantile``) is left out; without loops the chain of A is returned
    (it satisfies every overlap constraint). Returns (G (K, 4, 4), facts dict)."""
    G0 = np.asarray(G0, np.float64)
    K = G0.shape[0]
    if K < 2:
        return G0, {"constraints": 0, "loops": 0, "loops_kept": 0}
    ia, ib, meas, sig = [], [], [], []
    base = np.array([cfg.sigma_rot] * 3 + [cfg.sigma_trans] * 3 + [cfg.sigma_scale])
    for k in range(1, K):
        ia.append(k - 1), ib.append(k), meas.append(np.asarray(A[k], np.float64)), sig.append(base)
    from scipy.stats import chi2

    limit = float(chi2.ppf(cfg.loop_quantile, 7)) if cfg.loop_quantile < 1 else np.inf
    chain = [np.eye(4)]
    for k in range(1, K):
        chain.append(chain[-1] @ np.asarray(A[k], np.float64))
    chain = np.stack(chain)
    discrepancy, kept = [], 0
    for lc in loops:
        if not (0 <= lc.other < K and 0 <= lc.chunk < K) or lc.other == lc.chunk:
            raise StitchError(f"loops: chunk {lc.chunk} -> {lc.other} is not a pair of distinct chunks of {K}")
        loop_sigma = base * cfg.loop_factor if lc.sigma is None else np.asarray(lc.sigma, np.float64)
        chain_sigma = np.sqrt(base ** 2 * abs(lc.chunk - lc.other) + loop_sigma ** 2)
        with jax.enable_x64(True):
            r = _residuals(jnp.zeros((K - 1, 7)), _f(chain), jnp.asarray([lc.other]), jnp.asarray([lc.chunk]),
                                     _f(np.asarray(lc.transform, np.float64)[None]), _f(chain_sigma[None]))
        d2 = float(jnp.sum(r * r))
        discrepancy.append(d2)
        if d2 <= limit:
            kept += 1
            ia.append(lc.other), ib.append(lc.chunk), meas.append(np.asarray(lc.transform, np.float64))
            sig.append(loop_sigma)
    facts = {"constraints": len(ia), "loops": len(loops), "loops_kept": kept, "loop_limit": limit,
             "loop_discrepancy_max": max(discrepancy) if discrepancy else 0.0,
             "loop_discrepancy": discrepancy, "loop_kept": [d2 <= limit for d2 in discrepancy]}
    if kept == 0:  # a chain (a tree) of constraints: the chained transforms satisfy every one exactly
        return chain, {**facts, "cost_initial": 0.0, "cost": 0.0, "steps": 0}
    with jax.enable_x64(True):
        args = (_f(G0), jnp.asarray(ia), jnp.asarray(ib), _f(np.stack(meas)), _f(np.stack(sig)))
        r0 = _residuals(jnp.zeros((K - 1, 7)), *args)
        G, cost, steps = _solve_pose_graph(*args, max_steps=cfg.max_steps)
        G = np.asarray(G)
    return G, {**facts, "cost_initial": float(0.5 * jnp.sum(r0 * r0)), "cost": float(cost), "steps": int(steps)}


def recall_loops(results, min_gap: int = 2) -> list[LoopClosure]:
    """Loop closures from the pipeline's per-chunk results (chunks run in order with one memory
    bank, :func:`cm3d.pipeline.run`): every accepted recall of a map created by a chunk at least
    ``min_gap`` chunks earlier (consecutive chunks are tied by their overlap already). The map keeps
    the frame of the chunk that created it (updates are moved into it), so the recall's Sim(3) maps
    the recalling chunk's frame into the creator's."""
    creator = {}
    loops = []
    for k, res in enumerate(results):
        for w in res.windows:
            made = creator.get(w.recalled_map)
            if w.accepted and made is not None and k - made[0] >= min_gap:
                loops.append(LoopClosure(chunk=k, other=made[0], frames=tuple(w.frames),
                                         transform=np.asarray(w.transform, np.float64),
                                         inliers=int(w.inlier_count), rmse=float(w.rmse), other_frames=made[1]))
            if w.created_map and w.map_id >= 0:
                creator.setdefault(w.map_id, (k, tuple(w.frames)))
    return loops


def window_frame_change(chunk: Sequence, refined, frames, config: StitchConfig = StitchConfig()):
    """The Sim(3) (4, 4) from a window's refined frame to its chunk's prior frame: the window's
    frames ``[f0, f1]`` (inclusive) are lifted on a pixel grid with the prior poses and with the
    ``refined`` poses (S, 4, 4) and fitted like an overlap (:func:`align_overlap`: the same pixels
    of the same frames, no matching). The pipeline refines each window starting from the prior, so
    this is near the identity; what is left is the window's refinement, as a similarity."""
    f0, f1 = int(frames[0]), int(frames[1])
    sl = slice(f0, f1 + 1)
    with jax.enable_x64(True):
        prior = (_f(chunk.depth[sl]), _f(chunk.intrinsic[sl]), _f(chunk.cam_to_world[sl]))
        ref = (_f(chunk.depth[sl]), _f(chunk.intrinsic[sl]), _f(np.asarray(refined)[sl]))
        D, _ = align_overlap(prior, ref, cfg=config)
    return np.asarray(D, np.float64)


def loop_to_prior_frames(lc: LoopClosure, chunks, results, config: StitchConfig = StitchConfig()) -> LoopClosure:
    """A loop closure's transform re-expressed between the two chunks' *prior* frames.

    The memory verifies a recall between clouds built from the pipeline's *refined* window poses
    (the recalling window's, and the creating window's for the map), while the pose graph places the
    chunks' priors: ``T' = D_other T D_chunk^{-1}``, ``D`` the window's refined -> prior frame change
    (:func:`window_frame_change`). Without it a loop carries the two windows' refinements as if they
    were a difference between the chunks (measured on the loop video, ``docs/long_video.md``: the
    recall's centre error 0.32 m -> 0.19 m in one run, 0.230 -> 0.226 m in another; the recall's own
    registration error dominates)."""
    if lc.other_frames is None:
        raise StitchError(f"loops: chunk {lc.chunk} -> {lc.other} does not name the creating window's frames")
    Dc = window_frame_change(chunks[lc.chunk], results[lc.chunk].poses, lc.frames, config)
    Do = window_frame_change(chunks[lc.other], results[lc.other].poses, lc.other_frames, config)
    T = Do @ np.asarray(lc.transform, np.float64) @ np.linalg.inv(Dc)
    return dataclasses.replace(lc, transform=T, measured=np.asarray(lc.transform, np.float64))


def measure_loop(lc: LoopClosure, chunks, G, config: StitchConfig = StitchConfig(),
                 frame_config: FrameGraphConfig = FrameGraphConfig(), max_pairs: int = 8,
                 max_angle_deg: float = 20.0) -> LoopClosure:
    """A loop closure measured frame to frame, like an overlap, instead of by the memory's coarse
    cloud registration.

    The recalling window's frames (``lc.frames`` of chunk ``lc.chunk``) and the creating window's
    (``lc.other_frames`` of ``lc.other``) are placed by the current chunk transforms ``G`` (K, 4, 4)
    (e.g. the chain of overlap alignments); each recalling frame is paired with the creating frame
    nearest in pose (centre distance over the median depth plus the viewing angle), pairs within
    ``max_angle_deg`` kept, the ``max_pairs`` closest used. Each pair's relative Sim(3) is measured
    from the images and depths (:func:`measure_frame_pairs`: flow across the two chunks, robust
    fit), which is independent of the chunks' pose noise, and gives ``L_p = P_a[j] M_p P_b[i]^{-1}``
    (chunk -> other). The loop's Sim(3) is the robust fit of every pair's lifted grid pixels mapped
    by its ``L_p`` (as :func:`align_overlap` does for shared frames); its ``sigma`` is the pairs'
    scatter in the chart over sqrt(pairs) (:func:`stitch_with_memory` floors it at the pose graph's
    overlap sigmas). Returns the loop with ``transform``, ``sigma`` and ``pairs`` replaced (``measured``
    keeps the memory's transform); unchanged when no pair passes (``pairs`` 0)."""
    if lc.other_frames is None:
        raise StitchError(f"loops: chunk {lc.chunk} -> {lc.other} does not name the creating window's frames")
    a, b = lc.other, lc.chunk
    ca, cb = chunks[a], chunks[b]
    fa = np.arange(int(lc.other_frames[0]), int(lc.other_frames[1]) + 1)
    fb = np.arange(int(lc.frames[0]), int(lc.frames[1]) + 1)
    G = np.asarray(G, np.float64)
    with jax.enable_x64(True):
        pa = np.asarray(place_poses(_f(G[a]), _f(ca.cam_to_world[fa])))
        pb = np.asarray(place_poses(_f(G[b]), _f(cb.cam_to_world[fb])))
    depth = np.asarray(ca.depth[fa], np.float64)
    unit = float(np.median(depth[depth > 0])) if np.any(depth > 0) else 1.0
    unit *= float(np.cbrt(np.linalg.det(G[a][:3, :3])))  # the median depth in common units
    dist = np.linalg.norm(pb[:, None, :3, 3] - pa[None, :, :3, 3], axis=-1) / unit
    cosang = np.clip((np.einsum("bij,aij->ba", pb[:, :3, :3], pa[:, :3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    ang = np.rad2deg(np.arccos(cosang))
    score = dist + np.deg2rad(ang)
    jbest = np.argmin(score, axis=1)
    keep = ang[np.arange(len(fb)), jbest] <= max_angle_deg
    order = np.argsort(score[np.arange(len(fb)), jbest])
    order = [o for o in order if keep[o]][:max_pairs]
    if not order:
        return dataclasses.replace(lc, pairs=0)
    pairs = np.array([(fa[jbest[o]], fb[o]) for o in order], np.int64)  # (frame of other, frame of chunk)
    M, frac, npts, rel = measure_frame_pairs(ca, pairs, None, frame_config, other=cb,
                                             pad_to=frame_config.pad_frames - 1)  # refine_frames' program
    good = ((frac >= frame_config.min_inlier_fraction) & (npts >= frame_config.min_points)
            & (rel <= frame_config.max_residual))
    if not np.any(good):
        return dataclasses.replace(lc, pairs=0)
    pairs, M = pairs[good], M[good]
    L = np.stack([ca.cam_to_world[j] @ m @ np.linalg.inv(cb.cam_to_world[i]) for (j, i), m in zip(pairs, M)])
    # one fit over every pair: frame i's grid pixels in chunk b's frame -> their images under L_p
    H, W = cb.image_size
    rows, cols = _sample_grid(H, W, config.grid)
    with jax.enable_x64(True):
        src, ok = (np.asarray(x) for x in _lift_jit(_f(cb.depth[pairs[:, 1]]), _f(cb.intrinsic[pairs[:, 1]]),
                                                      _f(cb.cam_to_world[pairs[:, 1]]), jnp.asarray(rows),
                                                      jnp.asarray(cols)))
        per = rows.size * cols.size
        dst = np.concatenate([src[p * per:(p + 1) * per] @ L[p, :3, :3].T + L[p, :3, 3] for p in range(len(L))])
        cap = max(max_pairs, len(L)) * per  # one compiled fit per max_pairs
        T = robust_sim3(_f(_pad(src, cap, "zeros")), _f(_pad(dst, cap, "zeros")), jnp.asarray(_pad(ok, cap, "zeros")),
                        iterations=config.robust_iterations, k=config.robust_k)[0]
        T = np.asarray(T, np.float64)
        chart = np.asarray(jax.vmap(_sim3_log)(_f(np.linalg.inv(T)[None] @ L)))
    n = len(L)
    spread = np.sqrt(np.sum(chart ** 2, 0) / max(n - 1, 1)) / np.sqrt(n) if n > 1 else np.full(7, np.inf)
    return dataclasses.replace(lc, transform=T, sigma=spread, pairs=int(n),
                               measured=lc.measured if lc.measured is not None else np.asarray(lc.transform))


def memory_config_for_chunks(height: int, width: int, chunk_lengths, **changes):
    """The pipeline config for chunks of a long video: :func:`cm3d.pipeline.config_for` (``changes``
    passed on), with windows of 20 frames (the paper's) unless that leaves the longest chunk fewer
    than two (then at most half of it, at least config_for's), and room in a new bank for one map
    per window of every chunk. chunk_lengths: frames per chunk."""
    from cm3d import pipeline

    lengths = [int(n) for n in chunk_lengths]
    if not lengths or min(lengths) < 2:
        raise StitchError(f"chunk_lengths: every chunk needs at least 2 frames, got {lengths}")
    cfg = pipeline.config_for(height, width, **changes)
    if "keyframe_interval" not in changes:
        cfg = dataclasses.replace(cfg, keyframe_interval=max(cfg.keyframe_interval, min(20, max(lengths) // 2)))
    ki = cfg.keyframe_interval
    windows = sum(-(-(n - 1) // ki) for n in lengths)  # a window ends every ki frames and at the last
    mem = dataclasses.replace(cfg.memory, max_maps=max(cfg.memory.max_maps, windows))
    return dataclasses.replace(cfg, memory=mem)


def stitch_with_memory(chunks, overlap: int | None = None, config: StitchConfig = StitchConfig(),
                       pipeline_config=None, bank=None, graph: PoseGraphConfig = PoseGraphConfig(),
                       progress=None, use_refined: bool = False, measure_loops: bool = False,
                       refine: bool = True, frame_config: FrameGraphConfig = FrameGraphConfig(),
                       results=None) -> StitchResult:
    """Stitch chunks with memory recall across them, then refine the whole trajectory.

    1. every chunk runs through the pipeline (:func:`cm3d.pipeline.run`: motion cues, windowed
       factor graph, memory recall / verify / update) threading **one** memory bank, so a chunk that
       comes back to an earlier place recalls the earlier chunk's map;
    2. consecutive chunks are aligned by Sim(3) on their shared frames (as :func:`stitch_chunks`),
       from the chunks' prior poses (``use_refined``: from the pipeline's refined poses instead; at
       96x128 that was worse: the per-chunk refinement's scale and translation errors break the
       alignment, ATE 0.154 against 0.022 on the loop video, moderate noise);
    3. each accepted recall of a chunk at least two chunks earlier is a Sim(3) loop constraint
       (:func:`recall_loops`), re-expressed between the chunks' prior frames
       (:func:`loop_to_prior_frames`; not with ``use_refined``), and the chunk transforms are
       refined by a Sim(3) pose graph (:func:`sim3_pose_graph`): overlap + loop constraints, scale
       included, so the drift the chain of alignments accumulates is spread back along the loop;
       a loop inconsistent with the chain (χ² check) is left out. ``measure_loops``: each loop is
       first re-measured frame to frame (:func:`measure_loop`: flow + depth between the revisiting
       frames and the frames they revisit) with its sigma from the pairs' scatter (floored at the
       overlap sigmas); a loop no frame pair supports keeps the memory's transform and the coarse
       loop sigma. Off by default: on the synthetic loop videos such a loop is no more accurate
       than the chain of overlaps (it carries the revisiting chunk's own prior drift) and raised
       ATE (docs/long_video.md);
    4. the chunks are placed by the refined transforms and fused (the stitched priors);
    5. ``refine``: the whole trajectory is refined in one pose graph over every frame
       (:func:`refine_frames`: image-measured relative motions across chunk boundaries, static
       pixels from the pipeline's motion masks), kept when it passes its self-check.

    pipeline_config: the pipeline's config (None: :func:`memory_config_for_chunks`); bank: a memory
    bank to start from (e.g. loaded with ``--memory``); progress: optional ``(stage, done, total)``
    callable (:func:`cm3d.pipeline.run`'s); results: the pipeline's per-chunk results of an
    earlier call (skips step 1; ``bank`` is then returned as given). Returns :class:`StitchResult`
    (method ``"cm3d-memory"``) with ``loops``, ``bank`` and the per-chunk pipeline ``results``
    filled in; ``poses_aligned``: the chained overlap alignment; ``refinement`` holds the pose
    graph's facts (per loop: ``loop_discrepancy``, ``loop_kept``), ``poses_stitched`` (the pose
    graph's placement of the priors) and ``frames`` (:func:`refine_frames`' facts);
    ``sequence.cam_to_world`` is the refined trajectory when kept, else ``poses_stitched``.
    """
    from cm3d import pipeline

    chunks = _check_chunks(chunks)
    ranges, overlaps, ts = chunk_layout(chunks, overlap)
    H, W = chunks[0].image_size
    cfg = pipeline_config or memory_config_for_chunks(H, W, [c.num_frames for c in chunks])
    t0 = time.perf_counter()
    if results is None:
        bank, results = pipeline.run(list(chunks), cfg, bank, progress=progress)
    t_pipe = time.perf_counter() - t0
    refined = [c.replace(cam_to_world=r.poses) for c, r in zip(chunks, results)] if use_refined else chunks
    with jax.enable_x64(True):
        A, G0, bounds = _boundaries(refined, ranges, overlaps, None, None, config, fit=True)
    loops = recall_loops(results)
    if not use_refined:
        loops = [loop_to_prior_frames(lc, chunks, results, config) for lc in loops]
        if measure_loops:
            base = np.array([graph.sigma_rot] * 3 + [graph.sigma_trans] * 3 + [graph.sigma_scale])
            loops = [measure_loop(lc, chunks, G0, config, frame_config) for lc in loops]
            loops = [dataclasses.replace(lc, sigma=np.maximum(lc.sigma, base)) if lc.pairs else lc for lc in loops]
    G, facts = sim3_pose_graph(G0, A, loops, graph)
    with jax.enable_x64(True):
        seq, frame_chunk = _merge(refined, ranges, overlaps, ts, G, "cm3d-memory")
        chained, _ = _merge(refined, ranges, overlaps, ts, G0, "cm3d-memory")
    stitched, frame_facts, kept = seq.cam_to_world, {"kept": False}, False
    if refine:
        static = np.ones(seq.depth.shape, bool)
        for k, ((a, b), r) in enumerate(zip(ranges, results)):
            mine = np.flatnonzero(frame_chunk[a:b] == k)
            static[a + mine] = ~np.asarray(r.masks, bool)[mine]
        noise = float(np.sqrt(np.mean([b.rmse_centres ** 2 for b in bounds])) / np.sqrt(2.0)) if bounds else None
        poses, frame_facts = refine_frames(seq, static, frame_config, noise,
                                           _rotation_noise(refined, ranges, overlaps, G))
        kept = frame_facts["kept"]
        seq = seq.replace(cam_to_world=poses)
    facts = {**facts, "chained_transforms": G0, "pipeline_s": t_pipe, "windows": sum(len(r.windows) for r in results),
             "recalls": sum(int(w.accepted) for r in results for w in r.windows), "use_refined": bool(use_refined),
             "poses_stitched": stitched, "frames": frame_facts, "loops_measured": sum(lc.pairs > 0 for lc in loops)}
    return StitchResult(sequence=seq, poses_aligned=chained.cam_to_world, poses_refined=seq.cam_to_world,
                        chunk_transforms=G, ranges=ranges, frame_chunk=frame_chunk, boundaries=bounds,
                        refined=kept, refinement=facts, method="cm3d-memory",
                        loops=tuple(loops), bank=bank, results=tuple(results))


def place_chunks(chunks, transforms, overlap: int | None = None) -> Sequence:
    """The merged sequence of chunks placed by given Sim(3)s ``transforms`` (K, 4, 4), chunk k ->
    common frame (e.g. a pose graph's, or ground truth's for a reference), fused as in
    :func:`stitch_chunks`."""
    chunks = _check_chunks(chunks)
    ranges, overlaps, ts = chunk_layout(chunks, overlap)
    G = np.asarray(transforms, np.float64)
    if G.shape != (len(chunks), 4, 4):
        raise StitchError(f"transforms: expected shape ({len(chunks)}, 4, 4) (one per chunk), got {G.shape}")
    with jax.enable_x64(True):
        return _merge(chunks, ranges, overlaps, ts, G, "placed")[0]


def memory_sequence_result(res: StitchResult, chunks):
    """A :class:`cm3d.pipeline.SequenceResult` of the whole video from :func:`stitch_with_memory`,
    for the output writers (``cm3d run chunk0.npz chunk1.npz ... --memory BANK``): the pose-graph
    trajectory, the overlap-stitched priors as the prior, each frame's mask from the chunk its image
    comes from, and every chunk's windows with global frame numbers and a ``chunk`` field."""
    from cm3d import pipeline

    if res.method != "cm3d-memory":
        raise StitchError(f"res: expected a stitch_with_memory result, got method {res.method!r}")
    prior = (stitch_chunks(chunks, refine=False).sequence.cam_to_world if res.refinement.get("use_refined")
             else res.refinement.get("poses_stitched", res.poses_aligned))  # the pose graph's placement of the priors
    masks = np.zeros(res.sequence.depth.shape, bool)
    windows = []
    for k, ((a, b), r) in enumerate(zip(res.ranges, res.results)):
        mine = np.flatnonzero(res.frame_chunk[a:b] == k)
        masks[a + mine] = r.masks[mine]
        for w in r.windows:
            windows.append(dataclasses.replace(w, chunk=k, frames=(w.frames[0] + a, w.frames[1] + a)))
    return pipeline.SequenceResult(poses=np.asarray(res.sequence.cam_to_world), prior=np.asarray(prior),
                                   masks=masks, windows=windows, sequence=res.sequence)


# ----------------------------------------------------------------------------------------------
# Chunk files


def concat_chunks(chunks) -> tuple[Sequence, np.ndarray]:
    """Chunks concatenated frame by frame (shared frames repeated) -> (Sequence, chunk index (S_total,)).

    ``gt_flow`` pairs straddling two chunks are zeros; meta is ``{"chunks": [meta_k, ...]}``.
    """
    chunks = _check_chunks(chunks)
    idx = np.concatenate([np.full(c.num_frames, k, np.int64) for k, c in enumerate(chunks)])
    cat = lambda xs: np.concatenate(xs)  # noqa: E731
    wp = None if any(c.world_points is None for c in chunks) else cat([c.world_points for c in chunks])
    gt = None
    if all(c.gt is not None for c in chunks):
        gts = [c.gt for c in chunks]
        flow = None
        if all(g.flow is not None for g in gts):
            z = np.zeros((1,) + gts[0].flow.shape[1:], np.float32)
            flow = cat([x for g in gts for x in (g.flow, z)][:-1])
        gt = GroundTruth(cam_to_world=cat([g.cam_to_world for g in gts]), depth=cat([g.depth for g in gts]),
                         intrinsic=cat([g.intrinsic for g in gts]),
                         dynamic_mask=None if any(g.dynamic_mask is None for g in gts)
                         else cat([g.dynamic_mask for g in gts]), flow=flow)
    seq = Sequence(images=cat([c.images for c in chunks]), depth=cat([c.depth for c in chunks]),
                   depth_conf=cat([c.depth_conf for c in chunks]), intrinsic=cat([c.intrinsic for c in chunks]),
                   cam_to_world=cat([c.cam_to_world for c in chunks]), timestamps=cat([c.timestamps for c in chunks]),
                   world_points=wp, gt=gt, meta={"chunks": [c.meta for c in chunks]})
    return seq, idx


def split_chunks(seq: Sequence, chunk_index, source: str = "<memory>") -> list[Sequence]:
    """Split a concatenated sequence by its per-frame ``chunk`` index (S,) int (0, 1, ..., K-1 in
    non-decreasing order, every index present) into K chunks; inverse of :func:`concat_chunks`."""
    c = np.asarray(chunk_index)
    if c.shape != (seq.num_frames,):
        raise StitchError(f"{source}: key 'chunk': shape {c.shape}, expected ({seq.num_frames},) (one per frame)")
    if not np.issubdtype(c.dtype, np.integer):
        raise StitchError(f"{source}: key 'chunk': dtype {c.dtype} is not an integer type")
    if c.size == 0 or c[0] != 0 or np.any(np.diff(c) < 0) or np.any(np.diff(c) > 1):
        raise StitchError(f"{source}: key 'chunk': must run 0, 1, ..., K-1 in non-decreasing order without "
                          f"gaps (chunks stored one after the other), got {np.unique(c).tolist()[:10]}")
    metas = seq.meta.get("chunks") if isinstance(seq.meta.get("chunks"), list) else None
    K = int(c[-1]) + 1
    if metas is not None and len(metas) != K:
        metas = None
    out = []
    for k in range(K):
        a, b = np.flatnonzero(c == k)[[0, -1]]
        part = seq.slice(int(a), int(b) + 1)
        out.append(part.replace(meta=dict(metas[k]) if metas is not None else dict(seq.meta)))
    return out


def save_chunks(path: str | os.PathLike, chunks, compress: bool = False) -> None:
    """Write every chunk to one ``.npz``: the sequence format plus a ``chunk`` key (atomic)."""
    seq, idx = concat_chunks(chunks)
    path = Path(path)
    tmp = path.with_name(f".{path.name}.chunks.npz")
    try:
        io.save_sequence(tmp, seq, compress=compress)
        with np.load(tmp, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    finally:
        if tmp.exists():
            tmp.unlink()
    arrays["chunk"] = idx
    with atomic_write(path, "wb") as f:
        (np.savez_compressed if compress else np.savez)(f, **arrays)


def load_chunks(paths) -> list[Sequence]:
    """Chunks from a list of chunk ``.npz`` files (one sequence each, in temporal order), or from one
    file (a path or a one-element list) holding a ``chunk`` key (see the module docstring)."""
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    paths = [Path(p) for p in paths]
    if not paths:
        raise StitchError("paths: empty list, need at least one chunk file")
    for p in paths:
        if not p.is_file():
            raise FileNotFoundError(f"{p}: no such file")
    if len(paths) == 1:
        with np.load(paths[0], allow_pickle=False) as npz:
            chunk = npz["chunk"] if "chunk" in npz.files else None
        seq = io.load_sequence(paths[0])
        return [seq] if chunk is None else split_chunks(seq, chunk, source=str(paths[0]))
    out = []
    for p in paths:
        with np.load(p, allow_pickle=False) as npz:
            if "chunk" in npz.files:
                raise StitchError(f"{p}: key 'chunk': a file holding several chunks must be loaded alone")
        out.append(io.load_sequence(p))
    return out
