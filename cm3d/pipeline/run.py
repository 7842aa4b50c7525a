"""The host side around the compiled scan: one :class:`WindowRecord` per window and a
:class:`SequenceResult` per sequence (:func:`collect`), and the one-call API :func:`run` with its
checks: inputs with nothing to refine are not run (:func:`cm3d.data.quality.assess_input`), sensor
holes are filled for the front end, and a refinement is kept only when the images do not agree
with it worse than with the prior (:func:`cm3d.pipeline.photometric.check_refinement`; refused, the
prior poses are the result and the windows' maps are still stored). A degenerate input stores
nothing in the bank (:class:`RunReport`)."""

from __future__ import annotations

import dataclasses
import functools
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from cm3d import memory
from cm3d.data import quality
from cm3d.pipeline.config import PipelineConfig
from cm3d.pipeline.global_graph import global_refine
from cm3d.pipeline.photometric import PhotometricCheck, check_refinement
from cm3d import programs
from cm3d.pipeline.prepare import Inputs, piece_spec, prepare_chunks
from cm3d.pipeline.state import empty_bank_host, fresh_state
from cm3d.pipeline.step import StepOutputs, run_frames


@dataclasses.dataclass(frozen=True, eq=False)
class WindowRecord:
    """One window's facts on the host (``recall.json`` lists them): frames (first, last); the recall's
    candidates (ids >= 0) and evidence; the verification (accepted, recalled_map, ICP facts,
    ``transform`` (4, 4) window -> map); ``placement`` (4, 4): the Sim(3) the memory priors and the
    merge used; the map written; the gate, graph counts and the memory's χ² test; chunk: the chunk of
    a long video (None for one sequence)."""

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
    lm_cost: float = float("nan")
    chunk: int | None = None
    acceptance: float = float("nan")  # the acceptance model's score (accept >= 0)
    pose_inliers: int = 0  # the chance test: keypoint inliers of the final pose ...
    chance_inliers: float = 0.0  # ... expected by chance (shuffled matches) ...
    log_nfa: float = 0.0  # ... log10 false alarms (accept < MemoryConfig.max_log_nfa)
    placement_error: float = float("inf")  # how precisely those inliers fix the pose (memory.placement_error)
    decision: str = ""  # which test accepted / rejected the verified candidate, and by how much
    photo_free: float = float("nan")  # grey error (levels) of the window's static pixels: memory-free poses ...
    photo_memory: float = float("nan")  # ... and the memory solution's (used only when lower by more than the tie)
    photo_p: float = float("nan")  # ... and when better on more frame pairs than chance (sign test p < SIGN_ALPHA)

    @classmethod
    def from_result(cls, w, memory_on: bool) -> "WindowRecord":
        """The record of one window's :class:`cm3d.pipeline.step.WindowResult` (numpy, one window)."""
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
            lm_iterations=int(w.iterations), lm_cost=float(w.cost), acceptance=float(r.acceptance),
            pose_inliers=int(r.pose_inliers), chance_inliers=float(r.chance_inliers), log_nfa=float(r.log_nfa),
            placement_error=float(r.placement_error), decision=memory_decision(r, memory_on),
            photo_free=float(w.photo_free), photo_memory=float(w.photo_memory), photo_p=float(w.photo_p))

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


