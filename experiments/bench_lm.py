"""Benchmark: cm3d's Schur-complement LM against GTSAM, optimistix and jaxopt on bundle adjustment.

    .venv/bin/python experiments/bench_lm.py [--repeats 5] [--quick] [--json PATH]

All in one run, on the same seeded problems (:func:`cm3d.solvers.factors.random_problem`: a
video-like camera path, landmarks tracked over 12 consecutive frames, 1 px noise, 2 % gross
outliers, Huber projection factors, a gauge prior on the first pose and motion factors between the
pose pairs of ``GraphConfig.motion_pairs``, consecutive by default; GTSAM gets BetweenFactors between
the same pairs, :func:`cm3d.baselines.gtsam_graph`):

1. small (60 poses, 1500 landmarks, 18k projections) and large (200 poses, 5000 landmarks, 60k):
   cm3d (dense Schur; the large one also with the matrix-free PCG Schur solver) and GTSAM's
   ``LevenbergMarquardtOptimizer`` (same LM schedule): time to convergence, per iteration, final
   cost; runs interleaved, median of ``--repeats``;
2. optimistix and jaxopt LevenbergMarquardt on the same residuals (Huber as ``sqrt(2ρ)``
   residuals, poses as tangent increments), dense Jacobians: on growing problems until they pass
   a time/memory budget, next to cm3d on the same problem;
3. ``vmap`` over a batch of 8 problems against 8 sequential solves (throughput ratio), on one
   device and with the batch sharded over the two CPU cores (``shard_map``, two host devices);
4. the implicit gradient of a loss of the optimum w.r.t. the observations: its cost in forward LM
   iterations, and its error against central finite differences of tightly converged solves.

Every ratio compares peers measured in the same run. OpenBLAS (jax's LAPACK on CPU) is pinned to
one thread: its spinning threads collapse on shared cores.
Headline JSON keys: speedup_small, speedup_large, cost_rel_diff_small, batch8_throughput_ratio,
grad_cost_in_iterations, grad_rel_err (and more).
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# two host "devices" (one per core) so that a batch can be sharded across the cores; every other
# measurement runs on the first one
if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from cm3d import baselines  # noqa: E402
from cm3d.outputs import write_json  # noqa: E402
from cm3d.ops import se3  # noqa: E402
from cm3d.solvers import factors, lm  # noqa: E402

COMPILER = {}  # --quick: {"xla_backend_optimization_level": 0}, compile time dominates there


def jit(f, **kw):
    return jax.jit(f, compiler_options=COMPILER or None, **kw)


def SOLVE(graph, init, options):  # noqa: N802
    return _SOLVE(graph, init, options)


_SOLVE = None


def _timed(fn, *args):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - t0


def _problem(seed, n, m, obs=12):
    return factors.random_problem(seed, n, m, obs_per_point=obs, outlier_frac=0.02)


# ----------------------------------------------------------------------------------------------
# 1. cm3d vs GTSAM


def bench_vs_gtsam(name, n, m, repeats, with_pcg):
    graph, init, _ = _problem(0, n, m)
    cap = lm.schur_pair_count(graph, m)
    opts = lm.LMOptions(backward="none", pair_capacity=cap, linear_solver="dense")
    SOLVE(graph, init, opts).cost.block_until_ready()  # compile
    cm, gt = [], []
    res = ref = None
    for _ in range(repeats):
        res, t = _timed(SOLVE, graph, init, opts)
        cm.append(t)
        ref = baselines.gtsam_solve(graph, init)
        gt.append(ref.time_s)
    row = {"problem": name, "poses": n, "landmarks": m,
           "projections": int(np.sum(np.asarray(graph.projection.weight) > 0)),
           "cm3d_s": statistics.median(cm), "cm3d_min_s": min(cm),
           "gtsam_s": statistics.median(gt), "gtsam_min_s": min(gt),
           "cm3d_iters": int(res.iterations), "cm3d_solves": int(res.linear_solves), "gtsam_iters": ref.iterations,
           "cm3d_cost": float(res.cost), "gtsam_cost": ref.cost, "initial_cost": float(res.initial_cost)}
    row["cm3d_per_iter_ms"] = 1e3 * row["cm3d_s"] / max(row["cm3d_iters"], 1)
    row["gtsam_per_iter_ms"] = 1e3 * row["gtsam_s"] / max(row["gtsam_iters"], 1)
    row["speedup"] = row["gtsam_s"] / row["cm3d_s"]
    row["speedup_per_iter"] = row["gtsam_per_iter_ms"] / row["cm3d_per_iter_ms"]
    row["cost_rel_diff"] = abs(row["cm3d_cost"] - row["gtsam_cost"]) / row["gtsam_cost"]
    if with_pcg:
        popts = dataclasses.replace(opts, linear_solver="pcg")  # default 300 CG iterations, tol 1e-10
        SOLVE(graph, init, popts).cost.block_until_ready()
        times = []
        for _ in range(max(1, repeats // 2)):
            pres, t = _timed(SOLVE, graph, init, popts)
            times.append(t)
        row.update({"pcg_s": statistics.median(times), "pcg_iters": int(pres.iterations),
                    "pcg_solves": int(pres.linear_solves), "pcg_cost": float(pres.cost)})
        row["pcg_per_iter_ms"] = 1e3 * row["pcg_s"] / max(row["pcg_iters"], 1)
        row["pcg_cost_rel_diff"] = abs(row["pcg_cost"] - row["gtsam_cost"]) / row["gtsam_cost"]
    return row


# ----------------------------------------------------------------------------------------------
# 2. dense least-squares peers on the same residuals


def dense_residual_fn(graph, init):
    """Residual vector r(y) with ½|r|² = the graph's objective; y = (pose tangents, point offsets)."""
    N, M = init.poses.shape[0], init.points.shape[0]
    k = graph.huber_k
    w = graph.projection.weight

    def fn(y, args=None):
        dp = y[: 6 * N].reshape(N, 6)
        dl = y[6 * N:].reshape(M, 3)
        x = factors.Variables(init.poses @ se3.exp(dp), init.points + dl)
        e, _ = factors.projection_residual(graph, x)
        sq = jnp.sum(e * e, -1)
        rho = factors.huber_loss(sq, k)
        scale = jnp.where(sq > 0, jnp.sqrt(2 * rho / jnp.where(sq > 0, sq, 1.0)), 1.0)
        r_proj = (e * (scale * jnp.sqrt(w))[:, None]).ravel()
        ep, em = factors.pose_residuals(graph, x.poses)
        r_p = (ep * jnp.sqrt(graph.prior.weight)[:, None]).ravel()
        r_m = (em * jnp.sqrt(graph.motion.weight)[:, None]).ravel()
        return jnp.concatenate([r_proj, r_p, r_m])

    return fn, jnp.zeros(6 * N + 3 * M)


