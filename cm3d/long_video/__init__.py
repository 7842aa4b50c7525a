"""Long videos: overlapping, separately normalised chunks stitched into one trajectory.

Modules in pipeline order: ``layout`` (chunk checks, ranges, overlaps), ``overlap`` (Sim(3) per
boundary), ``fuse`` (place and fuse), ``frame_graph`` (whole-trajectory refinement), ``stitch``,
``loops`` (loop closures measured in the images, frame-level graph), ``pose_graph`` (Sim(3) graph over
chunks), ``memory_loops`` (recalls as loop closures),
``chunk_files``. Host bookkeeping is NumPy float64; jitted fits run in the inputs' dtype.

    chunks = load_chunks(["c0.npz", "c1.npz", ...])   # or load_chunks("all.npz") with a `chunk` key
    res = stitch_chunks(chunks, overlap=None, config=StitchConfig(), static=None, refine=True)
    base = naive_stitch(chunks)                          # the baseline, also a StitchResult
    mem = stitch_with_memory(chunks, bank=None)          # memory recall across chunks + Sim(3) pose graph
"""

from cm3d.long_video.chunk_files import concat_chunks, load_chunks, save_chunks, split_chunks
from cm3d.long_video.frame_graph import (FrameGraphConfig, PairMeasurements, frame_graph, frame_pair_points,
                                         measure_frame_pairs, refine_frames)
from cm3d.long_video.fuse import fuse_frames, place_chunks, place_poses
from cm3d.long_video.layout import ChunkLayout, StitchError, chunk_layout
from cm3d.long_video.loops import LoopConfig, close_loops, loop_candidates, measure_loops, solve_loops
from cm3d.long_video.memory_loops import (loop_to_prior_frames, memory_config_for_chunks, memory_sequence_result,
                                          recall_loops, stitch_with_memory, window_frame_change)
from cm3d.long_video.overlap import Boundary, OverlapFit, StitchConfig, align_overlap, lift_pixels
from cm3d.long_video.pose_graph import LoopClosure, PoseGraphConfig, sim3_pose_graph
from cm3d.long_video.stitch import StitchResult, naive_stitch, stitch_chunks

__all__ = ["Boundary", "ChunkLayout", "FrameGraphConfig", "LoopClosure", "LoopConfig", "OverlapFit",
           "PairMeasurements", "PoseGraphConfig", "StitchConfig", "StitchError", "StitchResult", "align_overlap",
           "chunk_layout", "close_loops", "concat_chunks", "frame_graph", "frame_pair_points", "fuse_frames",
           "lift_pixels", "load_chunks", "loop_candidates", "loop_to_prior_frames", "measure_frame_pairs",
           "measure_loops", "memory_config_for_chunks", "memory_sequence_result", "naive_stitch", "place_chunks",
           "place_poses", "recall_loops", "refine_frames", "save_chunks", "sim3_pose_graph", "solve_loops",
           "split_chunks", "stitch_chunks", "stitch_with_memory", "window_frame_change"]
