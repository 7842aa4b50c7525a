"""Learning the factor graph's noise model through the solver (implicit gradients).

    .venv/bin/python experiments/learn_weights.py [--train 4 --test 4 --steps 30] [--quick] [--json PATH]

A template for differentiable pose-refinement research. Each problem is a rendered synthetic
visit with VGGT-like priors at one noise level: landmarks from static, confident pixels (ground-
truth static mask), tracked by OpenCV DIS flow, lifted with the prior depth; a share of them are
*memory landmarks* (their initial 3D position comes from an exact stored map, their projections
get the covariance ``α Σ``). After one outlier-rejection round with the default weights, the
refined poses are a differentiable function of the graph's weights:

    poses*(θ) = argmin  |f_prior|² + Σ ρ_k(|f_proj|² / σ²·(α if memory)) + Σ |f_motion / σ_motion|²

with θ = (Huber threshold k, motion-factor std σ_rot and σ_trans, memory factor α), all learned in
log/logit space. The loss is the refined trajectory's ATE (Sim(3)-aligned RMSE of camera centres
against ground truth, differentiable through the closed-form Umeyama). Its gradient comes from
:func:`cm3d.solvers.lm.solve`'s implicit ``custom_vjp`` (exact-Hessian adjoint at the optimum);
optax Adam updates θ, with early stopping on validation scenes. The script reports the ATE on
held-out scenes of the default and the learned weights, and the gradient's agreement with central
finite differences.

Headline JSON keys: ``ate_prior_<split>``, ``ate_default_<split>``, ``ate_learned_<split>`` for
``split`` in train / val / test, ``grad_fd_rel_err``, ``huber_k``, ``motion_sigma_rot``,
``motion_sigma_trans``, ``memory_alpha``, ``step_s``.
"""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import functools  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

from cm3d import trajectory  # noqa: E402
from cm3d.data import synthetic  # noqa: E402
from cm3d.outputs import write_json  # noqa: E402
from cm3d.ops import flow as oflow  # noqa: E402
from cm3d.solvers import factors, lm  # noqa: E402
from cm3d.solvers.align import umeyama  # noqa: E402

PARAM_NAMES = ("huber_k", "motion_sigma_rot", "motion_sigma_trans", "memory_alpha")


# ----------------------------------------------------------------------------------------------
# Problems


def make_problem(scene_seed: int, cfg, frames: int, level: str, track_cfg, memory_share: float):
    """One rendered visit -> (graph after one outlier round, initial variables, GT centres)."""
    scene = synthetic.make_scene(scene_seed, cfg)
    images, gt = synthetic.render_ground_truth(scene, 0, frames, cfg)
    seq = synthetic.make_priors(images, gt, level, seed=7919 * scene_seed + 1)
    fw = oflow.sequence_flow(images)
    bw = np.stack([oflow.compute_flow(images[i + 1], images[i]) for i in range(frames - 1)])
    f64 = lambda a: jnp.asarray(a, jnp.float64)  # noqa: E731
    static = jnp.asarray(~gt.dynamic_mask)
    K, prior = f64(seq.intrinsic), f64(seq.cam_to_world)
    pts, obs, tracks, _ = _landmarks(f64(seq.depth), f64(seq.depth_conf), static, K, prior, f64(fw), f64(bw),
                                     track_cfg)
    # Memory landmarks: a random share of the landmarks, placed where an exact stored map has them
    # (ground truth in the prior's frame and scale).
    s = seq.meta["prior_scale"]
    rel = np.linalg.inv(gt.cam_to_world[0]) @ gt.cam_to_world
    rel[:, :3, 3] *= s
    gt_pts, gt_ok = jax.jit(trajectory.lift_landmarks)(tracks, f64(gt.depth * s), K, f64(rel))
    rng = np.random.default_rng(scene_seed)
    mem = jnp.asarray(rng.random(pts.shape[0]) < memory_share) & gt_ok
    pts = jnp.where(mem[:, None], gt_pts, pts)
    T = tracks.valid.shape[1]
    graph = factors.build_graph(prior, K, obs.pose_idx, obs.point_idx, obs.uv, obs.valid,
                                jnp.repeat(mem, T), cfg=factors.GraphConfig())
    x0 = factors.Variables(prior, pts)
    graph = _reject(graph, x0)
    centres = jnp.asarray(gt.cam_to_world[:, :3, 3])
    return {"graph": graph, "x0": x0, "gt": centres, "prior_ate": float(ate(prior[:, :3, 3], centres))}


