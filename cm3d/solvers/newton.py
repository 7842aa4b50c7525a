"""Exact-Newton solves in the tangent space at an optimum, and the implicit-gradient adjoint.
Why the exact Hessian: the Gauss–Newton one alone gives wrong gradients (weak gauge/scale directions)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from cm3d.solvers.factors import total_cost
from cm3d.solvers.lm_options import LMOptions, LMResult
from cm3d.solvers.normal_equations import gradient, linearize, retract, structure
from cm3d.solvers.schur import SchurSystem, factor_dense, pcg, schur_solve

def _tangent_cost(graph, xstar, st, dp, dl):
    x = retract(xstar, dp, dl)
    return total_cost(graph, x, st.obs_active)


def newton_damping(lin, options):
    mean_diag = jnp.mean(jnp.diagonal(lin.H_pose, axis1=-2, axis2=-1))
    return options.implicit_damping * jnp.maximum(mean_diag, 1.0)


def exact_newton_solve(graph, st, x, sys: SchurSystem, v, options: LMOptions):
    """``H^{-1} v`` for the exact Hessian ``H`` of the objective in the tangent space at ``x``: CG on
    Hessian-vector products (forward-mode derivative of the analytic gradient), preconditioned by the
    Gauss–Newton Schur factorisation ``sys``. Inactive variables stay 0. ``H v`` omits the
    retraction's curvature term, which vanishes at the optimum where it is used."""
    N, M = x.poses.shape[0], x.points.shape[0]
    dt = x.points.dtype
    pa = st.pose_active[:, None].astype(dt)
    la = st.point_active[:, None].astype(dt)
    zp, zl = jnp.zeros((N, 6), dt), jnp.zeros((M, 3), dt)

    def grad_at(dp, dl):
        return gradient(graph, retract(x, dp, dl), st)

    def hvp(u):
        _, (hp, hl) = jax.jvp(grad_at, (zp, zl), (u[0] * pa, u[1] * la))
        return (hp * pa, hl * la)

    def precond(r):
        return schur_solve(graph, st, sys, -r[0], -r[1])

    return _pcg_tree(hvp, precond, (v[0] * pa, v[1] * la), options.implicit_cg_iterations,
                     options.implicit_cg_tol)[0]



def implicit_bwd(options: LMOptions, saved, ct: LMResult):
    """IFT at the optimum: ``θ̄ = −(∂g/∂θ)^T H^{-1} x̄`` with the exact Hessian ``H``, solved by CG
    preconditioned by the forward pass's last (Newton) Gauss–Newton factorisation."""
    graph, xstar, init, sys, st = saved
    N, M = xstar.poses.shape[0], xstar.points.shape[0]
    dt = xstar.points.dtype
    if sys is None or not st.pair_k1.shape[0] > 1:
        st = structure(graph, M, options, with_pairs=True)
        lin = linearize(graph, xstar, st)
        sys = factor_dense(graph, lin, st, newton_damping(lin, options))
    zp, zl = jnp.zeros((N, 6), dt), jnp.zeros((M, 3), dt)

    # cotangent of the outputs -> cotangent in the tangent space at x*
    _, vjp_retract = jax.vjp(lambda dp, dl: retract(xstar, dp, dl), zp, zl)
    ct_params = jax.tree.map(lambda c, p: jnp.zeros_like(p) if c.dtype == jax.dtypes.float0 else c,
                             ct.params, xstar)
    gp, gl = vjp_retract(ct_params)

    u = exact_newton_solve(graph, st, xstar, sys, (gp, gl), options)
    ct_cost = ct.cost if ct.cost.dtype != jax.dtypes.float0 else jnp.zeros((), dt)

    def scalar(g):
        _, d = jax.jvp(lambda dp, dl: _tangent_cost(g, xstar, st, dp, dl), (zp, zl), (u[0], u[1]))
        return -d + ct_cost * total_cost(g, xstar, st.obs_active)

    _, vjp_graph = jax.vjp(scalar, graph)
    (ct_graph,) = vjp_graph(jnp.ones((), dt))
    ct_init = jax.tree.map(jnp.zeros_like, init)
    return ct_graph, ct_init


def _pcg_tree(matvec, precond, b, max_iterations, tol):
    """:func:`pcg` on a tuple of arrays (flattened)."""
    shapes = [a.shape for a in b]
    sizes = [a.size for a in b]

    def flat(t):
        return jnp.concatenate([a.reshape(-1) for a in t])

    def unflat(v):
        out, o = [], 0
        for sh, n in zip(shapes, sizes):
            out.append(v[o:o + n].reshape(sh))
            o += n
        return tuple(out)

    x, it = pcg(lambda v: flat(matvec(unflat(v))), lambda r: flat(precond(unflat(r))), flat(b),
                max_iterations, tol)
    return unflat(x), it
