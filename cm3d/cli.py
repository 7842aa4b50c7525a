"""The ``cm3d`` command: parse arguments, call the library, print. No logic lives here."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path


def _generate(args) -> int:
    from cm3d.data import io, synthetic

    cfg = synthetic.WorldConfig(height=args.height, width=args.width)
    out = Path(args.out)
    for v in range(args.visits):
        seq = synthetic.generate(args.scene, v, args.frames, args.level, cfg)
        stem = out / f"scene{args.scene:03d}_visit{v:02d}"
        if args.format == "npz":
            path = stem.with_suffix(".npz")
            io.save_sequence(path, seq)
        elif args.format == "tum":
            from cm3d.data.tum_rgbd import write_tum_rgbd

            path = stem
            write_tum_rgbd(path, seq)
        else:
            from cm3d.data.loaders import write_image_folder

            path = stem
            write_image_folder(path, seq)
        io.write_tum(Path(f"{stem}.gt.txt"), seq.timestamps, seq.gt.cam_to_world)
        io.write_tum(Path(f"{stem}.prior.txt"), seq.timestamps, seq.cam_to_world)
        print(f"wrote {path} ({args.format}: {seq.num_frames} frames, {seq.image_size[0]}x{seq.image_size[1]}, "
              f"level {args.level}) and its .gt.txt / .prior.txt trajectories")
    return 0


def _eval(args) -> int:
    from cm3d.eval.metrics import evaluate_trajectory_files

    m = evaluate_trajectory_files(args.gt, args.est, max_diff=args.max_diff)
    if args.json:
        print(json.dumps(m))
    else:
        print(f"pairs      {m['pairs']}")
        print(f"extent     {m['extent']:.6f}")
        if m["ate_defined"]:
            print(f"ATE (Sim3) {m['ate']:.6f}")
        else:
            print(f"ATE (Sim3) undefined: {m['ate']:.6f}, but the ground truth's extent is below the estimate's noise "
                  "(a Sim(3) fit shrinks any estimate towards its centroid); read ATE (SE3) and the rotation error")
        print(f"ATE (SE3)  {m['ate_se3']:.6f}")
        print(f"RPE trans  {m['rpe_trans']:.6f}")
        print(f"RPE rot    {m['rpe_rot']:.6f} deg")
        print(f"rotation   {m['rot_rmse']:.6f} deg (RMSE after the best global rotation, whatever the positions)")
    return 0


class _Progress:
    """``progress(stage, done, total)`` callback drawing one tqdm bar per stage on stderr."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.bars = {}

    def __call__(self, stage: str, done: int, total: int) -> None:
        if not self.enabled:
            return
        from tqdm import tqdm

        bar = self.bars.get(stage)
        if bar is None:
            bar = self.bars[stage] = tqdm(total=total, desc=stage, unit="frame" if total > 1 else "step",
                                          file=sys.stderr, leave=True, dynamic_ncols=True)
        bar.update(done - bar.n)
        if done >= total:
            bar.close()


def _compile_cache() -> None:
    """Keep compiled programs between runs: XLA's cache (``$CM3D_JAX_CACHE``, default
    ~/.cache/cm3d/jax) and the pipeline's serialised executables (``$CM3D_PROGRAM_CACHE``, default
    ~/.cache/cm3d/programs: a second ``cm3d run`` of the same configuration and image size loads
    them instead of tracing); ``off`` disables either."""
    import os

    from cm3d import programs

    programs.set_cache_dir(programs.dir_from_env(Path.home() / ".cache" / "cm3d" / "programs"))
    path = os.environ.get("CM3D_JAX_CACHE", str(Path.home() / ".cache" / "cm3d" / "jax"))
    if path.lower() in ("", "0", "off", "none"):
        return
    import jax

    try:
        jax.config.update("jax_compilation_cache_dir", path)
        # every program, not only those over JAX's default 1 s of compile time: the host-side helpers
        # (the global pose graph's eager SE(3) logs, the metrics) compile ~90 small programs per run,
        # 3.2 s of a warm 120-frame run, 0.3 s to read back (stop 44). JAX's own variable wins.
        if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
            jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    except Exception:  # noqa: BLE001  an older jax without the option: just compile
        pass


def _holds_chunks(path) -> bool:
    """A ``.npz`` with a ``chunk`` key: several chunks of one long video in one file."""
    import zipfile

    path = Path(path)
    if not (path.is_file() and path.suffix == ".npz" and zipfile.is_zipfile(path)):
        return False
    with zipfile.ZipFile(path) as z:
        return "chunk.npy" in z.namelist()