def bench_dense_peers(sizes, budget_s, mem_budget_gb):
    import jaxopt
    import optimistix as optx

    rows = []
    stopped = {"optimistix": None, "jaxopt": None}
    last = {}  # name -> (time, residuals, params) of the previous size, to predict the next
    for n, m in sizes:
        graph, init, _ = _problem(0, n, m)
        fn, y0 = dense_residual_fn(graph, init)
        n_res = int(fn(y0).shape[0])
        jac_gb = n_res * y0.shape[0] * 8 / 1e9
        row = {"poses": n, "landmarks": m, "residuals": n_res, "params": int(y0.shape[0]), "jacobian_gb": jac_gb}
        opts = lm.LMOptions(backward="none", pair_capacity=lm.schur_pair_count(graph, m), linear_solver="dense")
        SOLVE(graph, init, opts).cost.block_until_ready()
        r, t = _timed(SOLVE, graph, init, opts)
        row.update({"cm3d_s": t, "cm3d_cost": float(r.cost), "cm3d_iters": int(r.iterations)})
        def run_optx(y):
            sol = optx.least_squares(fn, optx.LevenbergMarquardt(rtol=1e-6, atol=1e-6), y, max_steps=100,
                                     throw=False)
            return sol.value, sol.stats["num_steps"]

        def run_jaxopt(y):
            out = jaxopt.LevenbergMarquardt(fn, maxiter=100, tol=1e-6, solver="cholesky",
                                            materialize_jac=True).run(y)
            return out.params, out.state.iter_num

        peers = {"optimistix": jit(run_optx), "jaxopt": jit(run_jaxopt)}
        for name, run in peers.items():
            if name in last:  # dense LM: QR / Cholesky of the Jacobian, ~ residuals x params^2
                t0, r0, p0 = last[name]
                predicted = t0 * (n_res / r0) * (y0.shape[0] / p0) ** 2
                if predicted > budget_s and stopped[name] is None:
                    stopped[name] = f"stopped at {n} poses: predicted {predicted:.0f} s > budget {budget_s:.0f} s"
            if stopped[name] is not None or jac_gb > mem_budget_gb:
                row[f"{name}_s"] = None
                row[f"{name}_note"] = stopped[name] or f"skipped: dense Jacobian {jac_gb:.1f} GB"
                continue
            out = run(y0)
            jax.block_until_ready(out)  # compile + first run
            (y, iters), t = _timed(run, y0)
            iters = int(iters)
            row.update({f"{name}_s": t, f"{name}_cost": float(0.5 * jnp.sum(fn(y) ** 2)), f"{name}_iters": iters})
            last[name] = (t, n_res, y0.shape[0])
            if t > budget_s:
                stopped[name] = f"stopped after {n} poses: {t:.1f} s > budget {budget_s:.0f} s"
        rows.append(row)
    return rows


