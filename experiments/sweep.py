"""Sharded experiment sweep: seeds x prior-noise levels x config values, one compiled program each.

    .venv/bin/python experiments/sweep.py [--devices 2] [--seeds 0 1 2 3] [--levels slight moderate severe]
        [--huber 1 2 4] [--gmm-k 3] [--batching vmap|map] [--out DIR] [--quick] [--json PATH]

The batch of sequences (every seed x noise level) is stacked on a leading axis; the pipeline's
``run_sequence`` (:mod:`cm3d.pipeline`) is mapped over it (``jax.vmap``, or ``lax.map`` inside
each device's shard with ``--batching map``, cheaper on CPUs where ``vmap`` turns the step's
``lax.cond`` into both branches) and the batch is sharded over every device of a 1-D mesh
(``jax.sharding.Mesh`` + ``NamedSharding``, axis ``"batch"``): the same script uses one CPU,
several emulated CPU devices (``--devices N`` sets ``XLA_FLAGS=--xla_force_host_platform_device_count=N``),
8 GPUs, or several hosts after ``jax.distributed.initialize()`` (see the README).
Configuration values that change shapes or code (GMM K, keyframe interval) are static fields of
:class:`cm3d.pipeline.PipelineConfig`, so each config value is its own compiled program; seeds and
noise levels are data and share it. The batch is padded to a multiple of the device count.

Output: a tidy CSV (one row per sequence and config: ATE / RPE of the prior and of cm3d, mask IoU)
and a plot of ATE vs noise level per config, in ``--out`` (default ``sweep_out/``), plus compile
time and throughput (sequences per second) for the batch sizes of ``--throughput``.

Headline JSON keys: ``ate_prior_<level>``, ``ate_cm3d_<level>`` (mean over seeds, first config),
``compile_s``, ``seq_per_s_<b>`` for each throughput batch size, ``devices``, and with ``--check`` the
batch against each sequence run alone by :func:`cm3d.pipeline.run_sequence` on the default device
(:func:`compare_alone`): ``sharded_equals_single``, ``poses_within_1e-3``, ``window_ends_equal``,
``windows_equal``, ``mask_agreement``.
"""

from __future__ import annotations

import argparse
import os


def _parse():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", type=int, default=None, help="emulate N CPU devices (XLA_FLAGS)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    ap.add_argument("--levels", nargs="+", default=["none", "slight", "moderate", "severe"])
    ap.add_argument("--huber", type=float, nargs="+", default=[2.0], help="Huber thresholds (config axis)")
    ap.add_argument("--gmm-k", type=int, nargs="+", default=[3], help="GMM components (config axis)")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--size", type=int, nargs=2, default=[96, 128], metavar=("H", "W"))
    ap.add_argument("--batching", choices=["vmap", "map"], default=None,
                    help="map (default; cheaper on CPUs) or vmap (the default with --quick)")
    ap.add_argument("--throughput", type=int, nargs="*", default=[1, 8, 32], help="batch sizes to time")
    ap.add_argument("--check", action="store_true", help="also run on one device and compare")
    ap.add_argument("--out", default="sweep_out")
    ap.add_argument("--quick", action="store_true",
                    help="2 seeds x 2 levels of 6 frames, vmap batching on 2 emulated devices, with --check, "
                         "no throughput runs, one call of the batch (compile_s: compile + that run)")
    ap.add_argument("--json", default=None, metavar="PATH")
    return ap.parse_args()


ARGS = _parse() if __name__ == "__main__" else None
if ARGS is not None and ARGS.quick and ARGS.devices is None:
    ARGS.devices = 2  # the quick run proves sharded == single device on 2 emulated CPU devices
if ARGS is not None and ARGS.devices:
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") +
                               f" --xla_force_host_platform_device_count={ARGS.devices}").strip()
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import dataclasses  # noqa: E402
import functools  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax  # noqa: E402
import numpy as np  # noqa: E402
from jax.sharding import Mesh, NamedSharding, PartitionSpec  # noqa: E402

from cm3d import pipeline  # noqa: E402
from cm3d.data import synthetic  # noqa: E402
from cm3d.data.atomic import atomic_write  # noqa: E402
from cm3d.eval import metrics  # noqa: E402
from cm3d.outputs import write_json  # noqa: E402


