"""Levenberg–Marquardt for bundle-adjustment-shaped factor graphs, in pure JAX (:func:`solve`).

Poses on SE(3) (cam_to_world, ``T ← T exp(δ)``, jaxlie order), landmarks in R³ (``L ← L + δ``),
factors of :mod:`cm3d.solvers.factors`. Each trial solves the damped normal equations by the Schur
complement (:mod:`~cm3d.solvers.schur`); λ schedule, acceptance and stopping are GTSAM's
``LevenbergMarquardtOptimizer`` defaults. One ``lax.while_loop`` with fixed capacities: compiles
once, ``vmap``-able. Optional exact-Newton polish (``newton_steps``): IRLS converges only linearly
with Huber outliers. Gradients: ``LMOptions.backward`` (``"implicit"``, ``"unrolled"``, ``"none"``).
Variables no factor determines (landmarks under ``min_observations``, poses without factors,
``graph.pose_fixed``) are frozen (δ = 0) instead of producing NaN.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from flax import struct
from jax.custom_batching import custom_vmap

from cm3d.solvers.factors import FactorGraph, Variables, orthonormalize_poses
from cm3d.solvers.lm_options import (  # noqa: F401
    BACKWARDS, BATCHINGS, IMPLICIT_OPTIONS, LINEAR_SOLVERS, PAIR_OVERFLOW, STOP_REASONS, LMOptions, LMResult,
    use_dense
)
from cm3d.solvers.newton import exact_newton_solve, implicit_bwd, newton_damping
from cm3d.solvers.normal_equations import (  # noqa: F401
    Linearization, Structure, gradient, linearize, linearized_error, retract, schur_pair_count, structure
)
from cm3d.solvers.schur import SchurSystem, damped_step, factor_dense, schur_solve

# The LM loop
#
# One loop body evaluates the pending candidate (linearise, accept or reject, update λ) and then
# proposes the next one (damped Schur step, or an exact-Newton step in the polish phase), so the
# linearisation and the factorisation each appear once in the compiled program.


@struct.dataclass
class _State:
    x: Variables
    lin: Linearization
    cand: Variables
    pred: jnp.ndarray  # predicted (linearised) decrease of the candidate
    cand_newton: jnp.ndarray  # the candidate is a Newton-polish step
    first: jnp.ndarray  # the candidate is the initial point
    pending: jnp.ndarray
    lam: jnp.ndarray
    iterations: jnp.ndarray
    solves: jnp.ndarray
    newton: jnp.ndarray
    reason: jnp.ndarray
    initial_cost: jnp.ndarray
    history: jnp.ndarray
    sys: SchurSystem | None  # the last Newton factorisation (newton_steps > 0): reused by the adjoint


def _grad_scaled(lin: Linearization):
    """``max_i |g_i| / sqrt(H_ii)``: the Jacobi-scaled gradient (units of sqrt(cost), invariant to
    the variables' units); ``g_i² / 2 H_ii`` is the decrease a step along coordinate ``i`` offers."""
    hp = jnp.diagonal(lin.H_pose, axis1=-2, axis2=-1)
    hl = jnp.diagonal(lin.H_point, axis1=-2, axis2=-1)
    sp = jnp.abs(lin.g_pose) * jax.lax.rsqrt(jnp.maximum(hp, 1e-300))
    sl = jnp.abs(lin.g_point) * jax.lax.rsqrt(jnp.maximum(hl, 1e-300))
    sp = jnp.where(hp > 0, sp, 0.0)
    sl = jnp.where(hl > 0, sl, 0.0)
    return jnp.maximum(jnp.max(sp, initial=0.0), jnp.max(sl, initial=0.0))


def _evaluate(graph, st, options, s: _State, differentiable) -> _State:
    """Linearise at the candidate; GTSAM's acceptance test and λ update (or Newton's)."""
    lin, dt = s.lin, s.lam.dtype
    lin_c = linearize(graph, s.cand, st, differentiable)
    finite = jnp.isfinite(lin_c.cost) & jnp.all(jnp.isfinite(s.cand.poses)) & jnp.all(jnp.isfinite(s.cand.points))
    cost_change = lin.cost - lin_c.cost
    # Levenberg-Marquardt (GTSAM LevenbergMarquardtOptimizer::tryLambda)
    valid = finite & (s.pred >= 0)
    measurable = s.pred > jnp.finfo(dt).eps * lin.lin_err
    fidelity = cost_change / jnp.where(measurable, s.pred, 1.0)
    success = valid & measurable & (fidelity > options.min_model_fidelity)
    small = valid & (jnp.abs(cost_change) < options.rel_tol * lin.cost)
    rel = cost_change / jnp.where(lin.cost != 0, lin.cost, 1.0)
    conv = (rel < options.rel_tol) | (cost_change < options.abs_tol)
    grad_ok = _grad_scaled(lin_c) <= options.grad_tol
    lam_up = s.lam * options.lambda_factor
    it = s.iterations + success.astype(jnp.int32)
    reason = jnp.where(success & grad_ok, 2, jnp.where(success & conv, 1, 0))
    reason = jnp.where(~success & small, 3, reason)
    reason = jnp.where(~success & ~small & (lam_up >= options.lambda_max), 4, reason)
    lam = jnp.where(success, jnp.maximum(options.lambda_min, s.lam / options.lambda_factor),
                    jnp.where(small, s.lam, lam_up))
    # Newton polish: accept when the cost does not rise (beyond round-off) and the gradient shrinks
    tiny = 1e-12 * jnp.abs(lin.cost)
    better = finite & ((lin_c.cost < lin.cost)
                       | ((lin_c.cost <= lin.cost + tiny) & (_grad_scaled(lin_c) < _grad_scaled(lin))))
    accept = jnp.where(s.first, finite, jnp.where(s.cand_newton, better, success))
    first_reason = jnp.where(finite, jnp.where(_grad_scaled(lin_c) <= options.grad_tol, 2, 0), 6)
    reason = jnp.where(s.first, first_reason,
                       jnp.where(s.cand_newton, jnp.where(better & grad_ok, 2, s.reason), reason))
    lm_trial = ~s.first & ~s.cand_newton
    it = jnp.where(lm_trial, it, s.iterations)
    lam = jnp.where(lm_trial, lam, s.lam)
    hidx = jnp.minimum(it, s.history.shape[0] - 1)
    history = s.history.at[hidx].set(jnp.where(lm_trial & success, lin_c.cost, s.history[hidx]))
    history = jnp.where(s.first, jnp.full_like(history, lin_c.cost), history)
    pick = lambda a, b: jax.tree.map(lambda u, v: jnp.where(accept, u, v), a, b)  # noqa: E731
    return s.replace(x=pick(s.cand, s.x), lin=pick(lin_c, lin), lam=lam.astype(dt), iterations=it,
                     solves=s.solves + (~s.first).astype(jnp.int32),
                     newton=s.newton + s.cand_newton.astype(jnp.int32),
                     reason=reason.astype(jnp.int32),
                     initial_cost=jnp.where(s.first, lin_c.cost, s.initial_cost), history=history,
                     first=jnp.zeros_like(s.first))


def _propose(graph, st, options, s: _State, newton, differentiable):
    """The next candidate: a damped Schur step, or (``newton``) an exact-Newton step."""
    lin = s.lin
    N = lin.H_pose.shape[0]
    sys = None
    if options.newton_steps and not differentiable:
        sys = factor_dense(graph, lin, st, jnp.where(newton, newton_damping(lin, options), s.lam))

        def lm_step():
            if use_dense(N, options):
                return schur_solve(graph, st, sys, lin.g_pose, lin.g_point)
            return damped_step(graph, lin, st, s.lam, options)

        def newton_step():
            return exact_newton_solve(graph, st, s.x, sys, (-lin.g_pose, -lin.g_point), options)

        dp, dl = jax.lax.cond(newton, newton_step, lm_step)
    else:
        dp, dl = damped_step(graph, lin, st, s.lam, options, differentiable)
    finite = jnp.all(jnp.isfinite(dp)) & jnp.all(jnp.isfinite(dl))
    dp, dl = jnp.where(finite, dp, 0.0), jnp.where(finite, dl, 0.0)
    pred = jnp.where(finite, lin.lin_err - linearized_error(graph, lin, dp, dl), -1.0)
    return retract(s.x, dp, dl), pred.astype(s.lam.dtype), sys


def _overflow(st: Structure):
    return st.pair_count > st.pair_k1.shape[0]


def _body(graph, st, options, s: _State, differentiable: bool) -> _State:
    s = _evaluate(graph, st, options, s, differentiable)
    ok = ~_overflow(st)  # incomplete Schur pairs: evaluate the initial point, take no step
    lm_running = ok & (s.reason == 0) & (s.solves < options.max_linear_solves) & (s.iterations < options.max_iterations)
    polish = ok & (~lm_running) & (s.newton < options.newton_steps) & (_grad_scaled(s.lin) > options.grad_tol)
    propose = lm_running | polish
    if differentiable:
        cand, pred, sys = _propose(graph, st, options, s, polish, differentiable)
    else:
        cand, pred, sys = jax.lax.cond(propose, lambda: _propose(graph, st, options, s, polish, False),
                                       lambda: (s.x, jnp.zeros_like(s.lam), s.sys))
    return s.replace(cand=cand, pred=pred, cand_newton=polish, pending=propose, sys=sys)


def _start(graph, init: Variables, st, options) -> _State:
    """A state whose pending candidate is the initial point (evaluated by the first body)."""
    dt = init.points.dtype
    N, M = init.poses.shape[0], init.points.shape[0]
    zeros = lambda tree: jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), tree)  # noqa: E731
    lin0 = zeros(jax.eval_shape(lambda: linearize(graph, init, st)))
    sys0 = None
    if options.newton_steps:
        sys0 = zeros(jax.eval_shape(lambda: factor_dense(graph, lin0, st, jnp.ones((), dt))))
    z = jnp.zeros((), jnp.int32)
    return _State(x=init, lin=lin0, cand=init, pred=jnp.zeros((), dt), cand_newton=jnp.zeros((), bool),
                  first=jnp.ones((), bool), pending=jnp.ones((), bool),
                  lam=jnp.asarray(options.lambda_init, dt), iterations=z, solves=z, newton=z, reason=z,
                  initial_cost=jnp.zeros((), dt), history=jnp.zeros((options.max_iterations + 1,), dt),
                  sys=sys0)


