"""Memory recall across chunks: loop closures from the pipeline's memory, the Sim(3) pose graph over
the chunks, and the whole-trajectory refinement (:func:`stitch_with_memory`).

Chunks run through the pipeline with one memory bank; a recall of a map that the previous chunk
did not write is a Sim(3) loop (:func:`recall_loops`, :func:`loop_to_prior_frames`).
"""

from __future__ import annotations

import dataclasses
import time

import jax.numpy as jnp
import numpy as np

from cm3d.data.sequence import Sequence
from cm3d.long_video.frame_graph import FrameGraphConfig, refine_frames, rotation_noise
from cm3d.long_video.fuse import merge_chunks, place_poses
from cm3d.long_video.layout import StitchError, check_chunks, chunk_layout
from cm3d.long_video.loops import LoopConfig, close_loops, motion_noise
from cm3d.long_video.overlap import StitchConfig, align_boundaries, align_overlap
from cm3d.long_video.pose_graph import LoopClosure, PoseGraphConfig, sim3_pose_graph
from cm3d.long_video.stitch import StitchResult, centre_noise


def recall_loops(results, min_gap: int = 2) -> list[LoopClosure]:
    """Loop closures from the pipeline's per-chunk results: every accepted recall of a map that
    neither the last ``min_gap - 1`` chunks nor an earlier window of the recalling chunk wrote
    (created or merged into). A map keeps its creator chunk's frame, so the recall's Sim(3) maps
    the recalling chunk's frame into the creator's.

    A map the chunks keep extending as the camera moves on (each chunk recalls the map its
    predecessor just merged into) is the chain of overlaps again, not a return to an earlier place:
    its recalls are measured against the newest chunks' content, already tied to the recalling
    chunk by the overlaps, and as loops to the creator they would count the chain twice."""
    creator, written = {}, {}
    loops = []
    for k, res in enumerate(results):
        for w in res.windows:
            made = creator.get(w.recalled_map)
            if w.accepted and made is not None and k - written[w.recalled_map] >= min_gap:
                loops.append(LoopClosure(chunk=k, other=made[0], frames=tuple(w.frames),
                                         transform=np.asarray(w.transform, np.float64),
                                         inliers=int(w.inlier_count), rmse=float(w.rmse), other_frames=made[1]))
            if w.map_id >= 0:
                if w.created_map:
                    creator.setdefault(w.map_id, (k, tuple(w.frames)))
                written[w.map_id] = k
    return loops


def window_frame_change(chunk: Sequence, refined, frames, config: StitchConfig = StitchConfig()):
    """The Sim(3) (4, 4) from a window's refined frame to its chunk's prior frame: the window's
    frames ``[f0, f1]`` (inclusive) are lifted on a pixel grid with the prior poses and with the
    ``refined`` poses (S, 4, 4) and fitted like an overlap (:func:`align_overlap`: the same pixels
    of the same frames, no matching). Near the identity: what is left is the window's refinement."""
    sl = slice(int(frames[0]), int(frames[1]) + 1)
    d, K = jnp.asarray(chunk.depth[sl]), jnp.asarray(chunk.intrinsic[sl])
    fit = align_overlap((d, K, jnp.asarray(chunk.cam_to_world[sl])), (d, K, jnp.asarray(np.asarray(refined)[sl])),
                        cfg=config)
    return np.asarray(fit.transform, np.float64)