# ----------------------------------------------------------------------------------------------
# The sweep as functions (tests import these)


def make_config(base: pipeline.PipelineConfig, huber: float, gmm_k: int) -> pipeline.PipelineConfig:
    graph = dataclasses.replace(base.refine.graph, huber_k=huber)
    motion = dataclasses.replace(base.motion, gmm=dataclasses.replace(base.motion.gmm, num_components=gmm_k))
    return dataclasses.replace(base, refine=dataclasses.replace(base.refine, graph=graph), motion=motion)


def make_batch(seeds, levels, frames: int, size, cfg: pipeline.PipelineConfig):
    """Sequences (host) and their stacked, padded pipeline inputs: one per (seed, level)."""
    wcfg = synthetic.WorldConfig(height=size[0], width=size[1])
    seqs, rows = [], []
    for seed in seeds:
        scene = synthetic.make_scene(seed, wcfg)
        images, gt = synthetic.render_ground_truth(scene, 0, frames, wcfg)
        for level in levels:
            seqs.append(synthetic.make_priors(images, gt, level, seed=1009 * seed + 1))
            rows.append({"seed": seed, "level": level})
    inputs = [pipeline.prepare(s, cfg) for s in seqs]
    return seqs, rows, jax.tree.map(lambda *a: np.stack(a), *inputs)


def _pad(tree, n: int):
    B = jax.tree.leaves(tree)[0].shape[0]
    idx = np.minimum(np.arange(n), B - 1)
    return jax.tree.map(lambda a: np.asarray(a)[idx], tree)


@functools.lru_cache(maxsize=None)
def batched_runner(cfg: pipeline.PipelineConfig, mesh: Mesh, batching: str):
    """``run(states, inputs) -> (states, outputs)`` over a leading batch axis, sharded on ``mesh``
    (cached: one jitted function per config, mesh and batching; jit caches one program per shape)."""
    one = lambda s, i: pipeline._run_sequence(s, i, cfg)  # noqa: E731
    if batching == "vmap":
        body = jax.vmap(one)
    else:
        body = lambda s, i: jax.lax.map(lambda a: one(*a), (s, i))  # noqa: E731
    spec = NamedSharding(mesh, PartitionSpec("batch"))
    return jax.jit(body, in_shardings=(spec, spec), out_shardings=spec), spec


