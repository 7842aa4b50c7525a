"""Recorders: what one sequence's run holds (:func:`sequence_facts`, host-side, after the run), logged
on the ``frame`` / ``visit`` timelines by :class:`Recorder` for a visit, a multi-visit demo or a
stitched long video (chunks on one timeline, boundaries and loop closures drawn).

The intermediate motion cues are not outputs of the compiled scan: they are recomputed per frame
after the run with the same function the step traces (:func:`cm3d.motion.motion_cues_jit`) on the
run's own inputs, and checked against the pipeline's mask (``agreement``)."""

from __future__ import annotations

import dataclasses
import types

import numpy as np

from cm3d.viz import log

PRIOR, REFINED, TRUTH = (230, 120, 40), (40, 200, 90), (90, 140, 255)
KEPT, REJECTED, LOOP = (60, 230, 60), (255, 50, 50), (255, 0, 255)
#: cues recomputed on every 8th frame: every frame costs ~60 ms at 192x256 on 2 cores (a quarter of
#: the run's time per frame); every 4th measured +9.0 % on a quiet machine (recorder 2.47 s of a 20.8 s
#: run), too close to the 10 % budget (experiments/bench_rerun.py)
CUE_EVERY = 8
#: the static map drawn from every 8th pixel (static_map.ply keeps every 4th)
MAP_STRIDE = 8


@dataclasses.dataclass(frozen=True)
class FrameLayers:
    """Per frame, at the back end's resolution (h, w): the input image (S, h, w, 3) uint8, prior
    depth and confidence (S, h, w), the pipeline's dynamic mask, the cues (flow GMM, geometry,
    residual px with its Otsu threshold (S,)) and the keypoint matches uv (S, n, 2) kept (static) or
    rejected (on a moving object); ``cued`` (S,): the frames whose cues were recomputed."""

    image: np.ndarray
    depth: np.ndarray
    conf: np.ndarray
    dynamic: np.ndarray
    cued: np.ndarray
    flow_mask: np.ndarray
    geo_mask: np.ndarray
    residual: np.ndarray
    threshold: np.ndarray
    kp_uv: np.ndarray
    kp_kept: np.ndarray
    kp_rejected: np.ndarray


@dataclasses.dataclass(frozen=True)
class SequenceFacts:
    """What a recording needs beyond the :class:`cm3d.pipeline.SequenceResult`: the frame layers
    (None when the back end did not run), per window the factor graph's landmarks (n, 3) and the
    recalled memory map in the sequence's frame ((points, colours) or None), and the share of pixels
    where the recomputed robust cue equals the pipeline's mask (1.0 when it reproduces it)."""

    layers: FrameLayers | None
    landmarks: list
    memory: list
    agreement: float


def _memory_solution(w) -> str:
    """Whether a window's memory solution was used, or which test refused it."""
    if w.memory_used:
        return "used"
    if w.memory_stat > w.memory_threshold:
        return f"refused by its chi2 test ({w.memory_stat:.1f} > {w.memory_threshold:.1f})"
    from cm3d.pipeline.photometric import memory_wins

    mean_ok, pairs_ok = memory_wins(w.photo_free, w.photo_memory, w.photo_p)
    if np.isfinite(w.photo_memory) and not mean_ok:
        return (f"refused by its photometric test (grey error {w.photo_memory:.4f}, memory-free {w.photo_free:.4f}: "
                "not lower by more than the tie)")
    if np.isfinite(w.photo_p) and not pairs_ok:
        return f"refused by its photometric test (better on too few frame pairs: sign test p = {w.photo_p:.3f})"
    return "not used (too few landmarks on the remembered surface, or non-finite)"