def memory_decision(r, memory_on: bool) -> str:
    """Which acceptance test of a window's verified candidate accepted or rejected it, and by how much:
    the chance test (log10 NFA against MemoryConfig.accept_log_nfa) and the acceptance model (score against 0)."""
    cand = [int(c) for c in np.asarray(r.candidates) if c >= 0]
    if not memory_on:
        return "memory off"
    if not cand:
        return "no candidate"
    nfa, score = float(r.log_nfa), float(r.acceptance)
    tests = []
    if np.isfinite(score):
        tests.append(f"model {'pass' if score >= 0 else 'FAIL'}: score {score:+.2f} (accept >= 0)")
    alone = bool(r.accepted) and np.isfinite(score) and score < 0
    tests.append(f"chance test{' PASS alone' if alone else ''}: {int(r.pose_inliers)} keypoint inliers vs "
                 f"{float(r.chance_inliers):.2f} by chance, log10 NFA {nfa:+.1f}, placement error "
                 f"{float(r.placement_error):.3f} rad (accepts alone below MemoryConfig.accept_log_nfa with a "
                 f"placement error at most alone_max_placement_error, gates below max_log_nfa)")
    if not bool(r.accepted) and not (np.isfinite(score) and score < 0):
        tests.append(f"another check FAIL (chance test, overlap, scale or transform): overlap {float(r.fitness):.2f} "
                     f"(MemoryConfig.min_overlap), scale {float(r.scale):.3f}")
    return ("accepted" if bool(r.accepted) else "rejected") + " (" + "; ".join(tests) + ")"


def recalled_earlier_map(windows) -> bool:
    """Whether a window accepted a map that an earlier sequence stored (not one this sequence created)."""
    created = {w.map_id for w in windows if w.created_map}
    return any(w.accepted and w.recalled_map >= 0 and w.recalled_map not in created for w in windows)


@dataclasses.dataclass(frozen=True)
class RunReport:
    """What :func:`run` decided for one sequence: the input's facts (``quality``), the photometric
    check (None when the back end did not run), whether the refined poses were kept, whether the
    bank holds what this sequence changed (``stored``) and the warnings a user should read."""

    quality: quality.InputQuality | None
    photometric: PhotometricCheck | None
    refinement_kept: bool
    stored: bool
    warnings: tuple = ()

    def to_json(self) -> dict:
        return {"refinement_kept": self.refinement_kept, "stored_in_memory": self.stored,
                "warnings": list(self.warnings),
                "input": None if self.quality is None else self.quality.to_json(),
                "photometric_check": None if self.photometric is None else self.photometric.to_json()}


@dataclasses.dataclass
class SequenceResult:
    """One sequence's results (numpy, input resolution): poses (S, 4, 4) refined cam_to_world, prior
    (S, 4, 4), masks (S, H, W) dynamic, windows (one :class:`WindowRecord` each), the input sequence,
    and :func:`run`'s :class:`RunReport` (None from :func:`collect` alone)."""

    poses: np.ndarray
    prior: np.ndarray
    masks: np.ndarray
    windows: list
    sequence: Any
    report: RunReport | None = None
    chained: np.ndarray | None = None
    global_graph: dict | None = None


def upsample_masks(masks, stride: int, shape) -> np.ndarray:
    """Masks (S, h, w) at the back end's 1 / ``stride`` resolution -> (S, H, W) bool at the input's
    ``shape``: each pixel repeated ``stride`` times along both axes, cropped."""
    H, W = shape
    m = np.asarray(masks, bool)
    return np.repeat(np.repeat(m, stride, axis=1), stride, axis=2)[:, :H, :W]


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
    masks = upsample_masks(out.mask[:S], cfg.stride, (H, W))
    return SequenceResult(poses=poses, prior=np.asarray(sequence.cam_to_world, np.float64), masks=masks,
                          windows=windows, sequence=sequence)