def run_batch(cfg, inputs, mesh: Mesh, batching: str = "map", timed: bool = True):
    """Run every sequence of ``inputs`` (stacked) with a fresh memory each; returns (outputs, seconds
    of the first call incl. compilation, seconds of a second call; NaN with ``timed`` False, which
    skips the second call)."""
    B = jax.tree.leaves(inputs)[0].shape[0]
    n = mesh.devices.size
    Bp = -(-B // n) * n
    inputs = _pad(inputs, Bp)
    first = jax.tree.map(lambda a: a[0], inputs)
    state = pipeline.init_state(first, cfg)
    states = jax.tree.map(lambda a: np.broadcast_to(np.asarray(a), (Bp,) + np.shape(a)), state)
    run, spec = batched_runner(cfg, mesh, batching)
    states, inputs = jax.device_put((states, inputs), spec)
    t0 = time.perf_counter()
    out = jax.block_until_ready(run(states, inputs)[1])
    t1 = time.perf_counter()
    if not timed:
        return jax.tree.map(lambda a: np.asarray(a)[:B], out), t1 - t0, float("nan")
    jax.block_until_ready(run(states, inputs)[1])
    t2 = time.perf_counter()
    return jax.tree.map(lambda a: np.asarray(a)[:B], out), t1 - t0, t2 - t1


def run_alone(cfg, inputs):
    """The reference of the sharded batch: every sequence of ``inputs`` (stacked) run alone by the
    plain :func:`cm3d.pipeline.run_sequence` on the default device, fresh memory each; outputs stacked."""
    outs = []
    for b in range(jax.tree.leaves(inputs)[0].shape[0]):
        x = jax.tree.map(lambda a: a[b], inputs)
        outs.append(pipeline.run_sequence(pipeline.init_state(x, cfg), x, cfg)[1])
    return jax.tree.map(lambda *a: np.stack([np.asarray(v) for v in a]), *outs)


def evaluate(outputs, seqs, rows, cfg):
    table = []
    for b, (seq, row) in enumerate(zip(seqs, rows)):
        res = pipeline.collect(jax.tree.map(lambda a: a[b], outputs), seq, cfg)
        ts, gt = seq.timestamps, seq.gt
        prior = metrics.evaluate_trajectories(ts, gt.cam_to_world, ts, res.prior)
        ref = metrics.evaluate_trajectories(ts, gt.cam_to_world, ts, res.poses)
        iou = metrics.mask_metrics(res.masks, gt.dynamic_mask)["iou"]
        table.append({**row, "ate_prior": prior["ate"], "ate_cm3d": ref["ate"], "rpe_trans_prior": prior["rpe_trans"],
                      "rpe_trans_cm3d": ref["rpe_trans"], "rpe_rot_prior": prior["rpe_rot"],
                      "rpe_rot_cm3d": ref["rpe_rot"], "mask_iou": float(iou)})
    return table


def compare_alone(outputs, alone, seqs, cfg) -> dict:
    """The batch's outputs against each sequence run alone: ``sharded_equals_single`` (max |refined
    pose difference|; ~1e-7 with ``map``: the same program per sequence), ``poses_within_1e-3`` (share
    of pose entries), ``window_ends_equal`` and ``windows_equal`` (refined flags and observation counts;
    1.0 / 0.0), ``mask_agreement`` (share of pixels). With ``vmap`` the batched operations round
    differently, which moves the LM's optimum along directions tiny windows leave nearly flat (the
    ``--quick`` run at 96x128: at most 9e-6)."""
    same = lambda a, b: float(np.array_equal(np.asarray(a), np.asarray(b)))  # noqa: E731
    diff = np.abs(poses_of(alone, seqs, cfg) - poses_of(outputs, seqs, cfg))
    return {"sharded_equals_single": float(diff.max()), "poses_within_1e-3": float(np.mean(diff <= 1e-3)),
            "window_ends_equal": same(alone.window_end, outputs.window_end),
            "windows_equal": same(alone.window.refined, outputs.window.refined)
            * same(alone.window.observations, outputs.window.observations),
            "mask_agreement": float(np.mean(np.asarray(alone.mask) == np.asarray(outputs.mask)))}


def poses_of(outputs, seqs, cfg):
    return np.stack([pipeline.collect(jax.tree.map(lambda a: a[b], outputs), s, cfg).poses
                     for b, s in enumerate(seqs)])


# ----------------------------------------------------------------------------------------------


def write_csv(path: Path, table: list[dict]) -> None:
    cols = list(table[0])
    lines = [",".join(cols)] + [",".join(str(r[c]) for c in cols) for r in table]
    with atomic_write(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def plot(path: Path, table: list[dict], levels) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5), dpi=120)
    x = np.arange(len(levels))
    prior = [np.mean([r["ate_prior"] for r in table if r["level"] == lv]) for lv in levels]
    ax.plot(x, prior, "k--o", label="prior")
    for conf in sorted({r["config"] for r in table}):
        y = [np.mean([r["ate_cm3d"] for r in table if r["level"] == lv and r["config"] == conf]) for lv in levels]
        ax.plot(x, y, "-o", label=f"cm3d {conf}")
    ax.set_xticks(x, levels)
    ax.set_ylabel("ATE (Sim3-aligned)")
    ax.set_xlabel("prior noise")
    ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_write(path, "wb") as f:
        fig.savefig(f, format="png")
    plt.close(fig)