def frame_layers(inputs, outputs, num_frames: int, cfg, every: int = 1) -> tuple[FrameLayers, float]:
    """The cues of every ``every``-th real frame recomputed on the host (one jitted call per frame)
    from the run's NumPy :class:`cm3d.pipeline.Inputs` (the other frames' cue layers stay empty);
    returns (layers, agreement of the recomputed frames with ``outputs.mask``)."""
    import jax

    from cm3d.motion import motion_cues_jit

    keys = ("flow_mask", "geo_mask", "robust_mask", "residual", "geo_threshold", "kp_dynamic", "kp_valid")
    got = {k: [] for k in keys}
    frames = np.arange(0, num_frames, every)
    for t in frames:
        x = jax.tree.map(lambda a, t=t: a[t], inputs)
        c = motion_cues_jit(x.frame, x.partner, x.flow, x.matches, cfg.motion, flow_rev=x.flow_rev, second=x.second)
        for k in keys:
            got[k].append(getattr(c, k))
    S = num_frames

    def full(k, fill):  # every frame's slot, the recomputed frames filled
        v = np.asarray(jax.device_get(got[k]))
        out = np.full((S,) + v.shape[1:], fill, v.dtype)
        out[frames] = v
        return out

    dynamic = np.asarray(outputs.mask[:S], bool)
    m = np.asarray(inputs.matches.valid[:S], bool)
    cued = np.zeros(S, bool)
    cued[frames] = True
    kp_valid, kp_dyn = full("kp_valid", False), full("kp_dynamic", False)
    layers = FrameLayers(image=np.asarray(inputs.frame.image[:S]), depth=np.asarray(inputs.frame.depth[:S]),
                         conf=np.asarray(inputs.frame.depth_conf[:S]), dynamic=dynamic, cued=cued,
                         flow_mask=full("flow_mask", False), geo_mask=full("geo_mask", False),
                         residual=full("residual", 0.0), threshold=full("geo_threshold", 0.0),
                         kp_uv=np.asarray(inputs.matches.uv0[:S]),
                         kp_kept=m & kp_valid & ~kp_dyn, kp_rejected=m & kp_dyn)
    return layers, float(np.mean(full("robust_mask", False)[frames] == dynamic[frames]))


def recalled_cloud(bank, window):
    """The map a window accepted, from the bank as it was before the sequence, moved into the
    sequence's frame (inverse of the window -> map Sim(3)): (points (N, 3), colours (N, 3)) or None."""
    from cm3d import memory
    from cm3d.ops import sim3

    if bank is None or not window.accepted or window.recalled_map < 0:
        return None
    if not bool(np.asarray(bank.map_valid)[window.recalled_map]):
        return None
    cloud = memory.map_cloud(bank, window.recalled_map)
    ok = np.asarray(cloud.valid, bool)
    pts = sim3.apply(sim3.inverse(np.asarray(window.transform, np.float64)), np.asarray(cloud.points, np.float64)[ok])
    return np.asarray(pts, np.float32), np.asarray(cloud.colors)[ok]


def sequence_facts(inputs, outputs, result, bank_before, cfg, cue_every: int = 1) -> SequenceFacts:
    """:class:`SequenceFacts` of one sequence from what :func:`cm3d.pipeline.run` hands its
    ``observe`` callback (``inputs`` / ``outputs`` None: the back end did not run) and the bank the
    sequence started from."""
    S = result.sequence.num_frames
    if inputs is None or outputs is None:
        return SequenceFacts(None, [np.zeros((0, 3), np.float32)] * len(result.windows),
                             [None] * len(result.windows), 1.0)
    layers, agreement = frame_layers(inputs, outputs, S, cfg, cue_every)
    ends = np.flatnonzero(np.asarray(outputs.window_end))
    pts, ok = np.asarray(outputs.window.points), np.asarray(outputs.window.point_valid, bool)
    landmarks = [pts[t][ok[t] & np.all(np.isfinite(pts[t]), -1)] for t in ends]
    return SequenceFacts(layers, landmarks, [recalled_cloud(bank_before, w) for w in result.windows], agreement)


_ATE = []


def _jitted_ate():
    """:func:`cm3d.eval.metrics.ate` jitted once per process (one program per sequence length)."""
    if not _ATE:
        import jax

        from cm3d.eval import metrics

        _ATE.append(jax.jit(metrics.ate, static_argnames="align"))
    return _ATE[0]


def _centres(poses) -> np.ndarray:
    return np.asarray(poses, np.float64)[:, :3, 3]