def loop_to_prior_frames(lc: LoopClosure, chunks, results, config: StitchConfig = StitchConfig()) -> LoopClosure:
    """A loop closure's transform re-expressed between the frames of the two ``chunks``' poses.

    The memory verifies a recall between clouds built from the pipeline's *refined* window poses;
    the pose graph places ``chunks``: ``T' = D_other T D_chunk^{-1}``, ``D`` the window's refined ->
    chunk frame change (:func:`window_frame_change`). For chunks carrying their priors ``D`` is
    what the window's refinement did; for chunks carrying the refined poses
    (:func:`stitch_with_memory`) it is the identity."""
    if lc.other_frames is None:
        raise StitchError(f"loops: chunk {lc.chunk} -> {lc.other} does not name the creating window's frames")
    Dc = window_frame_change(chunks[lc.chunk], results[lc.chunk].poses, lc.frames, config)
    Do = window_frame_change(chunks[lc.other], results[lc.other].poses, lc.other_frames, config)
    T = Do @ np.asarray(lc.transform, np.float64) @ np.linalg.inv(Dc)
    return dataclasses.replace(lc, transform=T, measured=np.asarray(lc.transform, np.float64))


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
                       progress=None, refine: bool = True, frame_config: FrameGraphConfig = FrameGraphConfig(),
                       results=None, observe=None, loop_config: LoopConfig = LoopConfig()) -> StitchResult:
    """Stitch chunks with memory recall across them, then refine the whole trajectory.

    Run every chunk with one memory bank; align consecutive chunks' *refined* poses (each chunk's
    :attr:`~cm3d.pipeline.SequenceResult.poses`) on their shared frames; put loops and overlaps in the
    Sim(3) pose graph (inconsistent loops left out); place and fuse the refined chunks; ``refine``: loop
    closures measured in the images (:func:`cm3d.long_video.close_loops`, ``loop_config``), then
    :func:`cm3d.long_video.refine_frames`, each kept when it passes its own check.
    pipeline_config: None for :func:`memory_config_for_chunks`; bank: a bank to start from; progress:
    optional ``(stage, done, total)``; results: per-chunk results of an earlier call (skips the runs);
    observe: passed to :func:`cm3d.pipeline.run` (called after each chunk).
    Returns :class:`StitchResult` (method ``"cm3d-memory"``, with ``loops``, ``bank``, ``results``;
    ``refinement`` has the pose graph's per-loop facts, ``poses_stitched`` (the refined chunks
    placed by the pose graph), ``poses_stitched_prior`` (the baseline: the chunks' priors placed by
    their own overlaps), ``image_loops`` (:func:`~cm3d.long_video.close_loops`' facts) and ``frames``).
    """
    from cm3d import pipeline

    chunks = check_chunks(chunks)
    ranges, overlaps, ts = chunk_layout(chunks, overlap)
    H, W = chunks[0].image_size
    cfg = pipeline_config or memory_config_for_chunks(H, W, [c.num_frames for c in chunks])
    t0 = time.perf_counter()
    if results is None:
        bank, results = pipeline.run(list(chunks), cfg, bank, progress=progress, observe=observe)
    t_pipe = time.perf_counter() - t0
    # the chunks as the pipeline refined them: their poses are what is stitched (the priors only for
    # the baseline, placed by their own overlaps)
    refined = [c.replace(cam_to_world=np.asarray(r.poses, np.float64)) for c, r in zip(chunks, results)]
    _, Gp, _ = align_boundaries(chunks, ranges, overlaps, config)
    prior_seq, _ = merge_chunks(chunks, ranges, overlaps, ts, Gp, "cm3d-memory")
    A, G0, bounds = align_boundaries(refined, ranges, overlaps, config)
    loops = [loop_to_prior_frames(lc, refined, results, config) for lc in recall_loops(results)]
    G, facts = sim3_pose_graph(G0, A, loops, graph)
    seq, frame_chunk = merge_chunks(refined, ranges, overlaps, ts, G, "cm3d-memory")
    chained, _ = merge_chunks(refined, ranges, overlaps, ts, G0, "cm3d-memory")
    stitched, frame_facts, kept, loop_facts = seq.cam_to_world, {"kept": False}, False, {"kept": False}
    if refine:
        static = np.ones(seq.depth.shape, bool)
        for k, ((a, b), r) in enumerate(zip(ranges, results)):
            mine = np.flatnonzero(frame_chunk[a:b] == k)
            static[a + mine] = ~np.asarray(r.masks, bool)[mine]
        placed = [place_poses(G[k], c.cam_to_world) for k, c in enumerate(refined)]
        poses, loop_facts = close_loops(seq, motion_noise(placed, ranges), static, loop_config)
        seq = seq.replace(cam_to_world=poses)
        poses, frame_facts = refine_frames(seq, static, frame_config, centre_noise(bounds),
                                           rotation_noise(refined, overlaps, G))
        kept = frame_facts["kept"] or loop_facts["kept"]
        seq = seq.replace(cam_to_world=poses)
    facts = {**facts, "chained_transforms": G0, "pipeline_s": t_pipe, "windows": sum(len(r.windows) for r in results),
             "recalls": sum(int(w.accepted) for r in results for w in r.windows), "poses_stitched": stitched,
             "poses_stitched_prior": prior_seq.cam_to_world,
             "image_loops": loop_facts, "frames": frame_facts}
    return StitchResult(sequence=seq, poses_aligned=chained.cam_to_world, poses_refined=seq.cam_to_world,
                        chunk_transforms=G, ranges=ranges, frame_chunk=frame_chunk, boundaries=bounds,
                        refined=kept, refinement=facts, method="cm3d-memory",
                        loops=tuple(loops), bank=bank, results=tuple(results))


def memory_sequence_result(res: StitchResult, chunks):
    """A :class:`cm3d.pipeline.SequenceResult` of the whole video from :func:`stitch_with_memory`, for
    the output writers: refined trajectory, pose-graph priors, per-frame masks and window records."""
    from cm3d import pipeline

    if res.method != "cm3d-memory":
        raise StitchError(f"res: expected a stitch_with_memory result, got method {res.method!r}")
    prior = res.refinement.get("poses_stitched_prior", res.poses_aligned)
    masks = np.zeros(res.sequence.depth.shape, bool)
    windows = []
    for k, ((a, b), r) in enumerate(zip(res.ranges, res.results)):
        mine = np.flatnonzero(res.frame_chunk[a:b] == k)
        masks[a + mine] = r.masks[mine]
        for w in r.windows:
            windows.append(dataclasses.replace(w, chunk=k, frames=(w.frames[0] + a, w.frames[1] + a)))
    return pipeline.SequenceResult(poses=np.asarray(res.sequence.cam_to_world), prior=np.asarray(prior),
                                   masks=masks, windows=windows, sequence=res.sequence)