def _load_inputs(paths, frames=None, prior_noise=None, seed=0, camera="folder"):
    """(one sequence, None), or (None, chunks) for several paths or one file with a ``chunk`` key:
    the overlapping chunks of one long video (a file holding a single chunk is one sequence).
    ``frames``: 7-Scenes frame selection; ``prior_noise``: VGGT-like priors from the ground truth;
    ``camera``: 7-Scenes folders, "folder" (the folder's K for both images) or "kinect" (the Kinect
    colour camera, :data:`cm3d.data.sevenscenes.KINECT_COLOUR`)."""
    from cm3d.data.loaders import load_input
    from cm3d.data.quality import check_runnable

    if len(paths) == 1 and not _holds_chunks(paths[0]):
        from cm3d.data.sevenscenes import is_sevenscenes_folder

        kwargs = {}
        if is_sevenscenes_folder(paths[0]):
            from cm3d.data.sevenscenes import KINECT_COLOUR

            kwargs = {"frames": frames, "require_poses": prior_noise is not None,
                      "colour": KINECT_COLOUR if camera == "kinect" else None}
        elif frames is not None or camera != "folder":
            raise ValueError("--frames / --colour-camera: only for 7-Scenes folders")
        seq = load_input(paths[0], **kwargs)
        check_runnable(seq, str(paths[0]))
        if prior_noise is not None:
            from cm3d.data.priors import priors_for

            seq = priors_for(seq, prior_noise, seed)
        return seq, None
    if frames is not None or prior_noise is not None or camera != "folder":
        raise ValueError("--frames / --prior-noise / --colour-camera: for a single input")
    from cm3d import long_video as stitch

    chunks = stitch.load_chunks(paths)
    if len(chunks) == 1:
        return chunks[0], None
    stitch.chunk_layout(chunks)  # layout errors before any work
    return None, chunks


def _run_chunks(chunks, cfg, bank, args, recorder=None):
    """The chunks of one long video: the pipeline over every chunk threading one memory bank, Sim(3)
    overlap alignment, loop closures from recalls across chunks, the Sim(3) pose graph, then loop closures
    measured in the images and the whole-trajectory refinement (:func:`cm3d.long_video.stitch_with_memory`).
    Returns (bank, whole-video result: refined trajectory, the stitched priors as its prior; facts)."""
    from cm3d import long_video as stitch

    bars = _Progress(not args.quiet)
    chunk_facts = []
    st = stitch.stitch_with_memory(chunks, pipeline_config=cfg, bank=bank,
                                   progress=lambda stage, done, n: bars(stage.replace("visit", "chunk"), done, n),
                                   observe=None if recorder is None else recorder.chunk_observer(cfg, chunk_facts))
    res = stitch.memory_sequence_result(st, chunks)
    if recorder is not None:
        recorder.long_video(st, res, chunk_facts, cfg)
    f = st.refinement
    facts = {"ranges": st.ranges, "chunk_transforms": st.chunk_transforms, "refined": st.refined,
             "boundaries": [dataclasses.asdict(b) for b in st.boundaries],
             "pose_graph": {k: v for k, v in f.items()
                            if k not in ("loop_discrepancy", "loop_kept", "chained_transforms", "poses_stitched",
                                         "poses_stitched_prior", "frames", "image_loops")},
             "image_loops": f["image_loops"], "frame_refinement": f["frames"],
             "loops": [{"chunk": lc.chunk, "other": lc.other, "frames": list(lc.frames),
                        "other_frames": list(lc.other_frames or ()), "transform": lc.transform,
                        "inliers": lc.inliers, "rmse": lc.rmse, "discrepancy": f["loop_discrepancy"][i],
                        "kept": bool(f["loop_kept"][i])} for i, lc in enumerate(st.loops)]}
    return st.bank, res, facts


