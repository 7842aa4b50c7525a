"""Stitching overlapping, separately normalised chunks into one trajectory.

VGGT runs out of memory beyond a few dozen frames, so a long video runs in overlapping chunks,
each in its own frame and scale. :func:`stitch_chunks`: align each boundary by a robust Sim(3)
(:mod:`~cm3d.long_video.overlap`), chain into chunk 0's frame, fuse the shared frames
(:mod:`~cm3d.long_video.fuse`), refine in one frame graph (:mod:`~cm3d.long_video.frame_graph`).
:func:`naive_stitch` is the common rigid, scale-blind baseline.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from cm3d.data.sequence import Sequence
from cm3d.long_video.frame_graph import FrameGraphConfig, refine_frames, rotation_noise
from cm3d.long_video.fuse import merge_chunks, place_poses
from cm3d.long_video.layout import StitchError, check_chunks, chunk_layout
from cm3d.long_video.overlap import Boundary, StitchConfig, align_boundaries
from cm3d.ops import sim3


@dataclasses.dataclass(frozen=True)
class StitchResult:
    """A stitched long video.

    sequence: merged :class:`Sequence` (chunk 0's frame and scale; refined poses when kept, fused
    depth; ground truth when every chunk has it); poses_aligned (S, 4, 4): the stitched priors (align
    + chain + fuse); poses_refined (S, 4, 4) or None; chunk_transforms (K, 4, 4): ``G_k`` chunk k ->
    common; ranges: global [start, stop) per chunk; frame_chunk (S,): the chunk of each frame's image;
    boundaries: one :class:`Boundary` each; refined: the gate kept the refinement; refinement: its
    facts; method: "cm3d", "naive" or "cm3d-memory" (then also ``loops``, ``bank``, ``results``).
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


def centre_noise(bounds) -> float | None:
    """Per-frame centre noise from the overlaps: two chunks' independent estimates of a shared
    frame differ by sqrt(2) σ (None without boundaries)."""
    return float(np.sqrt(np.mean([b.rmse_centres ** 2 for b in bounds])) / np.sqrt(2.0)) if bounds else None


def stitch_chunks(chunks, overlap: int | None = None, config: StitchConfig = StitchConfig(), static=None,
                  refine: bool = True, frame_config: FrameGraphConfig = FrameGraphConfig()) -> StitchResult:
    """Stitch overlapping chunks (each in its own frame and scale) into one sequence.

    chunks: :class:`Sequence` list in temporal order; overlap: shared frames per boundary (None: from
    timestamps); static: optional (S, H, W) bool of the merged frames for the refinement. A single
    chunk is returned as it is. Returns :class:`StitchResult`.
    """
    if refine not in (True, False):
        raise StitchError(f"refine: expected True or False, got {refine!r}")
    chunks = check_chunks(chunks)
    ranges, overlaps, ts = chunk_layout(chunks, overlap)
    S, (H, W) = ranges[-1][1], chunks[0].image_size
    if static is not None:
        static = np.asarray(static, bool)
        if static.shape != (S, H, W):
            raise StitchError(f"static: expected shape {(S, H, W)} (merged frames, H, W), got {static.shape}")
    _, G, bounds = align_boundaries(chunks, ranges, overlaps, config)
    seq, frame_chunk = merge_chunks(chunks, ranges, overlaps, ts, G, "cm3d")
    aligned, refined_poses, facts, use = seq.cam_to_world, None, {}, False
    if refine:
        refined_poses, facts = refine_frames(seq, static, frame_config, centre_noise(bounds),
                                             rotation_noise(chunks, overlaps, G))
        use = facts["kept"]
        seq = seq.replace(cam_to_world=refined_poses)
    seq = seq.replace(meta={**seq.meta, "stitched": {**seq.meta["stitched"], "refined": bool(use)}})
    return StitchResult(sequence=seq, poses_aligned=aligned, poses_refined=refined_poses, chunk_transforms=G,
                        ranges=ranges, frame_chunk=frame_chunk, boundaries=bounds, refined=use,
                        refinement=facts, method="cm3d")


def naive_stitch(chunks, overlap: int | None = None, config: StitchConfig = StitchConfig()) -> StitchResult:
    """The common naive stitching: chunk k placed rigidly (SE(3), no scale) on chunk k-1's pose of their
    first shared frame; shared frames keep the earlier chunk's pose and depth. Diagnostics as
    :func:`stitch_chunks` (scale 1)."""
    chunks = check_chunks(chunks)
    ranges, overlaps, ts = chunk_layout(chunks, overlap)
    M = [np.eye(4)]
    for k in range(1, len(chunks)):
        first = place_poses(M[-1], chunks[k - 1].cam_to_world)[-overlaps[k - 1]]
        M.append(first @ sim3.inverse(np.asarray(chunks[k].cam_to_world[0], np.float64)))
    A = [np.eye(4)] + [np.linalg.inv(M[k - 1]) @ M[k] for k in range(1, len(chunks))]
    _, _, bounds = align_boundaries(chunks, ranges, overlaps, config, A=A)
    weights = []
    for k, (a, b) in enumerate(ranges):
        w = np.ones(b - a)
        if k > 0:
            w[:overlaps[k - 1]] = 0.0
        weights.append(w)
    seq, frame_chunk = merge_chunks(chunks, ranges, overlaps, ts, np.stack(M), "naive", weights)
    return StitchResult(sequence=seq, poses_aligned=seq.cam_to_world, poses_refined=None,
                        chunk_transforms=np.stack(M), ranges=ranges, frame_chunk=frame_chunk,
                        boundaries=bounds, refined=False, refinement={}, method="naive")