def _finish(s: _State, options, st: Structure) -> LMResult:
    idx = jnp.arange(s.history.shape[0])
    hist = jnp.where(idx <= s.iterations, s.history, s.lin.cost)
    reason = jnp.where(_grad_scaled(s.lin) <= options.grad_tol, 2, s.reason)
    reason = jnp.where(reason == 0, 5, reason)
    reason = jnp.where(_overflow(st), PAIR_OVERFLOW, reason)
    params = Variables(poses=orthonormalize_poses(s.x.poses), points=s.x.points)
    return LMResult(params=params, cost=s.lin.cost, initial_cost=s.initial_cost, iterations=s.iterations,
                    linear_solves=s.solves, converged=(reason >= 1) & (reason <= 3),
                    stop_reason=reason, grad_norm=_grad_scaled(s.lin), lambda_=s.lam, cost_history=hist)


def _prepare(graph, init, options, differentiable=False):
    M = init.points.shape[0]
    pairs = use_dense(init.poses.shape[0], options) or (options.newton_steps > 0 and not differentiable)
    return structure(graph, M, options, with_pairs=pairs)


def _run(graph: FactorGraph, init: Variables, options: LMOptions):
    st = _prepare(graph, init, options)
    s = jax.lax.while_loop(lambda s: s.pending, lambda s: _body(graph, st, options, s, False),
                           _start(graph, init, st, options))
    return _finish(s, options, st), s, st


