"""What a user waits for: ``cm3d run`` end to end, as a separate process, cold and warm (issue 23).

    .venv/bin/python experiments/bench_e2e.py [--frames 30 120] [--quick] [--json PATH] [--keep DIR]

Inputs (written once as ``.npz`` sequences, the VGGT-like format ``cm3d run`` reads): the real
kitchen (7-Scenes redkitchen, ``$CM3D_SHARED_DATA/sevenscenes_redkitchen``, frames from 100, moderate
priors from :func:`cm3d.data.priors.priors_for`) at 480x640 for each ``--frames``, and one synthetic
sequence (:func:`cm3d.data.synthetic.generate`, scene 0, moderate) of the first length.
Per input, ``cm3d run INPUT --out DIR --quiet`` runs as a child process twice on fresh, empty cache
folders (``$CM3D_JAX_CACHE``, ``$CM3D_PROGRAM_CACHE``): the first is *cold* (traces and compiles,
stores the programs), the second *warm* (loads them). Inputs of one configuration and image size
share one program (pieces of ``keyframe_interval`` frames), so the 120-frame warm run uses the
30-frame run's folders. The child is ``cm3d.cli.main`` with timers around the stages (nothing else
changed): ``import`` (jax and the modules ``cm3d run`` imports), ``load`` (reading the input),
``prepare`` (host flow, keypoints, features: time spent producing pieces), ``compile`` (the main
thread waiting for stored programs to load, or to be traced and compiled, where the loader thread
started before the first piece did not hide it), ``device`` (the rest of the back end: dispatch and
waiting for the device, what host preparation did not hide), ``outputs`` (files and pictures),
``other`` (the checks, the wall clock not in a stage); ``prefetch``: seconds the loader thread ran
beside them (not part of the total's split). The warm run's outputs must equal the cold run's byte
for byte (a loaded program computes what a traced one does).

In this process: ``steady_fps_e2e``, frames per second of :func:`cm3d.pipeline.run` (host preparation
included, outputs not) on a second kitchen sequence after a first one (programs in memory);
``fps_backend``: frames per second of the compiled pieces alone on prepared inputs.
``--quick`` (smoke test): one synthetic 8-frame 48x64 sequence, no memory, no pictures.

JSON keys: warm_process_s_30, warm_process_s_120, cold_process_s_30 (the first --frames value
stands for 30, the second for 120), warm/cold per input and stage (``<input>_<cold|warm>_<stage>_s``),
steady_fps_e2e, fps_backend, outputs_equal, quick.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # OpenBLAS threads spin on shared cores
if "xla_cpu_parallel_codegen_split_count" not in os.environ.get("XLA_FLAGS", ""):  # as cm3d.cli (its key)
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_parallel_codegen_split_count=1").strip()

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("CM3D_SHARED_DATA", ROOT.parent / "shared" / "data"))
KITCHEN = SHARED / "sevenscenes_redkitchen"
STAGES = ("import", "load", "prepare", "compile", "device", "outputs", "other")
# prefetch: seconds the program loader thread ran beside the stages (not part of the total's split)

# The child: cm3d.cli.main with timers around its stages; writes {stage: seconds} to argv[1].
CHILD = r"""
import sys, time, json, importlib, threading
t0 = time.perf_counter()
import jax
from cm3d import cli, long_video, memory, outputs, pipeline, programs
t_import = time.perf_counter() - t0
T = dict(load=0.0, prepare=0.0, compile=0.0, pieces=0.0, outputs=0.0, compile_pieces=0.0, compile_outputs=0.0,
         prefetch=0.0)
prun = importlib.import_module("cm3d.pipeline.run")
where = []

def timed(mod, name, key):
    f = getattr(mod, name)
    def g(*a, **k):
        if threading.current_thread() is not threading.main_thread():  # the prefetch, beside the stages
            t = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                T["prefetch"] += time.perf_counter() - t
        t = time.perf_counter()
        where.append(key)
        try:
            return f(*a, **k)
        finally:
            where.pop()
            dt = time.perf_counter() - t
            T[key] += dt
            for w in where:  # a program loaded or compiled inside a stage is not that stage's time
                if key == "compile" and f"compile_{w}" in T:
                    T[f"compile_{w}"] += dt
    setattr(mod, name, g)

def timed_gen(mod, name, key):
    f = getattr(mod, name)
    def g(*a, **k):
        it = f(*a, **k)
        while True:
            t = time.perf_counter()
            try:
                x = next(it)
            except StopIteration:
                T[key] += time.perf_counter() - t
                return
            T[key] += time.perf_counter() - t
            yield x
    setattr(mod, name, g)