def _decision(w, mem_cfg) -> tuple[str, str]:
    """The recall decision of a window as (text, level): candidates, votes, inliers, accepted or why not."""
    head = (f"frames {w.frames[0]}-{w.frames[1]}" + (f" (chunk {w.chunk})" if w.chunk is not None else "") + ": ")
    if not w.memory:
        return head + "memory off", "DEBUG"
    cands = (f"candidates {list(w.candidates)}, votes {[round(v, 3) for v in w.votes]}, "
             f"keypoint inliers {list(w.keypoint_inliers)}")
    if w.accepted:
        return (head + f"{cands}; ACCEPTED map {w.recalled_map}: {w.inlier_count} ICP inliers, RMSE {w.rmse:.4f}, "
                f"fitness {w.fitness:.3f}, scale {w.scale:.3f}; {w.memory_landmarks} memory landmarks in the graph, "
                f"memory solution {_memory_solution(w)}"), "INFO"
    if not w.candidates:
        why = "no candidate (the hashed 2D recall found no stored map)"
    elif max(w.keypoint_inliers, default=0) < mem_cfg.min_keypoint_inliers:
        why = (f"keypoint RANSAC: at most {max(w.keypoint_inliers, default=0)} distinct inliers "
               f"(< {mem_cfg.min_keypoint_inliers})")
    else:
        why = (f"the acceptance model rejected it ({w.inlier_count} ICP inliers, RMSE {w.rmse:.4f}, "
               f"fitness {w.fitness:.3f})")
    stored = (f"new map {w.map_id}" if w.created_map else f"merged into map {w.map_id}" if w.map_id >= 0
              else "not stored (bank full)")
    return head + f"{cands}; not accepted: {why}; {stored}", "WARN" if w.candidates else "INFO"


