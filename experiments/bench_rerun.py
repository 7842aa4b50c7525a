"""What ``--rerun`` costs: the pipeline over the demo's visits with and without a Rerun recording.

    .venv/bin/python experiments/bench_rerun.py [--visits 3 --frames 40] [--repeats 2] [--quick] [--json PATH]

The demo's world (scene 0, moderate prior noise, 384x512) is rendered once; then, in this one
process, :func:`cm3d.pipeline.run` threads one bank over the visits: a warm-up run with a recording
(compiles the pipeline and the host cue function, :func:`cm3d.motion.motion_cues_jit`; its compile
is timed on its own as ``cue_compile_s``), then ``--repeats`` alternating pairs of a plain run and a
recorded run (``cm3d.viz.record.Recorder``: cues recomputed per frame, everything logged, the file
closed). ``overhead_pct`` compares the best recorded run with the best plain one (target: <= 10 %).
``rrd_mb``: the recording's size. ``--quick`` (smoke test): 48x64, 2 visits of 8 frames.

JSON keys: overhead_pct, plain_s, recorded_s, record_s, cue_compile_s, rrd_mb, frames, visits, height,
width, quick.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # OpenBLAS threads spin on shared cores

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from cm3d import pipeline  # noqa: E402
from cm3d.data import synthetic  # noqa: E402
from cm3d.outputs import write_json  # noqa: E402


def plain_run(seqs, cfg) -> float:
    t0 = time.perf_counter()
    pipeline.run(seqs, cfg)
    return time.perf_counter() - t0


def recorded_run(seqs, cfg, path: Path) -> tuple[float, float]:
    """(seconds of the whole run with its recording, seconds inside the recorder's callback)."""
    from cm3d.viz.record import Recorder

    t0 = time.perf_counter()
    rec = Recorder(path)
    inner = rec.observe(cfg)
    spent = [0.0]

    def observe(*a):
        t = time.perf_counter()
        inner(*a)
        spent[0] += time.perf_counter() - t

    pipeline.run(seqs, cfg, observe=observe)
    t = time.perf_counter()
    rec.close()
    spent[0] += time.perf_counter() - t
    return time.perf_counter() - t0, spent[0]


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--visits", type=int, default=None, help="visits (default 3; 2 with --quick)")
    p.add_argument("--frames", type=int, default=None, help="frames per visit (default 40; 8 with --quick)")
    p.add_argument("--repeats", type=int, default=None, help="plain/recorded pairs (default 2; 1 with --quick)")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    q = args.quick
    H, W = (48, 64) if q else (384, 512)
    V, S = args.visits or (2 if q else 3), args.frames or (8 if q else 40)
    repeats = args.repeats or (1 if q else 2)
    wcfg = synthetic.WorldConfig(height=H, width=W)
    cfg = pipeline.config_for(H, W)
    seqs = [synthetic.generate(0, v, S, "moderate", wcfg) for v in range(V)]

    from cm3d.motion import motion_cues_jit

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.rrd"
        recorded_run(seqs[:1], cfg, path)  # warm-up: compiles the pipeline and the cue function
        n0 = motion_cues_jit._cache_size()
        motion_cues_jit.clear_cache()
        x = pipeline.prepare(seqs[0], cfg)
        t0 = time.perf_counter()
        import jax

        x0 = jax.tree.map(lambda a: a[0], x)
        jax.block_until_ready(motion_cues_jit(x0.frame, x0.partner, x0.flow, x0.matches, cfg.motion,
                                              flow_rev=x0.flow_rev, second=x0.second))
        cue_compile = time.perf_counter() - t0  # a persistent-cache hit after the warm-up when the cache is on
        assert n0 >= 1
        plain, recorded, inside = [], [], []
        for _ in range(repeats):
            plain.append(plain_run(seqs, cfg))
            r, s = recorded_run(seqs, cfg, path)
            recorded.append(r)
            inside.append(s)
        mb = path.stat().st_size / 1e6
    best_p, best_r = min(plain), min(recorded)
    out = {"overhead_pct": 100.0 * (best_r - best_p) / best_p, "plain_s": best_p, "recorded_s": best_r,
           "record_s": min(inside), "cue_compile_s": cue_compile, "rrd_mb": mb, "frames": V * S, "visits": V,
           "height": H, "width": W, "quick": q}
    print(f"{V} visits x {S} frames at {H}x{W}, best of {repeats} (same process, pipeline compiled)\n")
    print(f"{'run':<22}{'seconds':>9}")
    print(f"{'plain':<22}{best_p:>9.2f}")
    print(f"{'with --rerun':<22}{best_r:>9.2f}   (recorder itself {min(inside):.2f} s)")
    print(f"\noverhead {out['overhead_pct']:+.1f} % (target <= 10 %); recording {mb:.2f} MB; "
          f"host cue function compile {cue_compile:.1f} s once (persistent cache after)")
    if args.json:
        write_json(args.json, out)
    return out


if __name__ == "__main__":
    main()