@functools.partial(jax.jit, static_argnums=7)
def _landmarks(depth, conf, static, K, prior, fw, bw, track_cfg):
    return trajectory.prepare_landmarks(depth, conf, static, K, prior, fw, bw, track_cfg)


@jax.jit
def _reject(graph, x0):
    """One solve with the default weights, then the adaptive outlier rejection (fixed afterwards)."""
    first = lm.solve(graph, x0, lm.LMOptions(backward="none", max_iterations=50))
    return factors.reject_outliers(graph, first.params)[0]


def ate(est_centres, gt_centres):
    """Sim(3)-aligned RMSE of camera centres (differentiable)."""
    s, R, t = umeyama(est_centres, gt_centres, with_scale=True)
    aligned = s * est_centres @ R.T + t
    return jnp.sqrt(jnp.mean(jnp.sum((aligned - gt_centres) ** 2, -1)))


# ----------------------------------------------------------------------------------------------
# The learnable noise model


def default_params():
    g = factors.GraphConfig()
    raw = {"log_huber_k": np.log(g.huber_k), "log_motion_sigma_rot": np.log(g.motion_sigma_rot),
           "log_motion_sigma_trans": np.log(g.motion_sigma_trans),
           "logit_memory_alpha": np.log(g.memory_alpha / (1 - g.memory_alpha))}
    return {k: jnp.asarray(v, jnp.float64) for k, v in raw.items()}  # strongly typed: no retrace


def readable(params) -> dict:
    return {"huber_k": float(jnp.exp(params["log_huber_k"])),
            "motion_sigma_rot": float(jnp.exp(params["log_motion_sigma_rot"])),
            "motion_sigma_trans": float(jnp.exp(params["log_motion_sigma_trans"])),
            "memory_alpha": float(jax.nn.sigmoid(params["logit_memory_alpha"]))}


def with_params(graph: factors.FactorGraph, params) -> factors.FactorGraph:
    r, t = jnp.exp(params["log_motion_sigma_rot"]), jnp.exp(params["log_motion_sigma_trans"])
    sigma = jnp.broadcast_to(jnp.stack([t, t, t, r, r, r]), graph.motion.sigma.shape)
    return graph.replace(huber_k=jnp.exp(params["log_huber_k"]),
                         memory_alpha=jax.nn.sigmoid(params["logit_memory_alpha"]),
                         motion=graph.motion.replace(sigma=sigma))


#: A tightly converged forward solve (gradient-norm stop): the implicit gradient is exact only at
#: the optimum, and Adam turns even tiny gradients of a half-converged solve into full steps.
SOLVE = dataclasses.replace(lm.IMPLICIT_OPTIONS, max_iterations=400, max_linear_solves=1000)


def refined_ate(params, graph, x0, gt):
    res = lm.solve(with_params(graph, params), x0, SOLVE)
    return ate(res.params.poses[:, :3, 3], gt)


loss_and_grad = jax.jit(jax.value_and_grad(refined_ate))


def evaluate(params, graph, x0, gt):
    return loss_and_grad(params, graph, x0, gt)[0]  # one compiled program for training and evaluation


def mean_ate(params, problems) -> float:
    return float(np.mean([float(evaluate(params, p["graph"], p["x0"], p["gt"])) for p in problems]))


def fd_check(params, problem, eps: float = 1e-4, seed: int = 0):
    """Directional derivative along a random unit direction: implicit gradient vs central FD."""
    leaves, tree = jax.tree.flatten(params)
    d = np.random.default_rng(seed).normal(size=len(leaves))
    d /= np.linalg.norm(d)
    shift = lambda h: jax.tree.unflatten(tree, [v + h * di for v, di in zip(leaves, d)])  # noqa: E731
    args = (problem["graph"], problem["x0"], problem["gt"])
    _, g = loss_and_grad(params, *args)
    analytic = float(sum(float(gv) * di for gv, di in zip(jax.tree.leaves(g), d)))
    fd = (float(evaluate(shift(eps), *args)) - float(evaluate(shift(-eps), *args))) / (2 * eps)
    return analytic, fd, abs(analytic - fd) / max(abs(fd), 1e-12)