# ----------------------------------------------------------------------------------------------
# 3. vmap over a batch


def bench_batch(n, m, batch, repeats, shard=True):
    """8 sequential solves vs one ``vmap`` over the batch (one device), and ``vmap`` with the batch
    sharded over the host's CPU devices (``shard_map``: one half per core)."""
    probs = [_problem(s, n, m)[:2] for s in range(batch)]
    cap = max(lm.schur_pair_count(g, m) for g, _ in probs)
    opts = lm.LMOptions(backward="none", pair_capacity=cap, linear_solver="dense")
    stacked = jax.tree.map(lambda *a: jnp.stack(a), *probs)
    vsolve = jit(jax.vmap(lambda g, x: lm.solve(g, x, opts)))
    devices = jax.devices()
    sharded = None
    if shard and len(devices) > 1 and batch % len(devices) == 0:
        from jax.sharding import Mesh, PartitionSpec

        mesh = Mesh(np.array(devices), ("batch",))
        spec = PartitionSpec("batch")
        sharded = jit(jax.shard_map(jax.vmap(lambda g, x: lm.solve(g, x, opts)), mesh=mesh,
                                    in_specs=(spec, spec), out_specs=spec, check_vma=False))
        jax.block_until_ready(sharded(*stacked))
    jax.block_until_ready(vsolve(*stacked))
    jax.block_until_ready(SOLVE(*probs[0], opts))
    seq_t, bat_t, sh_t = [], [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for g, x in probs:
            jax.block_until_ready(SOLVE(g, x, opts))
        seq_t.append(time.perf_counter() - t0)
        out, t = _timed(vsolve, *stacked)
        bat_t.append(t)
        if sharded is not None:
            sh_t.append(_timed(sharded, *stacked)[1])
    seq, bat = statistics.median(seq_t), statistics.median(bat_t)
    row = {"batch": batch, "poses": n, "landmarks": m, "sequential_s": seq, "batched_s": bat, "vmap_ratio": seq / bat,
           "devices": len(devices), "max_iters": int(jnp.max(out.iterations)),
           "min_iters": int(jnp.min(out.iterations))}
    if sh_t:
        row["sharded_s"] = statistics.median(sh_t)
        row["sharded_ratio"] = seq / row["sharded_s"]
    return row


# ----------------------------------------------------------------------------------------------
# 4. implicit gradient


def bench_gradient(n, m, repeats):
    """Forward (LM + Newton polish, keeping the residuals) and backward (the implicit VJP) timed
    separately through ``jax.vjp``; the backward in units of one plain LM iteration."""
    graph, init, _ = _problem(0, n, m)
    cap = lm.schur_pair_count(graph, m)
    iopts = dataclasses.replace(lm.IMPLICIT_OPTIONS, pair_capacity=cap)
    wts = jnp.linspace(1.0, 2.0, n)[:, None]

    def loss(z):
        g = graph.replace(projection=graph.projection.replace(z=z))
        r = lm.solve(g, init, iopts)
        return jnp.sum(r.params.poses[:, :3, 3] * wts) + 1e-3 * jnp.sum(r.params.points)

    fwd = jit(lambda z: jax.vjp(loss, z))
    bwd = jit(lambda vjp_fn: vjp_fn(jnp.ones((), jnp.float64))[0])
    z = graph.projection.z
    val, vjp_fn = jax.block_until_ready(fwd(z))
    grad = jax.block_until_ready(bwd(vjp_fn))
    opts = lm.LMOptions(backward="none", pair_capacity=cap, linear_solver="dense")
    jax.block_until_ready(SOLVE(graph, init, opts))
    tf, tb, ti = [], [], []
    for _ in range(repeats):
        (val, vjp_fn), t = _timed(fwd, z)
        tf.append(t)
        grad, t = _timed(bwd, vjp_fn)
        tb.append(t)
        r, t = _timed(SOLVE, graph, init, opts)
        ti.append(t / max(int(r.iterations), 1))
    t_fwd, t_bwd, t_it = statistics.median(tf), statistics.median(tb), statistics.median(ti)
    d = jnp.asarray(np.random.default_rng(0).normal(size=z.shape))
    analytic = float(jnp.sum(grad * d))
    # central differences of tightly converged solves; the step must stay below the Huber kinks'
    # spacing (with 18k residuals some sit near the threshold, so the optimum is only piecewise
    # smooth): steps of 1e-2 px already mix pieces (see docs/factor_graph.md)
    fd = {}
    for eps in (1e-4, 3e-5):
        fd[eps] = float(fwd(z + eps * d)[0] - fwd(z - eps * d)[0]) / (2 * eps)
    best = min(fd.values(), key=lambda v: abs(v - analytic))
    return {"poses": n, "landmarks": m, "forward_s": t_fwd, "backward_s": t_bwd,
            "lm_iteration_s": t_it, "cost_in_iterations": t_bwd / t_it, "cost_in_forward_solves": t_bwd / t_fwd,
            "directional": analytic, "fd": best, "fd_all": fd, "rel_err": abs(analytic - best) / abs(best)}


# ----------------------------------------------------------------------------------------------


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="small problems, one repeat (seconds)")
    ap.add_argument("--json", default=None, metavar="PATH")
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    global _SOLVE
    if args.quick:
        COMPILER["xla_backend_optimization_level"] = 0
    _SOLVE = jit(lm.solve, static_argnames="options")
    if args.quick:  # one small problem for everything, so that few programs compile
        small, large, reps = (16, 300), None, 1
        dense_sizes, budget, batch_size = [], 5.0, (16, 300)
    else:
        small, large, reps = (60, 1500), (200, 5000), args.repeats
        dense_sizes, budget, batch_size = [(4, 60), (8, 150), (15, 350), (30, 750), (60, 1500)], 30.0, small
    print(f"device: {jax.devices()[0].device_kind}, {os.cpu_count()} CPUs visible, float64")
    if args.quick:
        print("--quick: one 16-pose problem, cm3d compiled at LLVM -O0 (compile time dominates): a smoke run, "
              "not the benchmark")
    print()

    rows = [bench_vs_gtsam("small", *small, reps, False)]
    if large is not None:
        rows.append(bench_vs_gtsam("large", *large, reps, True))
    print("1. bundle adjustment, cm3d (dense Schur) vs GTSAM LevenbergMarquardtOptimizer (median of "
          f"{reps}; same LM schedule)\n")
    head = (f"{'problem':>8} {'poses':>5} {'lmks':>5} {'proj':>6} | {'cm3d s':>7} {'GTSAM s':>8} {'speedup':>7} | "
            f"{'cm3d ms/it':>10} {'GTSAM ms/it':>11} {'ratio':>6} | {'iters':>7} | {'cm3d cost':>14} "
            f"{'GTSAM cost':>14} {'rel diff':>9}")
    print(head + "\n" + "-" * len(head))
    for r in rows:
        print(f"{r['problem']:>8} {r['poses']:>5} {r['landmarks']:>5} {r['projections']:>6} | {r['cm3d_s']:>7.3f} "
              f"{r['gtsam_s']:>8.3f} {r['speedup']:>6.2f}x | {r['cm3d_per_iter_ms']:>10.1f} "
              f"{r['gtsam_per_iter_ms']:>11.1f} "
              f"{r['speedup_per_iter']:>5.2f}x | {r['cm3d_iters']:>3}/{r['gtsam_iters']:<3} | {r['cm3d_cost']:>14.6f} "
              f"{r['gtsam_cost']:>14.6f} {r['cost_rel_diff']:>9.1e}")
    lg = rows[-1]
    if "pcg_s" in lg:
        print(f"\n   {lg['problem']}, matrix-free Schur + block-Jacobi PCG (300 CG iterations, tol 1e-10): "
              f"{lg['pcg_s']:.3f} s, {lg['pcg_iters']} iterations, {lg['pcg_solves']} solves "
              f"({lg['pcg_per_iter_ms']:.1f} ms/it; GTSAM time / PCG time {lg['gtsam_s'] / lg['pcg_s']:.2f}x), "
              f"final cost {lg['pcg_cost']:.6f} (rel diff to GTSAM {lg['pcg_cost_rel_diff']:.1e})")

    print("\n2. dense LM peers on the same residuals (time to convergence, compilation excluded)\n")
    drows = bench_dense_peers(dense_sizes, budget, 4.0) if dense_sizes else []
    if not drows:
        print("   (skipped with --quick)")
    head = (f"{'poses':>5} {'lmks':>5} {'jac GB':>7} | {'cm3d s':>7} {'optimistix s':>12} {'jaxopt s':>9} | "
            f"{'cm3d cost':>13} {'optx cost':>13} {'jaxopt cost':>13}")
    if drows:
        print(head + "\n" + "-" * len(head))
    fmt = lambda v, w, p: f"{v:>{w}.{p}f}" if isinstance(v, float) else f"{'-':>{w}}"  # noqa: E731
    for r in drows:
        print(f"{r['poses']:>5} {r['landmarks']:>5} {r['jacobian_gb']:>7.3f} | {r['cm3d_s']:>7.3f} "
              f"{fmt(r.get('optimistix_s'), 12, 3)} {fmt(r.get('jaxopt_s'), 9, 3)} | {r['cm3d_cost']:>13.4f} "
              f"{fmt(r.get('optimistix_cost'), 13, 4)} {fmt(r.get('jaxopt_cost'), 13, 4)}")
        for name in ("optimistix", "jaxopt"):
            if r.get(f"{name}_note"):
                print(f"      {name}: {r[f'{name}_note']}")

    b = bench_batch(*batch_size, 8, max(1, reps // 2 + 1), shard=not args.quick)
    print(f"\n3. vmap: batch of {b['batch']} problems ({b['poses']} poses, {b['landmarks']} landmarks, iterations "
          f"{b['min_iters']}-{b['max_iters']}): 8 sequential solves {b['sequential_s']:.3f} s; vmap on one device "
          f"{b['batched_s']:.3f} s ({b['vmap_ratio']:.2f}x throughput)")
    if "sharded_s" in b:
        print(f"   vmap with the batch sharded over the {b['devices']} CPU cores (shard_map): {b['sharded_s']:.3f} s "
              f"({b['sharded_ratio']:.2f}x throughput)")

    g = bench_gradient(*small, reps)
    print(f"\n4. implicit gradient d loss / d observations ({g['poses']} poses): forward (LM + Newton polish) "
          f"{g['forward_s']:.3f} s, backward (jax.vjp) {g['backward_s']:.3f} s "
          f"= {g['cost_in_iterations']:.2f} LM iterations ({1e3 * g['lm_iteration_s']:.1f} ms each); "
          f"directional derivative {g['directional']:.6e} vs finite differences {g['fd']:.6e}: "
          f"rel err {g['rel_err']:.1e} (steps 1e-4, 3e-5 px: {', '.join(f'{v:.6e}' for v in g['fd_all'].values())})")

    big = rows[1] if len(rows) > 1 else None
    figures = {
        "speedup_small": rows[0]["speedup"],
        "speedup_large": big and big["speedup"],
        "speedup_per_iter_small": rows[0]["speedup_per_iter"],
        "speedup_per_iter_large": big and big["speedup_per_iter"],
        "cost_rel_diff_small": rows[0]["cost_rel_diff"],
        "cost_rel_diff_large": big and big["cost_rel_diff"],
        "speedup_pcg_large": big and big["gtsam_s"] / big["pcg_s"],
        "pcg_cost_rel_diff_large": big and big["pcg_cost_rel_diff"],
        "batch8_throughput_ratio": b.get("sharded_ratio", b["vmap_ratio"]),
        "batch8_vmap_one_device_ratio": b["vmap_ratio"],
        "grad_cost_in_iterations": g["cost_in_iterations"],
        "grad_rel_err": g["rel_err"],
        "cm3d_ms_per_iter_small": rows[0]["cm3d_per_iter_ms"],
        "gtsam_ms_per_iter_small": rows[0]["gtsam_per_iter_ms"],
        "cm3d_ms_per_iter_large": big and big["cm3d_per_iter_ms"],
        "gtsam_ms_per_iter_large": big and big["gtsam_per_iter_ms"],
    }
    print("\nheadline:")
    for k, v in figures.items():
        print(f"  {k:28s} {'n/a (--quick: one problem size)' if v is None else f'{v:.4g}'}")
    if args.json:
        write_json(args.json, figures)


if __name__ == "__main__":
    main()
