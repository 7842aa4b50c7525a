"""Options and result of the Levenberg–Marquardt solver (:mod:`cm3d.solvers.lm`)."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
from flax import struct

from cm3d.solvers.factors import Variables

LINEAR_SOLVERS = ("auto", "dense", "pcg")
BATCHINGS = ("auto", "sequential", "native")
BACKWARDS = ("implicit", "unrolled", "none")
STOP_REASONS = ("running", "relative/absolute decrease", "gradient tolerance", "small cost change",
                "lambda upper bound", "max iterations", "non-finite initial point",
                "pair capacity too small: raise LMOptions.pair_capacity (schur_pair_count gives the need)")
PAIR_OVERFLOW = 7  # stop reason: the graph has more landmark observation pairs than the capacity


@dataclasses.dataclass(frozen=True)
class LMOptions:
    """Options (all static). Defaults are GTSAM's ``LevenbergMarquardtParams``.

    max_iterations: outer iterations (accepted steps); max_linear_solves: cap on trials (each a
    damped solve); rel_tol / abs_tol: GTSAM's relative/absolute error decrease tolerances;
    grad_tol: also stop when the Jacobi-scaled gradient ``max_i |g_i| / sqrt(H_ii)`` is at most
    ``grad_tol`` (0 disables); lambda_*: initial value, multiplicative factor and bounds of the
    damping; min_model_fidelity: accept a step when actual/predicted decrease exceeds it.
    linear_solver: "dense", "pcg" or "auto" (dense up to ``dense_max_poses`` pose slots);
    pcg_max_iterations / pcg_tol: inner CG of "pcg"; pair_capacity: static number of landmark
    observation pairs of the dense Schur assembly (``None``: 8 per observation; see
    :func:`schur_pair_count`); min_observations: landmarks with fewer are frozen. backward:
    "implicit", "unrolled" or "none"; unroll_steps: trials of the unrolled mode;
    implicit_cg_iterations / implicit_cg_tol: adjoint (and Newton) solves; implicit_damping: of their
    Gauss–Newton preconditioner; newton_steps: exact-Newton steps after LM (implicit gradients need a
    tight optimum). batching: "native" batches every operation under ``vmap``, "sequential" maps the
    problems one after another (docs/factor_graph.md), "auto": sequential on CPU.
    """

    max_iterations: int = 100
    max_linear_solves: int = 300
    rel_tol: float = 1e-5
    abs_tol: float = 1e-5
    grad_tol: float = 0.0
    lambda_init: float = 1e-5
    lambda_factor: float = 10.0
    lambda_min: float = 0.0
    lambda_max: float = 1e5
    min_model_fidelity: float = 1e-3
    linear_solver: str = "auto"
    dense_max_poses: int = 512
    pcg_max_iterations: int = 300
    pcg_tol: float = 1e-10
    pair_capacity: int | None = None
    min_observations: int = 2
    backward: str = "implicit"
    unroll_steps: int = 10
    implicit_cg_iterations: int = 8
    implicit_cg_tol: float = 1e-8
    implicit_damping: float = 1e-9
    newton_steps: int = 0
    batching: str = "auto"

    def __post_init__(self):
        if self.linear_solver not in LINEAR_SOLVERS:
            raise ValueError(f"LMOptions.linear_solver: unknown {self.linear_solver!r} {LINEAR_SOLVERS}")
        if self.batching not in BATCHINGS:
            raise ValueError(f"LMOptions.batching: unknown {self.batching!r} {BATCHINGS}")
        if self.backward not in BACKWARDS:
            raise ValueError(f"LMOptions.backward: unknown {self.backward!r} {BACKWARDS}")
        if self.max_iterations < 1 or self.max_linear_solves < 1 or self.unroll_steps < 1:
            raise ValueError("LMOptions: max_iterations, max_linear_solves, unroll_steps must be >= 1")
        if not (self.lambda_init > 0 and self.lambda_factor > 1 and self.lambda_max > self.lambda_init):
            raise ValueError("LMOptions: need lambda_init > 0, lambda_factor > 1, lambda_max > lambda_init")
        if self.pair_capacity is not None and self.pair_capacity < 1:
            raise ValueError("LMOptions.pair_capacity: must be >= 1 (or None)")
        if self.newton_steps < 0:
            raise ValueError("LMOptions.newton_steps: must be >= 0")
        if self.min_observations < 1:
            raise ValueError("LMOptions.min_observations: must be >= 1")


#: Options for a forward solve whose implicit gradient is accurate: stop on the gradient norm.
IMPLICIT_OPTIONS = LMOptions(rel_tol=1e-10, abs_tol=0.0, grad_tol=1e-8, max_iterations=100,
                             max_linear_solves=200, newton_steps=3)


@struct.dataclass
class LMResult:
    """Solver output. params: optimum (poses re-orthonormalised by SVD); cost: final objective;
    initial_cost; iterations: accepted steps (GTSAM's outer iterations); linear_solves: damped
    solves tried; converged: a tolerance was met; stop_reason: index into :data:`STOP_REASONS`;
    grad_norm: Jacobi-scaled gradient ``max |g_i|/sqrt(H_ii)`` at the optimum; lambda_: final damping; cost_history:
    (max_iterations + 1,) cost after each accepted step (last value repeated)."""

    params: Variables
    cost: jnp.ndarray
    initial_cost: jnp.ndarray
    iterations: jnp.ndarray
    linear_solves: jnp.ndarray
    converged: jnp.ndarray
    stop_reason: jnp.ndarray
    grad_norm: jnp.ndarray
    lambda_: jnp.ndarray
    cost_history: jnp.ndarray



def use_dense(num_poses: int, options: LMOptions) -> bool:
    """Whether the reduced camera system is factored densely (else matrix-free PCG)."""
    if options.linear_solver == "auto":
        return num_poses <= options.dense_max_poses
    return options.linear_solver == "dense"