# ----------------------------------------------------------------------------------------------


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train", type=int, default=4, help="training scenes")
    ap.add_argument("--val", type=int, default=2, help="validation scenes (early stopping)")
    ap.add_argument("--test", type=int, default=4, help="held-out test scenes")
    ap.add_argument("--steps", type=int, default=25, help="Adam steps (full batch)")
    ap.add_argument("--lr", type=float, default=0.05)
    ap.add_argument("--level", default="moderate", choices=list(synthetic.NOISE_LEVELS))
    ap.add_argument("--memory-share", type=float, default=0.3, help="share of landmarks recalled from memory")
    ap.add_argument("--quick", action="store_true", help="one tiny training and test scene, 3 steps")
    ap.add_argument("--json", default=None, metavar="PATH")
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    if args.quick:
        cfg, frames, n_train, n_val, n_test, steps = synthetic.WorldConfig(height=72, width=96), 6, 1, 1, 1, 3
        track_cfg = trajectory.TrackConfig(cell=8, keyframe_every=2, track_length=5)
    else:
        cfg, frames, n_train, n_val, n_test, steps = (synthetic.WorldConfig(height=120, width=160), 16,
                                                      args.train, args.val, args.test, args.steps)
        track_cfg = trajectory.TrackConfig(cell=10, keyframe_every=3, track_length=8)
    print(f"{n_train} training + {n_val} validation + {n_test} held-out test scenes, {frames} frames at {cfg.height}x{cfg.width}, "
          f"{args.level} prior noise, {100 * args.memory_share:.0f}% memory landmarks")
    t0 = time.perf_counter()
    build = lambda s: make_problem(s, cfg, frames, args.level, track_cfg, args.memory_share)  # noqa: E731
    train = [build(100 + i) for i in range(n_train)]
    val = [build(300 + i) for i in range(n_val)]
    test = [build(200 + i) for i in range(n_test)]
    print(f"problems built in {time.perf_counter() - t0:.1f} s "
          f"({int(train[0]['graph'].projection.weight.astype(bool).sum())} inlier projections in the first)")

    params = default_params()
    opt = optax.adam(args.lr)
    state = opt.init(params)
    ate_default_train = mean_ate(params, train)
    print(f"\n{'step':>4} | {'train ATE':>10} {'val ATE':>10} | " + " ".join(f"{n:>18}" for n in PARAM_NAMES))
    step_times = []
    best, best_val = params, np.inf
    for it in range(steps + 1):
        t1 = time.perf_counter()
        vals, grads = zip(*(loss_and_grad(params, p["graph"], p["x0"], p["gt"]) for p in train))
        grad = jax.tree.map(lambda *g: sum(g) / len(g), *grads)
        if it > 0:
            step_times.append(time.perf_counter() - t1)
        v = mean_ate(params, val)
        if v < best_val:  # early stopping: keep the weights with the best validation ATE
            best, best_val = params, v
        r = readable(params)
        print(f"{it:>4} | {np.mean(vals):>10.6f} {v:>10.6f} | " + " ".join(f"{r[n]:>18.5g}" for n in PARAM_NAMES)
              + (" *" if best is params else ""))
        if it == steps:
            break
        updates, state = opt.update(grad, state)
        params = optax.apply_updates(params, updates)
    params = best

    analytic, fd, rel = fd_check(default_params(), train[0])
    figures = {
        "ate_prior_train": float(np.mean([p["prior_ate"] for p in train])),
        "ate_default_train": ate_default_train, "ate_learned_train": mean_ate(params, train),
        "ate_prior_val": float(np.mean([p["prior_ate"] for p in val])),
        "ate_default_val": mean_ate(default_params(), val), "ate_learned_val": best_val,
        "ate_prior_test": float(np.mean([p["prior_ate"] for p in test])),
        "ate_default_test": mean_ate(default_params(), test), "ate_learned_test": mean_ate(params, test),
        "grad_fd_rel_err": rel, "grad_directional": analytic, "fd_directional": fd,
        "step_s": float(np.mean(step_times)) if step_times else float("nan"), **readable(params),
    }
    print("\nATE (m, Sim(3)-aligned camera centres), mean over scenes:\n")
    print(f"{'split':>9} | {'prior':>9} {'default':>9} {'learned':>9} | learned vs default")
    for split in ("train", "val", "test"):
        p, d, lrn = (figures[f"ate_{k}_{split}"] for k in ("prior", "default", "learned"))
        print(f"{split:>9} | {p:>9.5f} {d:>9.5f} {lrn:>9.5f} | {100 * (lrn - d) / d:+.1f} %")
    print("\nlearned weights (best validation step, marked *): " + ", ".join(f"{n} {figures[n]:.4g}" for n in PARAM_NAMES))
    print(f"gradient check (random direction, default weights): implicit {analytic:.6e}, "
          f"central FD {fd:.6e}, rel err {rel:.1e}")
    print(f"one training step (forward + implicit backward over {n_train} problems): {figures['step_s']:.2f} s")
    if args.json:
        write_json(args.json, figures)


if __name__ == "__main__":
    main()