def _run(args) -> int:
    from cm3d import memory, outputs, pipeline

    out = outputs.check_output_folder(args.out)  # fail before any work
    if args.rerun:
        from cm3d import viz

        viz.check_recording_path(args.rerun)
    bank_path = Path(args.memory) if args.memory else None
    if bank_path is not None and not args.no_memory:
        memory.check_bank_path(bank_path)
    snap = memory.snapshot(bank_path) if bank_path is not None else memory.Snapshot("")
    bank, mem_cfg = snap.bank, snap.cfg
    if snap.note:
        print(f"note: {snap.note}")
    seq, chunks = _load_inputs(args.inputs, args.frames, args.prior_noise, args.seed, args.colour_camera)
    H, W = (seq if seq is not None else chunks[0]).image_size
    changes = {"use_memory": not args.no_memory, "refine_masks": not args.cue_masks}
    if args.keyframe_interval is not None:
        changes["keyframe_interval"] = args.keyframe_interval
    if args.stride is not None:
        changes["stride"] = args.stride
    if chunks is None:
        cfg = pipeline.config_for(H, W, **changes)
    else:
        from cm3d import long_video as stitch

        cfg = stitch.memory_config_for_chunks(H, W, [c.num_frames for c in chunks], **changes)
    if bank is not None:
        cfg = dataclasses.replace(cfg, memory=mem_cfg)
    _compile_cache()
    what = (f"{args.inputs[0]}: {seq.num_frames} frames" if chunks is None else
            f"{len(chunks)} chunks ({', '.join(str(c.num_frames) for c in chunks)} frames)")
    print(f"{what} at {H}x{W}; windows of {cfg.keyframe_interval} frames; memory "
          f"{'off' if args.no_memory else (str(bank_path) if bank_path else 'in-process only')}")
    recorder = None
    if args.rerun:
        from cm3d.viz.record import Recorder

        recorder = Recorder(args.rerun, bank)
    try:
        if chunks is None:
            bank, (res,) = pipeline.run([seq], cfg, bank, progress=_Progress(not args.quiet),
                                        observe=None if recorder is None else recorder.observe(cfg))
        else:
            bank, res, facts = _run_chunks(chunks, cfg, bank, args, recorder)
    except BaseException:
        if recorder is not None:
            recorder.abort()
        raise
    if recorder is not None:
        rrd = recorder.close()
        print(f"recording {rrd} ({rrd.stat().st_size / 1e6:.1f} MB; cm3d view {rrd})")
    commit = None
    if bank_path is not None and cfg.use_memory:  # stored before the outputs: a failed write loses no map
        _, commit = memory.commit(bank_path, snap, bank, cfg.memory)
    m = outputs.write_results(out, res, bank if cfg.use_memory else None, pictures=not args.no_pictures,
                              commit=commit)
    if chunks is not None:
        outputs.write_json(out / "stitch.json", facts)
        fr = facts["frame_refinement"]
        print(f"stitched {res.sequence.num_frames} frames: {len(facts['loops'])} loop closures recalled across "
              f"chunks, {sum(lc['kept'] for lc in facts['loops'])} kept by the pose graph's consistency check; "
              f"whole-trajectory refinement {'kept' if fr['kept'] else 'refused: ' + fr.get('reason', 'self-check')}"
              + (f" ({fr['pairs_used']} of {fr['pairs']} frame pairs)" if "pairs" in fr else ""))
    for w in res.windows:
        print("  " + outputs.window_line(w))
    for w in (res.report.warnings if res.report is not None else ()):
        print(f"warning: {w}")
    if m:
        print(outputs.headline(m))
    saved = f"; {outputs.commit_line(commit)}" if commit is not None else ""
    print(f"wrote {out}/ (trajectory.txt, trajectory_prior.txt, masks/, static_map.ply, recall.json"
          f"{', metrics.json' if m else ''}{', stitch.json' if chunks is not None else ''}"
          f"{'' if args.no_pictures else ', pictures'}){saved}")
    return 0


def _demo(args) -> int:
    from cm3d.demo import run_demo

    if args.rerun:
        from cm3d import viz

        viz.check_recording_path(args.rerun)
    _compile_cache()
    run_demo(scene=args.scene, visits=args.visits, frames=args.frames, quick=args.quick,
             json_path=args.json, out=args.out, height=args.height, width=args.width,
             progress=_Progress(not args.quiet), rerun=args.rerun)
    return 0


def _view(args) -> int:
    from cm3d import viz

    print(viz.view(args.recording))
    return 0