def _sequential_batching(options: LMOptions) -> bool:
    if options.batching == "auto":
        return jax.default_backend() == "cpu"
    return options.batching == "sequential"


@functools.lru_cache(maxsize=None)
def _batchable_run(options: LMOptions):
    """``_run`` (result, last factorisation, structure) with a ``vmap`` rule that maps the batch
    sequentially (``lax.map``) instead of batching every operation."""

    @custom_vmap
    def run(graph, init):
        res, s, st = _run(graph, init, options)
        return res, s.sys, st

    @run.def_vmap
    def _rule(axis_size, in_batched, graph, init):
        args = jax.tree.map(lambda a, b: a if b else jnp.broadcast_to(a, (axis_size,) + a.shape),
                            (graph, init), tuple(in_batched))
        out = jax.lax.map(lambda gi: run(*gi), args)
        return out, jax.tree.map(lambda _: True, out)

    return run


def _run_batchable(graph, init, options):
    if _sequential_batching(options):
        return _batchable_run(options)(graph, init)
    res, s, st = _run(graph, init, options)
    return res, s.sys, st


def _solve_unrolled(graph: FactorGraph, init: Variables, options: LMOptions) -> LMResult:
    st = _prepare(graph, init, options, differentiable=True)

    @jax.checkpoint
    def body(s, _):
        new = _body(graph, st, options, s, True)
        return jax.tree.map(lambda a, b: jnp.where(s.pending, a, b), new, s), None

    s, _ = jax.lax.scan(body, _start(graph, init, st, options), None, length=options.unroll_steps + 1)
    return _finish(s, options, st)


# Implicit differentiation


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _solve_implicit(options, graph, init):
    return _run_batchable(graph, init, options)[0]


def _implicit_fwd(options, graph, init):
    res, sys, st = _run_batchable(graph, init, options)
    return res, (graph, res.params, init, sys, st)


_solve_implicit.defvjp(_implicit_fwd, implicit_bwd)


# Public entry point


def solve(graph: FactorGraph, init: Variables, options: LMOptions = LMOptions()) -> LMResult:
    """Minimise the factor graph's objective from ``init`` -> :class:`LMResult`.

    graph: :class:`~cm3d.solvers.factors.FactorGraph`; init: :class:`~cm3d.solvers.factors.Variables`
    (poses (N, 4, 4), points (M, 3)). Jittable (``options`` static), ``vmap``-able over equal
    capacities; gradients w.r.t. the graph's float leaves follow ``options.backward``.
    """
    if options.backward == "implicit":
        return _solve_implicit(options, graph, init)
    if options.backward == "unrolled":
        return _solve_unrolled(graph, init, options)
    return _run_batchable(graph, init, options)[0]


solve_jit = jax.jit(solve, static_argnames=("options",))
