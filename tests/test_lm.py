"""Levenberg–Marquardt with the Schur complement: against GTSAM, gradients against finite differences."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cm3d.ops import se3
from cm3d.solvers import factors, lm
from cm3d.solvers.factors import Variables

# compile fast (LLVM -O0): these programs run on tiny problems, compile time dominates
FAST = {"xla_backend_optimization_level": 0}

N, M = 6, 40
SOLVE = jax.jit(lm.solve, static_argnames="options", compiler_options=FAST)
OPTS = lm.LMOptions(backward="none", pair_capacity=400)


def _problem(seed, outlier_frac=0.08, **kw):
    return factors.random_problem(seed, N, M, obs_per_point=4, outlier_frac=outlier_frac,
                                  pose_noise=0.03, point_noise=0.1, **kw)


@pytest.fixture(scope="module")
def problem():
    with jax.enable_x64(True):
        yield _problem(0)


def _with_weights(graph, weight):
    return graph.replace(projection=graph.projection.replace(weight=jnp.asarray(weight, jnp.float64)))


def test_matches_gtsam_optimum_and_cost_history(problem):
    import gtsam  # noqa: F401  (a test dependency: fail loudly if missing)
    from cm3d import baselines

    graph, init, _ = problem
    with jax.enable_x64(True):
        r = SOLVE(graph, init, OPTS)
    ref = baselines.gtsam_solve(graph, init, history=True)
    assert bool(r.converged)
    assert float(r.cost) == pytest.approx(ref.cost, rel=1e-9)
    assert float(r.initial_cost) == pytest.approx(ref.initial_cost, rel=1e-12)
    assert int(r.iterations) == ref.iterations
    hist = np.asarray(r.cost_history)[: int(r.iterations) + 1]
    np.testing.assert_allclose(hist, ref.history, rtol=1e-8)
    np.testing.assert_allclose(r.params.poses, ref.poses, atol=1e-7)
    np.testing.assert_allclose(r.params.points, ref.points, atol=1e-6)
    R = np.asarray(r.params.poses[:, :3, :3])
    np.testing.assert_allclose(np.swapaxes(R, 1, 2) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-14)


def test_gauge_fixed_by_the_prior(problem):
    graph, init, _ = problem
    with jax.enable_x64(True):
        G = se3.exp(jnp.array([0.3, -0.2, 0.1, 0.05, 0.1, -0.08]))
        moved = Variables(G @ init.poses, (init.points @ G[:3, :3].T) + G[:3, 3])
        a = SOLVE(graph, init, OPTS)
        b = SOLVE(graph, moved, OPTS)
    # the prior pins pose 0 to its target; both starts reach the same optimum (up to the
    # 1e-5 relative-decrease stopping rule)
    np.testing.assert_allclose(a.params.poses[0], graph.prior.target[0], atol=1e-5)
    np.testing.assert_allclose(b.params.poses[0], graph.prior.target[0], atol=1e-5)
    np.testing.assert_allclose(b.params.poses, a.params.poses, atol=1e-3)
    assert float(b.cost) == pytest.approx(float(a.cost), rel=1e-5)


def test_huber_downweights_planted_outliers():
    with jax.enable_x64(True):
        graph, init, truth = _problem(1, outlier_frac=0.15)
        huber = SOLVE(graph, init, OPTS)
        l2 = SOLVE(graph.replace(huber_k=jnp.full((), jnp.inf, jnp.float64)), init, OPTS)
        def err(r):
            d = r.params.poses[:, :3, 3] - truth.poses[:, :3, 3]
            return float(jnp.sqrt(jnp.mean(jnp.sum(d * d, -1))))
        assert err(huber) < 0.5 * err(l2)
        # the final IRLS weights of the gross outliers are small
        st = lm.structure(graph, M, OPTS, with_pairs=False)
        lin = jax.jit(lm.linearize, compiler_options=FAST)(graph, huber.params, st)
        gross = np.asarray(factors.reprojection_errors(graph, truth)) > 8
        assert np.asarray(lin.w)[gross].mean() < 0.15
        assert np.asarray(lin.w)[~gross].mean() > 0.9


def test_degenerate_inputs_give_finite_results(problem):
    graph, init, _ = problem
    f = graph.projection
    w = np.ones(f.weight.shape)
    pid, lid = np.asarray(f.pose_idx), np.asarray(f.point_idx)
    once = w.copy()
    once[np.flatnonzero(lid == 0)[1:]] = 0  # landmark 0 seen once
    empty = w.copy()
    empty[pid == 3] = 0  # frame 3 without observations
    with jax.enable_x64(True):
        for weights in (once, empty, np.zeros_like(w)):
            r = SOLVE(_with_weights(graph, weights), init, OPTS)
            assert np.all(np.isfinite(np.asarray(r.params.poses)))
            assert np.all(np.isfinite(np.asarray(r.params.points)))
            assert np.isfinite(float(r.cost)) and bool(r.converged)
        r = SOLVE(_with_weights(graph, once), init, OPTS)
        np.testing.assert_allclose(r.params.points[0], init.points[0])  # frozen, not NaN
        # every observation rejected: only prior and motion factors, which the initial poses satisfy
        r = SOLVE(_with_weights(graph, np.zeros_like(w)), init, OPTS)
        np.testing.assert_allclose(r.params.poses, init.poses, atol=1e-12)
        assert float(r.cost) == pytest.approx(0.0, abs=1e-20)
        # a pose slot with no factor at all (padding) stays where it is
        g = _with_weights(graph, empty)
        g = g.replace(motion=g.motion.replace(weight=g.motion.weight.at[2:4].set(0.0)))
        r = SOLVE(g, init, OPTS)
        np.testing.assert_allclose(r.params.poses[3], init.poses[3], atol=1e-12)
        assert np.all(np.isfinite(np.asarray(r.params.poses)))


def test_vmap_and_jit_invariance_and_pcg_solver(problem):
    """vmap of the solver over two problems (with the matrix-free PCG reduced solver) equals the
    jitted single (dense) solves."""
    with jax.enable_x64(True):
        probs = [problem[:2], _problem(5)[:2]]
        single = [SOLVE(g, x, OPTS) for g, x in probs]
        stacked = jax.tree.map(lambda *a: jnp.stack(a), *probs)
        popts = dataclasses.replace(OPTS, linear_solver="pcg", pcg_tol=1e-12)
        batched = jax.jit(jax.vmap(lambda g, x: lm.solve(g, x, popts)), compiler_options=FAST)(*stacked)
    for i, r in enumerate(single):
        assert float(batched.cost[i]) == pytest.approx(float(r.cost), rel=1e-9)
        assert int(batched.iterations[i]) == int(r.iterations)
        np.testing.assert_allclose(batched.params.poses[i], r.params.poses, atol=1e-7)


def _loss_factory(problem, options):
    graph, init, _ = problem
    memory = jnp.arange(graph.projection.z.shape[0]) % 3 == 0
    f = graph.projection
    w = jnp.arange(1, N + 1, dtype=jnp.float64)[:, None]

    def loss(theta):
        poses0 = init.poses @ se3.exp(theta["xi"])
        g = factors.build_graph(poses0, graph.intrinsics, f.pose_idx, f.point_idx, theta["z"], f.weight,
                                memory=memory)
        g = g.replace(projection=g.projection.replace(sigma=theta["sigma"]), huber_k=theta["huber_k"],
                      memory_alpha=theta["alpha"])
        r = lm.solve(g, Variables(poses0, init.points), options)
        return jnp.sum(r.params.poses[:, :3, 3] * w) + jnp.sum(r.params.points[:4]) + 1e-3 * r.cost

    theta = {"xi": jnp.zeros((N, 6), jnp.float64), "z": f.z, "sigma": f.sigma,
             "huber_k": jnp.asarray(2.0, jnp.float64), "alpha": jnp.asarray(0.5, jnp.float64)}
    return jax.jit(jax.value_and_grad(loss), compiler_options=FAST), theta


def _directional_check(vg, theta, seed, eps):
    rng = np.random.default_rng(seed)
    d = jax.tree.map(lambda a: jnp.asarray(rng.normal(size=a.shape)), theta)
    d["sigma"] = d["sigma"] * 0.05
    _, g = vg(theta)
    analytic = sum(float(jnp.sum(a * b)) for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(d)))
    plus = vg(jax.tree.map(lambda a, b: a + eps * b, theta, d))[0]
    minus = vg(jax.tree.map(lambda a, b: a - eps * b, theta, d))[0]
    return analytic, float(plus - minus) / (2 * eps), g


def test_implicit_gradient_matches_finite_differences(problem):
    with jax.enable_x64(True):
        opts = dataclasses.replace(lm.IMPLICIT_OPTIONS, pair_capacity=400)
        vg, theta = _loss_factory(problem, opts)
        analytic, fd, g = _directional_check(vg, theta, 0, 1e-5)
    assert analytic == pytest.approx(fd, rel=1e-2)
    for leaf in jax.tree.leaves(g):
        assert np.all(np.isfinite(np.asarray(leaf)))
    assert float(jnp.abs(g["huber_k"])) > 0 and float(jnp.abs(g["alpha"])) > 0


def test_unrolled_gradient_matches_finite_differences(problem):
    with jax.enable_x64(True):
        opts = lm.LMOptions(backward="unrolled", unroll_steps=6, pair_capacity=400)
        vg, theta = _loss_factory(problem, opts)
        analytic, fd, _ = _directional_check(vg, theta, 1, 1e-6)
    assert analytic == pytest.approx(fd, rel=1e-3)


def test_bad_options_and_capacity_raise(problem):
    with pytest.raises(ValueError, match="linear_solver"):
        lm.LMOptions(linear_solver="qr")
    with pytest.raises(ValueError, match="backward"):
        lm.LMOptions(backward="adjoint")
    graph, init, _ = problem
    with jax.enable_x64(True):
        need = lm.schur_pair_count(graph, M)
        lid = np.asarray(graph.projection.point_idx)
        n = np.bincount(lid, minlength=M)
        assert need == int(np.sum(n * (n - 1) // 2))
        small = dataclasses.replace(OPTS, pair_capacity=need - 1)
        st = jax.jit(lambda g: lm.structure(g, M, small), compiler_options=FAST)(graph)
        assert int(st.pair_count) == need > st.pair_k1.shape[0]  # the overflow is visible
        res = lm.solve_jit(graph, init, small)  # ... and the solver refuses to step, saying why
        assert int(res.stop_reason) == lm.PAIR_OVERFLOW and not bool(res.converged)
        assert "pair_capacity" in lm.STOP_REASONS[lm.PAIR_OVERFLOW]
        np.testing.assert_allclose(res.params.points, init.points)