class MaskStream:
    """The cue's masks of one sequence refined and tracked (:func:`cm3d.refine.refine_sequence`, bitwise:
    the same :class:`cm3d.refine.MaskTracker` steps over the same frames, flows t -> t+1 and masks,
    OpenCV's generator seeded alike) at the back end's resolution, a piece at a time in a worker thread
    while the device runs the next piece and the host prepares the one after (GrabCut is single-threaded
    host work). ``add(first, piece, mask)`` queues a piece's real frames (host :class:`Inputs`, its device
    masks); ``result()`` waits for the worker and returns the masks upsampled to the input's (S, H, W)
    like :func:`collect`'s."""

    def __init__(self, sequence, cfg: PipelineConfig):
        from cm3d import refine

        self.S, self.H, self.W = sequence.depth.shape
        self.cfg = cfg
        self.tracker = refine.MaskTracker(rng_seed=0)  # refine_sequence's default
        self.parts, self.flow_in = [], None
        self.pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="cm3d-masks")
        self.jobs = []

    def add(self, first: int, piece: Inputs, mask) -> None:
        self.jobs.append(self.pool.submit(self._piece, first, piece, mask))

    def _piece(self, first: int, piece: Inputs, mask) -> None:
        n = max(0, min(piece.num_frames, self.S - first))
        m = np.asarray(mask, bool)[:n]  # waits for the device
        for i in range(n):
            t = first + i
            flow = np.asarray(piece.flow[i])
            out = flow if t < self.S - 1 else np.zeros_like(flow)  # refine_sequence's: the last frame's are zeros
            r, _ = self.tracker.step(t, np.asarray(piece.frame.image[i]), m[i], lambda _, i=i: m[i], self.flow_in, out)
            self.parts.append(r)
            self.flow_in = out

    def result(self) -> np.ndarray:
        try:
            for job in self.jobs:
                job.result()
        finally:
            self.pool.shutdown(wait=True)
        m = np.stack(self.parts)
        return upsample_masks(m, self.cfg.stride, (self.H, self.W))

    def cancel(self) -> None:
        for job in self.jobs:
            job.cancel()
        self.pool.shutdown(wait=True)


def prior_result(seq, q: quality.InputQuality) -> SequenceResult:
    """The result of a sequence the back end did not run (degenerate input): the prior poses, no
    dynamic pixel, no window; its report carries the reasons."""
    prior = np.asarray(seq.cam_to_world, np.float64)
    warnings = tuple(f"kept the prior, stored nothing: {p}" for p in q.problems)
    return SequenceResult(poses=prior.copy(), prior=prior, masks=np.zeros(np.asarray(seq.depth).shape, bool),
                          windows=[], sequence=seq, report=RunReport(q, None, False, False, warnings))


def _without_hole_features(inputs: Inputs) -> Inputs:
    """Keypoint features on pixels with confidence 0 (sensor holes, filled) are not lifted to 3D."""
    f = inputs.features
    h, w = inputs.frame.depth_conf.shape[1:]
    r = np.clip(np.round(np.asarray(f.uv)[..., 1]).astype(np.int64), 0, h - 1)
    c = np.clip(np.round(np.asarray(f.uv)[..., 0]).astype(np.int64), 0, w - 1)
    conf = np.asarray(inputs.frame.depth_conf)
    on_depth = np.take_along_axis(conf.reshape(len(conf), -1), r * w + c, axis=1) > 0
    return inputs.replace(features=f.replace(valid=np.asarray(f.valid) & on_depth))


def initial_state(inputs: Inputs, cfg: PipelineConfig, bank: memory.MemoryBank | None = None):
    """:func:`cm3d.pipeline.init_state` for pieces shaped like ``inputs``, as one stored program
    (:mod:`cm3d.programs`) around ``bank`` (None: a new empty bank of ``cfg.memory``)."""
    bank = empty_bank_host(cfg.memory) if bank is None else bank
    return programs.call("fresh_state", fresh_state, _state_static(inputs, cfg), bank)


def _state_static(inputs, cfg: PipelineConfig) -> dict:
    """The static arguments of :func:`fresh_state` for pieces shaped like ``inputs`` (arrays or a
    :func:`piece_spec`): the config and (h, w, features per frame, descriptor length)."""
    h, w = inputs.frame.depth.shape[-2:]
    n, dk = inputs.features.desc.shape[-2:]
    return {"cfg": cfg, "shape": (int(h), int(w), int(n), int(dk))}