def main(args) -> None:
    if args.quick:  # the test of vmap + sharding == one sequence at a time (tests/test_sweep.py)
        # two sequences per device, so that vmap batches more than one
        args.seeds, args.levels, args.frames, args.throughput, args.check = [0, 1], ["slight", "moderate"], 6, [], True
        args.batching = args.batching or "vmap"
    args.batching = args.batching or "map"
    devices = jax.devices()
    mesh = Mesh(np.array(devices), ("batch",))
    # every sequence starts from an empty bank, so the memory can never recall (and since a sequence's
    # own stored map no longer supplies landmarks, the poses equal a memory-free run's): off, which
    # saves its share of every compilation
    base = pipeline.config_for(*args.size, use_memory=False)
    configs = [(f"huber={h:g},K={k}", make_config(base, h, k)) for h in args.huber for k in args.gmm_k]
    print(f"{len(devices)} {devices[0].platform} device(s); {len(args.seeds)} seeds x {len(args.levels)} levels x "
          f"{len(configs)} configs; {args.frames} frames at {args.size[0]}x{args.size[1]}; batching {args.batching}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    table, figures = [], {"devices": len(devices)}
    for ci, (name, cfg) in enumerate(configs):
        seqs, rows, inputs = make_batch(args.seeds, args.levels, args.frames, args.size, cfg)
        # (--quick: one call, the equality check; its timing would cost a second run of the batch)
        outputs, t_first, t_run = run_batch(cfg, inputs, mesh, args.batching, timed=not args.quick)
        rows_c = [{**r, "config": name} for r in evaluate(outputs, seqs, rows, cfg)]
        table += rows_c
        print(f"config {name}: {len(seqs)} sequences, first call {t_first:.1f} s (compile + run), "
              + (f"run {t_run:.2f} s" if np.isfinite(t_run) else "second run skipped (--quick)"))
        if ci == 0:
            # (--quick: compile + one run, an upper bound)
            figures["compile_s"] = t_first - t_run if np.isfinite(t_run) else t_first
            for lv in args.levels:
                sel = [r for r in rows_c if r["level"] == lv]
                figures[f"ate_prior_{lv}"] = float(np.mean([r["ate_prior"] for r in sel]))
                figures[f"ate_cm3d_{lv}"] = float(np.mean([r["ate_cm3d"] for r in sel]))
            if args.check:
                figures |= compare_alone(outputs, run_alone(cfg, inputs), seqs, cfg)
                print(f"sharded over {len(devices)} device(s) ({args.batching}) vs one sequence at a time: max |pose "
                      f"difference| {figures['sharded_equals_single']:.2e} ({figures['poses_within_1e-3']:.1%} of "
                      f"entries within 1e-3), window ends equal {bool(figures['window_ends_equal'])}, masks agree on "
                      f"{figures['mask_agreement']:.2%} of pixels")

    print(f"\n{'config':>14} {'level':>9} | {'ATE prior':>9} {'ATE cm3d':>9} | {'RPEr prior':>10} "
          f"{'RPEr cm3d':>9} | {'mask IoU':>8}   (mean over {len(args.seeds)} seeds)")
    for name, _ in configs:
        for lv in args.levels:
            sel = [r for r in table if r["config"] == name and r["level"] == lv]
            m = {k: np.mean([r[k] for r in sel]) for k in ("ate_prior", "ate_cm3d", "rpe_rot_prior", "rpe_rot_cm3d",
                                                           "mask_iou")}
            print(f"{name:>14} {lv:>9} | {m['ate_prior']:>9.5f} {m['ate_cm3d']:>9.5f} | {m['rpe_rot_prior']:>10.3f} "
                  f"{m['rpe_rot_cm3d']:>9.3f} | {m['mask_iou']:>8.3f}")
    write_csv(out / "sweep.csv", table)
    plot(out / "ate_vs_noise.png", table, args.levels)
    print(f"\nwrote {out / 'sweep.csv'} and {out / 'ate_vs_noise.png'}")

    name, cfg = configs[0]
    if args.throughput:
        print(f"\nthroughput ({name}, {args.frames}-frame sequences, {len(devices)} device(s)):")
        print(f"{'batch':>6} | {'compile s':>9} | {'run s':>7} | {'seq/s':>7}")
        seeds = list(range(max(args.throughput)))
        seqs, rows, inputs = make_batch(seeds, ["moderate"], args.frames, args.size, cfg)
        for b in args.throughput:
            sub = jax.tree.map(lambda a: a[:b], inputs)
            _, t_first, t_run = run_batch(cfg, sub, mesh, args.batching)
            figures[f"seq_per_s_{b}"] = b / t_run
            print(f"{b:>6} | {t_first - t_run:>9.1f} | {t_run:>7.2f} | {b / t_run:>7.2f}")
    if args.json:
        write_json(args.json, figures)


if __name__ == "__main__":
    main(ARGS)