timed(cli, "_load_inputs", "load")
timed_gen(prun, "prepare_chunks", "prepare")
timed(programs, "compiled", "compile")
timed(prun, "_run_pieces", "pieces")
timed(outputs, "write_results", "outputs")
t1 = time.perf_counter()
rc = cli.main(sys.argv[2:])
wall = time.perf_counter() - t1
res = {"import": t_import, "load": T["load"], "prepare": T["prepare"], "compile": T["compile"],
       "device": T["pieces"] - T["prepare"] - T["compile_pieces"], "outputs": T["outputs"] - T["compile_outputs"]}
res["other"] = wall - sum(v for k, v in res.items() if k != "import")
res["prefetch"] = T["prefetch"]
with open(sys.argv[1], "w") as f:
    json.dump(res, f)
cli.finish(rc)  # as the console script ends
"""


def kitchen(frames: int, start: int = 100):
    """``frames`` consecutive kitchen frames from ``start`` with moderate VGGT-like priors."""
    import numpy as np

    from cm3d.data import priors, sevenscenes

    nums = sevenscenes.frame_numbers(KITCHEN)
    i = nums.index(start)
    seq = sevenscenes.load_sevenscenes(KITCHEN, f"{start}:{nums[i + frames - 1] + 1}")
    if seq.num_frames != frames:
        raise ValueError(f"--frames: the kitchen has {seq.num_frames} consecutive frames from {start}, not {frames}")
    seq = priors.priors_for(seq, "moderate", seed=start)
    # the prior's rotations orthonormalised (SVD) so that the .npz's extrinsic and cam_to_world agree
    # to the loader's 1e-6 (priors_for's drifted rotations are orthonormal to ~1e-6 only)
    T = np.array(seq.cam_to_world, np.float64)
    U, _, Vt = np.linalg.svd(T[:, :3, :3])
    T[:, :3, :3] = U @ Vt
    return dataclasses.replace(seq, cam_to_world=T)


def make_inputs(folder: Path, lengths, quick: bool) -> dict:
    """name -> .npz path of every input."""
    from cm3d.data import io, synthetic

    out = {}
    if quick:
        seq = synthetic.generate(0, 0, 8, "moderate", synthetic.WorldConfig(height=48, width=64))
        io.save_sequence(folder / "synthetic_8.npz", seq)
        return {"synthetic_8": folder / "synthetic_8.npz"}
    for n in lengths:
        io.save_sequence(folder / f"kitchen_{n}.npz", kitchen(n))
        out[f"kitchen_{n}"] = folder / f"kitchen_{n}.npz"
    seq = synthetic.generate(0, 0, lengths[0], "moderate", synthetic.WorldConfig(height=480, width=640))
    io.save_sequence(folder / f"synthetic_{lengths[0]}.npz", seq)
    out[f"synthetic_{lengths[0]}"] = folder / f"synthetic_{lengths[0]}.npz"
    return out


def run_process(inp: Path, out: Path, cache: Path, extra=()) -> dict:
    """One ``cm3d run`` child on the cache folders under ``cache``: stage seconds and ``total``."""
    env = dict(os.environ, CM3D_JAX_CACHE=str(cache / "jax"), CM3D_PROGRAM_CACHE=str(cache / "programs"),
               OPENBLAS_NUM_THREADS="1")
    stages = out.parent / f"{out.name}.stages.json"
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", CHILD, str(stages), "run", str(inp), "--out", str(out), "--quiet",
                           *extra], cwd=ROOT, env=env, capture_output=True, text=True)
    total = time.perf_counter() - t
    if proc.returncode != 0:
        raise RuntimeError(f"cm3d run {inp} failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}")
    res = json.loads(stages.read_text())
    res["total"] = total
    return res


def same_outputs(a: Path, b: Path) -> bool:
    """The two runs wrote the same trajectories, masks, map and metrics (byte for byte)."""
    files = ["trajectory.txt", "static_map.ply", "recall.json"] + [p.name for p in a.glob("metrics.json")]
    masks = sorted(p.relative_to(a) for p in (a / "masks").glob("*.png"))
    return all((a / f).read_bytes() == (b / f).read_bytes() for f in files + masks)


def steady_state(lengths, quick: bool, cache: Path) -> tuple[float, float]:
    """(fps of pipeline.run on a second sequence, fps of the compiled pieces alone) in this process."""
    import importlib

    import jax
    import jax.numpy as jnp
    import numpy as np

    from cm3d import pipeline, programs
    from cm3d.data import quality, synthetic

    prun = importlib.import_module("cm3d.pipeline.run")
    programs.set_cache_dir(cache / "programs")
    if quick:
        seqs = [synthetic.generate(0, v, 8, "moderate", synthetic.WorldConfig(height=48, width=64)) for v in (0, 1)]
        cfg = pipeline.config_for(48, 64, use_memory=False)
    else:
        seqs = [kitchen(lengths[0], 100), kitchen(lengths[0], 460)]
        cfg = pipeline.config_for(480, 640)
    bank, _ = pipeline.run([seqs[0]], cfg)  # programs loaded (or compiled) once
    t = time.perf_counter()
    pipeline.run([seqs[1]], cfg, bank)
    fps = seqs[1].num_frames / (time.perf_counter() - t)
    pieces = [prun._without_hole_features(p) for _, p in pipeline.prepare_chunks(quality.fill_depth_holes(seqs[1]), cfg)]
    xs = [jax.tree.map(jnp.asarray, p) for p in pieces]
    state = prun.initial_state(pieces[0], cfg, bank)
    best = float("inf")
    for _ in range(2):
        st = state
        t = time.perf_counter()
        for k, x in enumerate(xs):
            st, out = programs.call("run_frames", pipeline.run_frames, {"cfg": cfg}, st, x, np.bool_(k == 0))
        jax.block_until_ready(out)
        best = min(best, time.perf_counter() - t)
    return fps, seqs[1].num_frames / best


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, nargs=2, default=(30, 120), metavar=("N30", "N120"))
    ap.add_argument("--quick", action="store_true", help="one synthetic 8-frame 48x64 sequence (smoke test)")
    ap.add_argument("--json", default=None, metavar="PATH", help="also write the headline figures as flat JSON")
    ap.add_argument("--keep", default=None, metavar="DIR", help="work in DIR (kept) instead of a temporary folder")
    args = ap.parse_args(argv)
    lengths = list(args.frames)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.keep or tmp)
        work.mkdir(parents=True, exist_ok=True)
        inputs = make_inputs(work, lengths, args.quick)
        extra = ("--no-memory", "--no-pictures") if args.quick else ()
        rows, equal = {}, True
        for name, path in inputs.items():
            n = int(name.rsplit("_", 1)[1])
            if n == lengths[0] or args.quick:  # cold: fresh, empty cache folders (a kept DIR's are emptied)
                cache = work / f"cache_{name}"
                shutil.rmtree(cache, ignore_errors=True)
                rows[(name, "cold")] = run_process(path, work / f"out_{name}_cold", cache, extra)
            else:  # one configuration and image size: the first kitchen run's programs
                cache = work / f"cache_kitchen_{lengths[0]}"
            rows[(name, "warm")] = run_process(path, work / f"out_{name}_warm", cache, extra)
            if (name, "cold") in rows:
                equal &= same_outputs(work / f"out_{name}_cold", work / f"out_{name}_warm")
        steady, backend = steady_state(lengths, args.quick, work / f"cache_{next(iter(inputs))}")
    print(f"cm3d run as a separate process ({os.cpu_count()} cores; load average "
          f"{os.getloadavg()[0]:.1f} at the end), seconds:")
    print(f"{'input':16s} {'cache':5s} " + " ".join(f"{s:>8s}" for s in STAGES) + f" {'total':>8s} {'prefetch':>8s}")
    fig = {}
    for (name, kind), r in rows.items():
        print(f"{name:16s} {kind:5s} " + " ".join(f"{r[s]:8.2f}" for s in STAGES) + f" {r['total']:8.2f}"
              f" {r['prefetch']:8.2f}")
        for s in (*STAGES, "total", "prefetch"):
            fig[f"{name}_{kind}_{s}_s"] = round(r[s], 3)
    first = next(iter(inputs))
    big = f"kitchen_{lengths[1]}"
    fig["warm_process_s_30"] = round(rows[(first, "warm")]["total"], 3)
    fig["cold_process_s_30"] = round(rows[(first, "cold")]["total"], 3)
    fig["warm_process_s_120"] = round(rows[(big, "warm")]["total"], 3) if (big, "warm") in rows else None
    fig.update(steady_fps_e2e=round(steady, 2), fps_backend=round(backend, 2), outputs_equal=bool(equal),
               quick=bool(args.quick))
    print(f"warm outputs equal the cold run's: {equal}")
    print(f"in-process steady state: {steady:.2f} fps end to end (pipeline.run, host preparation included), "
          f"{backend:.2f} fps back end alone")
    if args.json:
        from cm3d.outputs import write_json

        write_json(args.json, fig)
    return fig


if __name__ == "__main__":
    main()