def _prefetch(seq, cfg: PipelineConfig, state, bank):
    """Load (or compile) the pieces' programs in a thread while the host prepares the first piece
    (only with a program folder: in memory, the first call compiles them as before)."""
    if programs.cache_dir() is None:
        return None
    spec = piece_spec(seq, cfg)

    def load():
        try:
            _load_programs()
        except Exception as err:  # noqa: BLE001  the pieces compile their programs themselves then
            import warnings

            warnings.warn(f"program prefetch failed ({type(err).__name__}: {err})", stacklevel=2)

    def _load_programs():
        st = state
        if st is None or st.window.depth.shape[1:] != spec.frame.depth.shape[1:]:
            b = (empty_bank_host(cfg.memory) if bank is None else bank) if st is None else st.bank
            static = _state_static(spec, cfg)
            programs.compiled("fresh_state", fresh_state, static, b)
            st = jax.eval_shape(functools.partial(fresh_state, **static), b)
        st = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type), st)
        programs.compiled("run_frames", run_frames, {"cfg": cfg}, st, spec, jax.ShapeDtypeStruct((), bool))

    t = threading.Thread(target=load, daemon=True, name="cm3d-prefetch")
    t.start()
    return t


def _run_pieces(seq, cfg: PipelineConfig, state, bank, progress, masks: MaskStream | None = None, loader=None):
    """The back end over one sequence, a piece of ``keyframe_interval`` frames at a time: while the
    device runs piece k (asynchronous dispatch), the host prepares piece k+1 (and ``masks``, when
    given, refines piece k-1's masks in its thread); while the pieces' program is still loading
    (``loader``, the :func:`_prefetch` thread, started here when None), the host prepares the next
    pieces instead of waiting for it (the load runs on one core). ``state``: the previous sequence's
    (None: a fresh one around ``bank``). Returns (state, NumPy StepOutputs and Inputs of the padded
    sequence, the stream of refined masks: ``masks``, or its replacement when the pieces had to run again)."""
    outs, hosts, firsts, start = [], [], [], None
    loader = _prefetch(seq, cfg, state, bank) if loader is None else loader

    def dispatch(pending):
        nonlocal state, start
        for first, piece in pending:
            if state is None:
                state = initial_state(piece, cfg, bank)
            elif state.window.depth.shape[1:] != piece.frame.depth.shape[1:]:
                state = initial_state(piece, cfg, state.bank)  # another image size: new buffers, same bank
            start = state if start is None else start
            x = jax.tree.map(jnp.asarray, piece)
            state, out = programs.call("run_frames", run_frames, {"cfg": cfg}, state, x, np.bool_(first == 0))
            outs.append(out)
            hosts.append(piece)
            firsts.append(first)
            if masks is not None:
                masks.add(first, piece, out.mask)

    pending = []
    for first, piece in prepare_chunks(seq, cfg, progress=progress):
        pending.append((first, _without_hole_features(piece)))
        if loader is None or not loader.is_alive():
            dispatch(pending)
            pending = []
    dispatch(pending)
    try:
        jax.block_until_ready((state, outs))
    except jax.errors.JaxRuntimeError as err:
        # a stored program that this runtime loaded but cannot run (XLA:CPU has lost a kernel of a
        # branch the first runs never took): forget it and run the sequence again, traced afresh
        import warnings

        warnings.warn(f"program cache: the stored sequence program failed ({str(err)[:200]}); "
                      "compiling it afresh", stacklevel=2)
        state, outs = start, []
        if masks is not None:  # its pieces' masks came from the failed program: a new stream
            masks.cancel()
            masks = MaskStream(seq, cfg)
        for k, (first, piece) in enumerate(zip(firsts, hosts)):
            x = jax.tree.map(jnp.asarray, piece)
            if k == 0:
                programs.discard("run_frames", {"cfg": cfg}, state, x, np.bool_(True))
            state, out = programs.call("run_frames", run_frames, {"cfg": cfg}, state, x, np.bool_(k == 0))
            outs.append(out)
            if masks is not None:
                masks.add(first, piece, out.mask)
    stack = lambda parts: jax.tree.map(lambda *a: np.concatenate([np.asarray(p) for p in a]), *parts)  # noqa: E731
    return state, stack(outs), stack(hosts), masks