def _memory(args) -> int:
    import numpy as np

    from cm3d import memory

    stored = memory.read(args.bank)
    bank, cfg = stored.bank, stored.cfg
    if stored.note:
        print(f"note: {stored.note}", file=sys.stderr)
    valid = np.asarray(bank.map_valid)
    if args.action == "ls":
        print(f"{args.bank}: {int(valid.sum())} of {cfg.max_maps} maps "
              f"(capacity {cfg.max_points} points, {cfg.max_keyframes} keyframes each)")
        for m in np.flatnonzero(valid):
            c = memory.map_counts(bank, m)
            print(f"  map {m:3d}: {c['points']:6d} points, {c['keyframes']:3d} keyframes, {c['visits']} visits")
        return 0
    if args.map_id is None or not (0 <= args.map_id < cfg.max_maps) or not valid[args.map_id]:
        raise ValueError(f"map id: {args.map_id} is not a stored map (valid: {np.flatnonzero(valid).tolist()})")
    m = args.map_id
    if args.action == "show":
        cloud = memory.map_cloud(bank, m)
        pts = np.asarray(cloud.points)[np.asarray(cloud.valid)]
        lo, hi = (pts.min(0), pts.max(0)) if len(pts) else (np.zeros(3), np.zeros(3))
        print(json.dumps({"map_id": int(m), **memory.map_counts(bank, m), "bounds_min": lo.round(4).tolist(),
                          "bounds_max": hi.round(4).tolist()}, indent=1))
        return 0
    memory.modify(args.bank, lambda b, c: memory.remove_map(b, m))
    print(f"removed map {m} from {args.bank}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="cm3d", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    g = sub.add_parser("generate", help="write synthetic multi-visit sequences (.npz + TUM trajectories)")
    g.add_argument("--out", default="out/synthetic", help="output folder")
    g.add_argument("--scene", type=int, default=0, help="scene seed")
    g.add_argument("--visits", type=int, default=2)
    g.add_argument("--frames", type=int, default=30)
    g.add_argument("--level", default="moderate", help="prior noise: none, slight, moderate, severe")
    g.add_argument("--height", type=int, default=384)
    g.add_argument("--width", type=int, default=512)
    g.add_argument("--format", choices=("npz", "tum", "images"), default="npz",
                   help="npz: sequence file (VGGT keys); tum: TUM RGB-D folder (depth PNGs, pose prior from "
                        "RGB-D odometry when loaded); images: images/ + priors.npz")
    g.set_defaults(func=_generate)

    e = sub.add_parser("eval", help="ATE/RPE of an estimated TUM trajectory against ground truth")
    e.add_argument("--gt", required=True, help="reference trajectory, TUM format")
    e.add_argument("--est", required=True, help="estimated trajectory, TUM format")
    e.add_argument("--max-diff", type=float, default=0.01, help="timestamp association tolerance (s)")
    e.add_argument("--json", action="store_true", help="print one JSON object")
    e.set_defaults(func=_eval)

    r = sub.add_parser("run", help="run the pipeline on a sequence and write its outputs",
                       description="Motion masks, refined trajectory, static map and memory recall of one "
                       "sequence. Writes trajectory.txt (TUM, refined), trajectory_prior.txt, masks/, "
                       "static_map.ply, recall.json, metrics.json (with ground truth) and PNG pictures.")
    r.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="a .npz sequence, an image folder (images/ + priors.npz) or a TUM RGB-D folder; "
                   "several .npz files (or one holding a 'chunk' key): overlapping chunks of one long video: "
                   "the pipeline runs on every chunk threading the memory (recall across chunks), the chunks "
                   "are aligned by Sim(3) on their shared frames, a Sim(3) pose graph closes loops "
                   "recalled from memory, and one pose graph over every frame "
                   "refines the whole trajectory (trajectory.txt; trajectory_prior.txt: the stitched priors); "
                   "stitch.json holds the chunk transforms, loop closures and the refinement's facts")
    r.add_argument("--out", required=True, metavar="DIR", help="output folder")
    r.add_argument("--memory", metavar="BANK", help="memory bank file: loaded if present, updated, saved atomically")
    r.add_argument("--no-memory", action="store_true", help="no recall / verify / update")
    r.add_argument("--keyframe-interval", type=int, default=None, metavar="N",
                   help="frames per memory / factor-graph window (default 20; 4 for small images)")
    r.add_argument("--stride", type=int, default=None,
                   help="back end at 1/stride resolution (default 2; 1 for small images)")
    r.add_argument("--frames", default=None, metavar="A:B:STRIDE",
                   help="7-Scenes folders: the frames numbered A <= n < B, every STRIDE-th")
    r.add_argument("--prior-noise", default=None, metavar="LEVEL", choices=("none", "slight", "moderate", "severe"),
                   help="VGGT-like priors made from the input's ground truth (poses, depth) at this level")
    r.add_argument("--seed", type=int, default=0, help="seed of --prior-noise")
    r.add_argument("--colour-camera", choices=("folder", "kinect"), default="folder",
                   help="7-Scenes folders: the folder's K for both images (default), or the Kinect colour camera "
                        "(published K, 2.5 cm baseline; the depth registered into it; docs/real_data.md)")
    r.add_argument("--no-pictures", action="store_true", help="skip the PNG pictures")
    r.add_argument("--cue-masks", action="store_true",
                   help="write the motion cue's masks as they are (default: refined and tracked by GrabCut)")
    r.add_argument("--quiet", action="store_true", help="no progress bars")
    r.add_argument("--rerun", default=None, metavar="RRD", help="also write a Rerun recording of every stage "
                   "(needs the viz extra: pip install -e '.[viz]'); open it with cm3d view RRD")
    r.set_defaults(func=_run)

    d = sub.add_parser("demo", help="the full pipeline on a multi-visit synthetic world, with one memory",
                       description="Render several visits of one synthetic scene (moderate prior noise), run the "
                       "pipeline over them threading one memory bank, print prior vs refined metrics and the "
                       "recall decisions, and write every output per visit.")
    d.add_argument("--scene", type=int, default=0)
    d.add_argument("--visits", type=int, default=3)
    d.add_argument("--frames", type=int, default=None, help="frames per visit (default 40; 8 with --quick)")
    d.add_argument("--height", type=int, default=None, help="image height (default 384; 48 with --quick)")
    d.add_argument("--width", type=int, default=None, help="image width (default 512; 64 with --quick)")
    d.add_argument("--out", default="out/demo", metavar="DIR", help="output folder (one subfolder per visit)")
    d.add_argument("--quick", action="store_true", help="tiny images, for smoke tests")
    d.add_argument("--json", default=None, metavar="PATH", help="also write the table as JSON")
    d.add_argument("--quiet", action="store_true", help="no progress bars")
    d.add_argument("--rerun", default=None, metavar="RRD", help="also write a Rerun recording of every visit")
    d.set_defaults(func=_demo)

    v = sub.add_parser("view", help="open a Rerun recording (--rerun) in the viewer, or say how to open it")
    v.add_argument("recording", metavar="RRD", help="a .rrd file written by cm3d run/demo --rerun")
    v.set_defaults(func=_view)

    m = sub.add_parser("memory", help="list, show or remove maps of a memory bank file")
    m.add_argument("action", choices=["ls", "show", "rm"])
    m.add_argument("bank", help="memory bank file (.cm3d)")
    m.add_argument("map_id", nargs="?", type=int, help="map id, for show and rm")
    m.set_defaults(func=_memory)
    return p


