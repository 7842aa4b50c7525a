"""Long videos: overlapping, separately normalised chunks stitched into one trajectory.

Modules, in pipeline order: :mod:`~cm3d.long_video.layout` (chunk checks, frame ranges, overlaps),
:mod:`~cm3d.long_video.overlap` (Sim(3) per boundary from the shared frames),
:mod:`~cm3d.long_video.fuse` (place and fuse into one sequence), :mod:`~cm3d.long_video.frame_graph`
(whole-trajectory refinement), :mod:`~cm3d.long_video.stitch` (:func:`stitch_chunks`,
:func:`naive_stitch`), :mod:`~cm3d.long_video.pose_graph` (Sim(3) pose graph over the chunks),
:mod:`~cm3d.long_video.memory_loops` (memory recalls as loop closures, :func:`stitch_with_memory`),
:mod:`~cm3d.long_video.chunk_files` (every chunk in one ``.npz``). Poses are cam_to_world 4x4
(:mod:`cm3d.ops.se3`); host bookkeeping (chaining, placing, fusing poses) is NumPy float64, the
jitted fits and solves run in the inputs' JAX dtype (float32 by default).

    chunks = load_chunks(["c0.npz", "c1.npz", ...])   # or load_chunks("all.npz") with a `chunk` key
    res = stitch_chunks(chunks, overlap=None, config=StitchConfig(), static=None, refine=True)
    res.sequence, res.poses_aligned, res.boundaries, res.summary()
    base = naive_stitch(chunks)                          # the baseline, also a StitchResult
    mem = stitch_with_memory(chunks, bank=None)          # memory recall across chunks + Sim(3) pose graph
"""

from cm3d.long_video.chunk_files import concat_chunks, load_chunks, save_chunks, split_chunks
from cm3d.long_video.frame_graph import (FrameGraphConfig, PairMeasurements, frame_graph, frame_pair_points,
                                         measure_frame_pairs, refine_frames)
from cm3d.long_video.fuse import fuse_frames, place_chunks, place_poses
from cm3d.long_video.layout import ChunkLayout, StitchError, chunk_layout
from cm3d.long_video.memory_loops import (loop_to_prior_frames, memory_config_for_chunks, memory_sequence_result,
                                          recall_loops, stitch_with_memory, window_frame_change)
from cm3d.long_video.overlap import Boundary, OverlapFit, StitchConfig, align_overlap, lift_pixels
from cm3d.long_video.pose_graph import LoopClosure, PoseGraphConfig, sim3_pose_graph
from cm3d.long_video.stitch import StitchResult, naive_stitch, stitch_chunks

__all__ = ["Boundary", "ChunkLayout", "FrameGraphConfig", "LoopClosure", "OverlapFit", "PairMeasurements",
           "PoseGraphConfig", "StitchConfig", "StitchError", "StitchResult", "align_overlap", "chunk_layout",
           "concat_chunks", "frame_graph", "frame_pair_points", "fuse_frames", "lift_pixels", "load_chunks",
           "loop_to_prior_frames", "measure_frame_pairs", "memory_config_for_chunks", "memory_sequence_result",
           "naive_stitch", "place_chunks", "place_poses", "recall_loops", "refine_frames", "save_chunks",
           "sim3_pose_graph", "split_chunks", "stitch_chunks", "stitch_with_memory", "window_frame_change"]
