"""Frames per second of cm3d's back end (everything after the priors and the flow) at 384x512.

    .venv/bin/python experiments/bench_backend.py [--frames 40] [--repeats 2] [--quick] [--json PATH]

The back end is :func:`cm3d.pipeline.run_sequence`: per frame the motion cues, the static landmarks
and their tracking, and every 20 frames the memory recall / verification / update and the windowed
factor graph, all in one compiled ``lax.scan``; it is timed on a synthetic visit (scene 0, visit 1,
moderate prior noise) after compiling on the same shapes, best of ``--repeats`` runs from a fresh
state with an empty memory bank, plus one run on a second visit of the same shapes (memory
holding the first: the recall path verifies). The host front end is timed separately: OpenCV DIS
flow (``fps_flow``) and SIFT matches + features (``fps_keypoints``).

``--quick`` (smoke test, 96x128, 8 frames): times only the per-frame stages (motion cues, landmark
tracking, seeding) compiled on their own, so that it finishes in seconds; its numbers are not the
back end's and are flagged ``"quick": true`` in the JSON.

JSON keys: fps_backend, compile_s, fps_flow, fps_keypoints, frames, height, width, ms_per_frame,
fps_backend_revisit, quick.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # OpenBLAS threads spin on shared cores

import argparse  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from cm3d import pipeline  # noqa: E402
from cm3d.data import synthetic  # noqa: E402
from cm3d.outputs import write_json  # noqa: E402


def time_front_end(seq, cfg: pipeline.PipelineConfig):
    """Seconds per frame of DIS flow and of SIFT matching + feature detection (host)."""
    from cm3d.ops import flow as oflow
    from cm3d.ops import keypoints as okp
    from cm3d.pipeline.prepare import match_config

    imgs = seq.images
    t0 = time.perf_counter()
    for t in range(len(imgs) - 1):
        oflow.compute_flow(imgs[t], imgs[t + 1], cfg.flow)
    t_flow = (time.perf_counter() - t0) / (len(imgs) - 1)
    t0 = time.perf_counter()
    mk = match_config(cfg)
    for t in range(len(imgs) - 1):  # as pipeline.prepare (with match_reduced: at 1 / stride)
        if cfg.match_reduced:
            okp.match_detections(*[okp.detect_reduced(img, mk, cfg.stride) for img in imgs[t:t + 2]], mk)
        else:
            okp.match_keypoints(imgs[t], imgs[t + 1], cfg.keypoints)
    okp.detect_sequence(imgs[::cfg.feature_every], None, cfg.feature_capacity, cfg.keypoints)
    t_kp = (time.perf_counter() - t0) / (len(imgs) - 1)
    return t_flow, t_kp


def bench_full(args):
    wcfg = synthetic.WorldConfig()
    cfg = pipeline.PipelineConfig()
    seqs = [synthetic.generate(0, v, args.frames, "moderate", wcfg) for v in (1, 2)]
    t_flow, t_kp = time_front_end(seqs[0], cfg)
    inputs = [jax.tree.map(jnp.asarray, pipeline.prepare(s, cfg)) for s in seqs]
    state0 = pipeline.init_state(inputs[0], cfg)
    t0 = time.perf_counter()
    st, out = pipeline.run_sequence(state0, inputs[0], cfg)
    jax.block_until_ready(out)
    first = time.perf_counter() - t0
    runs = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        st, out = pipeline.run_sequence(state0, inputs[0], cfg)
        jax.block_until_ready(out)
        runs.append(time.perf_counter() - t0)
    run = min(runs)
    t0 = time.perf_counter()
    st2, out2 = pipeline.run_sequence(st, inputs[1], cfg)
    jax.block_until_ready(out2)
    revisit = time.perf_counter() - t0
    n = seqs[0].num_frames
    return {"fps_backend": n / run, "compile_s": max(first - run, 0.0), "fps_flow": 1.0 / t_flow,
            "fps_keypoints": 1.0 / t_kp, "frames": n, "height": wcfg.height, "width": wcfg.width,
            "ms_per_frame": 1e3 * run / n, "fps_backend_revisit": n / revisit,
            "recompiled": pipeline.run_sequence._cache_size() > 1, "quick": False}


def bench_quick(args):
    wcfg = synthetic.WorldConfig(height=96, width=128, supersample=1)
    cfg = pipeline.small_config()
    seq = synthetic.generate(0, 1, 8, "moderate", wcfg)
    t_flow, t_kp = time_front_end(seq, cfg)
    inputs = jax.tree.map(jnp.asarray, pipeline.prepare(seq, cfg))
    state = pipeline.init_state(inputs, cfg)

    @jax.jit
    def per_frame(lms, x, prev_flow):
        dyn, static = pipeline.static_mask(x, cfg)
        lms = pipeline.advance_landmarks(lms, prev_flow, static, jnp.int32(1), cfg, image=x.frame.image)
        lms = pipeline.seed_landmarks(lms, jnp.int32(0), x.frame.image, x.frame.depth, x.frame.depth_conf, static,
                                      x.frame.intrinsic, x.frame.cam_to_world, cfg)
        return lms, dyn

    frames = [jax.tree.map(lambda a, t=t: a[t], inputs) for t in range(seq.num_frames)]
    t0 = time.perf_counter()
    jax.block_until_ready(per_frame(state.landmarks, frames[0], frames[0].flow))
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    lms = state.landmarks
    for t in range(1, len(frames)):
        lms, dyn = per_frame(lms, frames[t], frames[t - 1].flow)
    jax.block_until_ready(dyn)
    run = (time.perf_counter() - t0) / (len(frames) - 1)
    return {"fps_backend": 1.0 / run, "compile_s": max(first - run, 0.0), "fps_flow": 1.0 / t_flow,
            "fps_keypoints": 1.0 / t_kp, "frames": seq.num_frames, "height": wcfg.height, "width": wcfg.width,
            "ms_per_frame": 1e3 * run, "fps_backend_revisit": float("nan"), "recompiled": False, "quick": True}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40, help="frames per visit (2 windows of 20 by default)")
    ap.add_argument("--repeats", type=int, default=2, help="timed runs (best is reported)")
    ap.add_argument("--quick", action="store_true", help="smoke test: per-frame stages at 96x128 only")
    ap.add_argument("--json", default=None, metavar="PATH")
    args = ap.parse_args()
    r = bench_quick(args) if args.quick else bench_full(args)
    what = "per-frame stages only (--quick)" if r["quick"] else "whole back end (run_sequence)"
    print(f"{r['frames']} frames at {r['height']}x{r['width']} on {jax.devices()[0].platform} "
          f"({os.cpu_count()} CPUs visible): {what}")
    print(f"{'stage':<34} {'fps':>8} {'ms/frame':>9}")
    print("-" * 53)
    print(f"{'front end: DIS flow (host)':<34} {r['fps_flow']:>8.1f} {1e3 / r['fps_flow']:>9.1f}")
    print(f"{'front end: SIFT matches+features':<34} {r['fps_keypoints']:>8.1f} {1e3 / r['fps_keypoints']:>9.1f}")
    print(f"{'back end':<34} {r['fps_backend']:>8.1f} {r['ms_per_frame']:>9.1f}")
    if not r["quick"]:
        print(f"{'back end, revisit (memory holds 1)':<34} {r['fps_backend_revisit']:>8.1f} "
              f"{1e3 / r['fps_backend_revisit']:>9.1f}")
    print(f"compile: {r['compile_s']:.1f} s (once per image size and padded length)"
          + ("" if r["quick"] else f"; second visit recompiled: {r['recompiled']}"))
    if args.json:
        write_json(args.json, r)


if __name__ == "__main__":
    main()