class Recorder:
    """One ``.rrd`` recording of a run: :meth:`sequence` per visit (frames numbered on from the last
    visit's), :meth:`long_video` for stitched chunks, :meth:`close` to finish the file."""

    def __init__(self, path, bank=None, cue_every: int = CUE_EVERY):
        self.rec, self._paths = log.open_recording(path)
        self.cue_every = cue_every
        self.bank = bank  # the bank the next sequence starts from
        self.frames = 0
        self.visits = 0
        self.agreement: list[float] = []

    # -- per sequence ------------------------------------------------------------------------------
    def observe(self, cfg, visit: int | None = None):
        """A callback for :func:`cm3d.pipeline.run`'s ``observe``: records each sequence as a visit."""
        def cb(i, inputs, outputs, result, bank_after):
            self.sequence(result, sequence_facts(inputs, outputs, result, self.bank, cfg, self.cue_every), cfg,
                          self.visits if visit is None else visit)
            self.bank = bank_after
        return cb

    def sequence(self, result, facts: SequenceFacts, cfg, visit: int) -> None:
        """Log one visit: frames ``self.frames ...`` on the frame timeline, ``visit`` on the visit one."""
        rec = self.rec
        log.set_time(rec, self.frames, visit)
        for entity in ("world/map", "world/memory", "world/landmarks", "world/trajectory", "world/loops"):
            log.clear(rec, entity)
        seq = result.sequence
        log.text(rec, "log/run", f"visit {visit}: {seq.num_frames} frames at {seq.image_size[0]}x{seq.image_size[1]}")
        self._frames(result, facts, cfg, visit, self.frames)
        self.agreement.append(facts.agreement)
        log.scalar(rec, "plots/cue_agreement", facts.agreement)
        if facts.agreement < 0.999:
            log.text(rec, "log/run", f"recomputed robust cue agrees with the pipeline's mask on only "
                                     f"{100 * facts.agreement:.2f} % of pixels", "WARN")
        self.frames += seq.num_frames
        self.visits = max(self.visits, visit + 1)

    def _frames(self, result, facts: SequenceFacts, cfg, visit: int, offset: int, world_of_window=None) -> None:
        """Every frame of ``result`` and, at each window's last frame, its map, memory, landmarks,
        decision and LM cost. ``world_of_window``: optional (window index) -> (4, 4) Sim(3) placing
        that window's points in the recording's world (chunks of a long video)."""
        from cm3d import outputs as outs
        from cm3d.eval import metrics
        from cm3d.ops import sim3

        rec, seq, L = self.rec, result.sequence, facts.layers
        S, (H, W) = seq.num_frames, seq.image_size
        images, K = np.asarray(seq.images), np.asarray(seq.intrinsic, np.float64)
        d = np.asarray(seq.depth)
        unit = float(np.median(d[d > 0])) if np.any(d > 0) else 1.0
        prior, refined = np.asarray(result.prior, np.float64), np.asarray(result.poses, np.float64)
        gt = None
        if seq.gt is not None:
            ate = _jitted_ate()
            gt_own = np.asarray(seq.gt.cam_to_world, np.float64)
            gt = np.asarray(metrics.align_trajectory(gt_own, refined), np.float64)
        ends = {w.frames[1]: i for i, w in enumerate(result.windows)}
        for t in range(S):
            log.set_time(rec, offset + t, visit)
            log.camera(rec, "world/camera", refined[t], K[t], W, H)
            log.jpeg(rec, "world/camera/image", images[t])
            log.mask(rec, "world/camera/image/dynamic", result.masks[t])
            if L is not None:
                log.jpeg(rec, "frame/image", L.image[t])
                log.depth(rec, "frame/depth", L.depth[t])
                c = L.conf[t]
                log.heat(rec, "frame/confidence", c, float(np.quantile(c, 0.99)) if c.size else 1.0)
                log.mask(rec, "frame/dynamic", L.dynamic[t])
            if L is not None and L.cued[t]:
                log.mask(rec, "frame/cues/flow_gmm", L.flow_mask[t])
                log.mask(rec, "frame/cues/geometry", L.geo_mask[t])
                log.heat(rec, "frame/cues/residual", L.residual[t], 2.0 * max(float(L.threshold[t]), 1e-3))
                log.points2d(rec, "frame/cues/keypoints/kept", L.kp_uv[t][L.kp_kept[t]], KEPT)
                log.points2d(rec, "frame/cues/keypoints/rejected", L.kp_uv[t][L.kp_rejected[t]], REJECTED)
            log.strip(rec, "world/trajectory/prior", _centres(prior[: t + 1]), PRIOR, 0.004 * unit)
            log.strip(rec, "world/trajectory/refined", _centres(refined[: t + 1]), REFINED, 0.004 * unit)
            if gt is not None:
                log.strip(rec, "world/trajectory/ground_truth", _centres(gt[: t + 1]), TRUTH, 0.004 * unit)
                if t >= 2:  # frames 0..t of full-length arrays: one shape, no compile per frame
                    so_far = np.arange(S) <= t
                    log.scalar(rec, "plots/ate_so_far/prior", float(ate(prior, gt_own, valid=so_far)))
                    log.scalar(rec, "plots/ate_so_far/refined", float(ate(refined, gt_own, valid=so_far)))
            if t in ends:
                i = ends[t]
                w = result.windows[i]
                place = np.eye(4) if world_of_window is None else world_of_window(i)
                sub = types.SimpleNamespace(depth=d[: t + 1], depth_conf=np.asarray(seq.depth_conf)[: t + 1],
                                            intrinsic=K[: t + 1], images=images[: t + 1])
                pts, cols = outs.static_map(sub, refined[: t + 1], result.masks[: t + 1], stride=MAP_STRIDE)
                log.points3d(rec, "world/map/new", pts, cols, 0.006 * unit)
                lms = facts.landmarks[i]
                log.points3d(rec, "world/landmarks", sim3.apply(place, lms) if len(lms) else lms, (255, 220, 0),
                             0.009 * unit)
                mem = facts.memory[i]
                if mem is not None:
                    log.points3d(rec, "world/memory/recalled", sim3.apply(place, mem[0]), log.brighter(mem[1]),
                                 0.012 * unit)
                msg, level = _decision(w, cfg.memory)
                log.text(rec, "log/recall", f"visit {visit}, " + msg, level)
                log.scalar(rec, "plots/lm_cost", w.lm_cost)
                log.scalar(rec, "plots/memory_landmarks", w.memory_landmarks)

    # -- long videos -------------------------------------------------------------------------------
    def chunk_observer(self, cfg, store: list):
        """A callback for :func:`cm3d.long_video.stitch_with_memory`'s ``observe``: keeps each chunk's
        :class:`SequenceFacts` in ``store`` (logged by :meth:`long_video` after stitching)."""
        def cb(i, inputs, outputs, result, bank_after):
            store.append(sequence_facts(inputs, outputs, result, self.bank, cfg, self.cue_every))
            self.bank = bank_after
        return cb

    def long_video(self, st, whole, chunk_facts: list, cfg, visit: int = 0) -> None:
        """A stitched long video on one timeline: ``whole`` (:func:`cm3d.long_video.memory_sequence_result`
        of ``st``), every frame's layers from the chunk whose image it shows, windows' points placed by
        their chunk's Sim(3), chunk boundaries as logs and a ``plots/chunk`` step, each chunk's placed
        prior as its own strip and loop closures as segments between the two windows' cameras."""
        from cm3d.ops import sim3

        rec = self.rec
        G = np.asarray(st.chunk_transforms, np.float64)
        fc = np.asarray(st.frame_chunk)
        layers = None
        if all(f.layers is not None for f in chunk_facts):
            def pick(name):
                parts = [getattr(chunk_facts[k].layers, name)[g - st.ranges[k][0]] for g, k in enumerate(fc)]
                return np.stack(parts)
            layers = FrameLayers(**{f.name: pick(f.name) for f in dataclasses.fields(FrameLayers)})
        window_chunk = [k for k, f in enumerate(chunk_facts) for _ in f.landmarks]
        facts = SequenceFacts(layers, [x for f in chunk_facts for x in f.landmarks],
                              [x for f in chunk_facts for x in f.memory], float(np.mean([f.agreement for f in chunk_facts])))
        log.set_time(rec, self.frames, visit)
        d = np.asarray(whole.sequence.depth)
        unit = float(np.median(d[d > 0])) if np.any(d > 0) else 1.0
        for k, (a, b) in enumerate(st.ranges):
            log.set_time(rec, self.frames + a, visit)
            placed = sim3.apply(G[k], _centres(st.results[k].prior))
            colour = tuple(int(v) for v in (np.array([80, 80, 80]) + 170 * np.eye(3)[k % 3]))
            log.strip(rec, f"world/chunks/{k}", placed, colour, 0.003 * unit)
            bd = next((x for x in st.boundaries if x.chunk == k), None)
            text = f"chunk {k}: frames {a}-{b - 1}"
            if bd is not None:
                text += (f"; boundary with chunk {k - 1} on frames {bd.frames[0]}-{bd.frames[1] - 1}: Sim(3) scale "
                         f"{bd.scale:.3f}, rotation {bd.rotation_deg:.2f} deg, centre RMSE {bd.rmse_centres:.4f}, "
                         f"inliers {100 * bd.inlier_fraction:.0f} %")
            log.text(rec, "log/chunks", text)
        for g in range(whole.sequence.num_frames):
            log.set_time(rec, self.frames + g, visit)
            log.scalar(rec, "plots/chunk", float(fc[g]))
        self._frames(whole, facts, cfg, visit, self.frames, lambda i: G[window_chunk[i]])
        kept = st.refinement.get("loop_kept", [True] * len(st.loops))
        refined = np.asarray(whole.poses, np.float64)
        for i, lc in enumerate(st.loops):
            a = np.arange(lc.frames[0], lc.frames[1] + 1) + st.ranges[lc.chunk][0]
            o = lc.other_frames or lc.frames
            b = np.arange(o[0], o[1] + 1) + st.ranges[lc.other][0]
            log.set_time(rec, self.frames + int(a[-1]), visit)
            log.segments(rec, f"world/loops/{i}", np.stack([_centres(refined[a]).mean(0), _centres(refined[b]).mean(0)])[None],
                         LOOP, 0.006 * unit)
            log.text(rec, "log/chunks", f"loop closure: chunk {lc.chunk} (frames {a[0]}-{a[-1]}) recalled the map of "
                     f"chunk {lc.other} (frames {b[0]}-{b[-1]}): {lc.inliers} inliers, RMSE {lc.rmse:.4f}; "
                     f"{'kept' if bool(kept[i]) else 'left out'} by the pose graph's consistency check",
                     "INFO" if bool(kept[i]) else "WARN")
        self.agreement.append(facts.agreement)
        self.frames += whole.sequence.num_frames
        self.visits = max(self.visits, visit + 1)

    def close(self):
        """Finish the file; returns its path."""
        return log.close_recording(self.rec, self._paths)

    def abort(self) -> None:
        """Stop recording and remove the unfinished file (a failed run leaves no ``.rrd``)."""
        self.rec.disconnect()
        self._paths[0].unlink(missing_ok=True)