#: XLA:CPU splits a program's code in parts compiled in parallel; a program stored split and loaded
#: by another process lost kernels of branches its first runs had not taken ("Function ... not
#: found": a 120-frame run after a 30-frame one). One part each: no lost kernel, same compile time.
XLA_CPU_FLAGS = "--xla_cpu_parallel_codegen_split_count=1"


def _xla_flags() -> None:
    """Add :data:`XLA_CPU_FLAGS` to ``$XLA_FLAGS`` before jax starts its backend (unless set there)."""
    import os

    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_parallel_codegen_split_count" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {XLA_CPU_FLAGS}".strip()


def main(argv: list[str] | None = None) -> int:
    _xla_flags()
    args = build_parser().parse_args(argv)
    t0 = time.perf_counter()
    try:
        rc = args.func(args)
    except (ValueError, FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError,
            TimeoutError) as err:  # TimeoutError: another process holds the memory bank's lock
        print(f"cm3d {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"cm3d {args.command}: interrupted", file=sys.stderr)
        return 130
    if args.command not in ("eval", "memory", "view"):
        print(f"done in {time.perf_counter() - t0:.1f} s")
    return rc


def finish(rc: int):
    """Leave the process with ``rc`` once every output is written (``main`` joins its writer threads and
    closes its files): flush the standard streams and exit without tearing the interpreter down, which
    spends ~0.6 s freeing the compiled programs and the XLA client after a ``cm3d run`` (measured on the
    kitchen's 30 frames: 0.75-1.5 s from the last output to the process's end, 0.2 s with this)."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(rc)


def entry() -> None:
    """The ``cm3d`` console script: :func:`main`, then :func:`finish`."""
    finish(main())


if __name__ == "__main__":
    entry()