def run(sequences, cfg: PipelineConfig = PipelineConfig(), bank: memory.MemoryBank | None = None,
        progress=None, checks: bool = True, observe=None) -> tuple[memory.MemoryBank, list[SequenceResult]]:
    """The pipeline on one or several visits (sequences or paths any loader reads) threading one
    memory bank (``bank``: one to start from); ``progress``: optional ``(stage, done, total)``;
    ``checks``: skip degenerate inputs (prior kept, bank untouched) and refuse refinements the
    images disagree with (prior kept; see the module docstring); ``observe``: optional
    ``(index, inputs, outputs, result, bank)`` called on the host after each sequence with its
    NumPy :class:`Inputs` and :class:`StepOutputs` (both None when the back end did not run) and the
    bank after it (what ``--rerun`` records).
    Returns (the updated bank, one :class:`SequenceResult` per visit)."""
    from cm3d.data.loaders import load_input

    if not isinstance(sequences, (list, tuple)):
        sequences = [sequences]
    state = None
    results = []
    for i, seq in enumerate(sequences):
        source = f"sequence {i}"
        if not hasattr(seq, "depth"):
            source = str(seq)
            seq = load_input(seq)
        quality.check_runnable(seq, source)
        # the front end's hole filling in a thread while the input is assessed (both host work that
        # releases the GIL; a degenerate input's filled copy is dropped); the programs start loading once
        # the input is known to need them, while the holes are filled and the pieces prepared
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="cm3d-holes") as pool:
            filled = pool.submit(quality.fill_depth_holes, seq)
            q = quality.assess_input(seq) if checks else None
            loader = None if q is not None and q.degenerate else _prefetch(seq, cfg, state, bank)
        if q is not None and q.degenerate:
            results.append(prior_result(seq, q))
            if observe is not None:
                observe(i, None, None, results[-1], state.bank if state is not None else bank)
            continue
        cb = None if progress is None else (lambda d, n, i=i: progress(f"visit {i}: flow", d, n))
        stream = MaskStream(seq, cfg) if cfg.refine_masks else None
        state, out, host_inputs, stream = _run_pieces(filled.result(), cfg, state, bank, cb, stream, loader)
        if progress is not None:
            progress(f"visit {i}: back end", 1, 1)
        res = collect(out, seq, cfg)
        # one pose graph over every frame: the windows' refined motions and the priors (issue 26), while
        # the mask stream finishes its last pieces
        res.chained = res.poses.copy()
        res.poses, res.global_graph = global_refine(res.prior, res.chained, [w.frames for w in res.windows],
                                                    cfg.global_graph)
        if cfg.refine_masks:
            res.masks = stream.result()
        res.report = RunReport(q, None, True, True)
        if checks:
            ph = check_refinement(seq, res.prior, res.poses, res.masks)
            warnings = ()
            if not ph.kept and res.global_graph.get("ran"):  # the images refuse the global graph: the chain?
                chain = check_refinement(seq, res.prior, res.chained, res.masks)
                warnings = (f"kept the windows' chained poses, not the global graph's: {ph.reason}",)
                res.global_graph["kept"] = False
                res.poses, ph = res.chained.copy(), chain
            elif res.global_graph.get("ran"):
                res.global_graph["kept"] = True
            warnings += () if ph.kept else (f"kept the prior poses: {ph.reason}",)
            if not ph.kept:
                res.poses = res.prior.copy()
            res.report = RunReport(q, ph, ph.kept, True, warnings)
        results.append(res)
        if observe is not None:
            observe(i, host_inputs, out, res, state.bank)
    return (state.bank if state is not None else bank), results
