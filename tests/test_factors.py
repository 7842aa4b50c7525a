"""Factors of the paper's graph: Jacobians against finite differences, costs against GTSAM."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cm3d.ops import se3
from cm3d.solvers import factors
from cm3d.solvers.factors import GraphConfig, Variables

# compile fast (LLVM -O0): these programs run on tiny problems, compile time dominates
FAST = {"xla_backend_optimization_level": 0}


@pytest.fixture(scope="module")
def problem():
    with jax.enable_x64(True):
        graph, init, truth = factors.random_problem(3, 6, 40, obs_per_point=4, pose_noise=0.05,
                                                    outlier_frac=0.1)
        # motion/prior residuals away from zero
        poses = init.poses @ se3.exp(jnp.asarray(np.random.default_rng(0).normal(0, 0.05, (6, 6))))
        yield graph, Variables(poses, init.points), truth


def _with_depth(graph, truth):
    """The problem's graph with measured depths: the true camera z times 2 % log-normal noise on
    three quarters of the observations (0 = none on the rest), some memory-scaled."""
    f = graph.projection
    rng = np.random.default_rng(2)
    _, z = factors.project(truth.poses[f.pose_idx], truth.points[f.point_idx], graph.intrinsics[f.pose_idx])
    d = np.asarray(z) * np.exp(rng.normal(0, 0.02, z.shape)) * (rng.random(z.shape) < 0.75)
    mem = jnp.asarray(rng.random(z.shape) < 0.3)
    return graph.replace(projection=f.replace(depth=jnp.asarray(d), depth_sigma=jnp.full(z.shape, 0.02), memory=mem))


def _perturbed_residual(graph, x, dp, dl):
    x2 = Variables(x.poses @ se3.exp(dp), x.points + dl)
    e, _ = factors.projection_residual(graph, x2)
    return e


@pytest.mark.parametrize("depth", [False, True], ids=["pixels", "pixels+depth"])
def test_projection_jacobians_match_autodiff_and_finite_differences(problem, depth):
    graph, x, truth = problem
    with jax.enable_x64(True):
        if depth:
            graph = _with_depth(graph, truth)
        e, A, B, front = jax.jit(factors.projection_linearize, compiler_options=FAST)(graph, x)
        e_ref, _ = jax.jit(factors.projection_residual, compiler_options=FAST)(graph, x)
        np.testing.assert_allclose(e, e_ref, rtol=1e-12, atol=1e-12)
        N, M = x.poses.shape[0], x.points.shape[0]
        zp, zl = jnp.zeros((N, 6)), jnp.zeros((M, 3))
        Jp, Jl = jax.jit(jax.jacfwd(_perturbed_residual, (2, 3)), compiler_options=FAST)(graph, x, zp, zl)
        f = graph.projection
        k = jnp.arange(f.pose_idx.shape[0])
        np.testing.assert_allclose(A, Jp[k, :, f.pose_idx], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(B, Jl[k, :, f.point_idx], rtol=1e-9, atol=1e-9)
        # finite differences of the residual along random directions
        rng = np.random.default_rng(1)
        dp, dl = jnp.asarray(rng.normal(size=(N, 6))), jnp.asarray(rng.normal(size=(M, 3)))
        h = 1e-6
        res = jax.jit(_perturbed_residual, compiler_options=FAST)
        fd = (res(graph, x, h * dp, h * dl) - res(graph, x, -h * dp, -h * dl)) / (2 * h)
        lin = jnp.einsum("kri,ki->kr", A, dp[f.pose_idx]) + jnp.einsum("kri,ki->kr", B, dl[f.point_idx])
        np.testing.assert_allclose(lin, fd, rtol=1e-5, atol=1e-5)
        assert e.shape == (f.pose_idx.shape[0], 3 if depth else 2)
        if depth:  # the depth row against its definition
            _, z = factors.project(x.poses[f.pose_idx], x.points[f.point_idx], graph.intrinsics[f.pose_idx])
            sd = 0.02 * np.where(np.asarray(f.memory), np.sqrt(float(graph.memory_alpha)), 1.0)
            want = np.where(np.asarray(f.depth) > 0, (np.log(np.asarray(z)) - np.log(np.where(f.depth > 0, f.depth, 1.0))) / sd, 0.0)
            np.testing.assert_allclose(e[:, 2], want, rtol=1e-10, atol=1e-10)


def test_depth_factors_fix_the_scale_and_noise_estimate(problem):
    """With measured depths the solve recovers the depth's scale (the reprojection factors leave it
    free up to the weak motion factors); :func:`factors.calibrate_depth` recovers the 2 % noise and
    removes per-frame depth scales while keeping the frames' common one."""
    from cm3d.solvers import lm

    graph, x, truth = problem
    with jax.enable_x64(True):
        g = _with_depth(graph, truth)
        f = g.projection
        inl = f.weight > 0
        frame_scale = jnp.exp(jnp.asarray(np.random.default_rng(3).normal(0, 0.05, g.num_poses)))
        bad = g.replace(projection=f.replace(depth=f.depth * 1.3 * frame_scale[f.pose_idx]))
        cal = jax.jit(factors.calibrate_depth, static_argnums=3)(bad, truth, inl, 1e-4).projection
        # the reference in NumPy: per-frame low-median log ratio, centred on the frames' median;
        # sigma = max(white noise, the frames' scatter x sqrt(observations))
        _, z = factors.project(truth.poses[f.pose_idx], truth.points[f.point_idx], g.intrinsics[f.pose_idx])
        d, pi = np.asarray(bad.projection.depth), np.asarray(f.pose_idx)
        ok = np.asarray(inl) & (d > 0)
        r = np.where(ok, np.log(np.asarray(z)) - np.log(np.where(ok, d, 1.0)), 0.0)
        n = np.bincount(pi[ok], minlength=g.num_poses)
        sc = np.array([np.sort(r[ok & (pi == i)])[(n[i] - 1) // 2] for i in range(g.num_poses)])
        sc -= np.median(sc)
        white = 1.4826 * np.median(np.abs((r - sc[pi])[ok] - np.median((r - sc[pi])[ok])))
        assert 0.015 < white < 0.025, white  # the 2 % noise, with the frame scales removed
        frame = 1.4826 * np.median(np.abs(sc - np.median(sc))) * np.sqrt(n)
        np.testing.assert_allclose(cal.depth_sigma, np.maximum(white, frame)[pi], rtol=1e-6)
        assert np.all(np.asarray(cal.depth_sigma) > 0.05 * 2)  # 5 % frame scatter outweighs the noise
        np.testing.assert_allclose(cal.depth, d * np.exp(sc)[pi], rtol=1e-6)
        ratio = np.asarray(cal.depth / jnp.where(f.depth > 0, f.depth, 1.0))[np.asarray(f.depth) > 0]
        assert np.std(np.log(ratio)) < 0.01 and abs(np.median(ratio) - 1.3) < 0.05
        # start at 0.8x the true scale (about pose 0): the depths pull it back, pixels alone cannot
        c0 = truth.poses[0, :3, 3]
        small = Variables(truth.poses.at[:, :3, 3].set(c0 + 0.8 * (truth.poses[:, :3, 3] - c0)),
                          c0 + 0.8 * (truth.points - c0))
        g = g.replace(motion=g.motion.replace(weight=jnp.zeros_like(g.motion.weight)))
        opts = lm.LMOptions(backward="none", max_iterations=60)
        res = jax.jit(lambda g, x: lm.solve(g, x, opts), compiler_options=FAST)(g, small)
        d_true = np.linalg.norm(np.asarray(truth.poses[1:, :3, 3] - c0), axis=1)
        d_fit = np.linalg.norm(np.asarray(res.params.poses[1:, :3, 3] - res.params.poses[0, :3, 3]), axis=1)
        assert abs(np.median(d_fit / d_true) - 1.0) < 0.03


def test_pose_factor_jacobians_analytic_equal_autodiff_and_fd(problem):
    graph, x, _ = problem
    with jax.enable_x64(True):
        a = jax.jit(factors.pose_factor_jacobians, compiler_options=FAST)(graph, x.poses)
        autodiff = jax.jit(lambda g, p: factors.pose_factor_jacobians(g, p, "autodiff"), compiler_options=FAST)
        b = autodiff(graph, x.poses)
        for u, v in zip(a, b):
            np.testing.assert_allclose(u, v, rtol=1e-8, atol=1e-8)

        @functools.partial(jax.jit, compiler_options=FAST)
        def res(dp):
            return jnp.concatenate(factors.pose_residuals(graph, x.poses @ se3.exp(dp)), 0)

        e = res(jnp.zeros((x.poses.shape[0], 6)))
        np.testing.assert_allclose(a[0], e[:1], atol=1e-12)
        np.testing.assert_allclose(a[2], e[1:], atol=1e-12)
        # finite differences of the stacked Jacobians along a random tangent direction
        d = jnp.asarray(np.random.default_rng(2).normal(size=(x.poses.shape[0], 6)))
        h = 1e-6
        fd = (res(h * d) - res(-h * d)) / (2 * h)
        f = graph.motion
        lin_p = jnp.einsum("pij,pj->pi", a[1], d[graph.prior.pose_idx])
        lin_m = jnp.einsum("qij,qj->qi", a[3], d[f.idx_a]) + jnp.einsum("qij,qj->qi", a[4], d[f.idx_b])
        np.testing.assert_allclose(jnp.concatenate([lin_p, lin_m]), fd, rtol=1e-5, atol=1e-4)
        with pytest.raises(ValueError, match="unknown method"):
            factors.pose_factor_jacobians(graph, x.poses, "numeric")


def test_huber_matches_gtsam_mestimator():
    import gtsam
    k = 1.345
    h = gtsam.noiseModel.mEstimator.Huber.Create(k)
    with jax.enable_x64(True):
        for x in [0.0, 0.3, 1.345, 2.0, 17.0]:
            assert float(factors.huber_loss(jnp.asarray(x * x), k)) == pytest.approx(h.loss(x), rel=1e-12, abs=1e-15)
            if x > 0:
                assert float(factors.huber_weight(jnp.asarray(x * x), k)) == pytest.approx(h.weight(x), rel=1e-12)
        # finite, zero-safe gradients
        from jax.test_util import check_grads

        g = jax.grad(lambda s: factors.huber_loss(s, k))(jnp.asarray(0.0))
        assert np.isfinite(g)
        check_grads(lambda s: factors.huber_loss(s, k), (jnp.asarray(0.7),), order=2)
        check_grads(lambda s: factors.huber_loss(s, k), (jnp.asarray(9.0),), order=2)
        assert float(factors.huber_loss(jnp.asarray(4.0), jnp.inf)) == 2.0


def test_total_cost_equals_gtsam_graph_error(problem):
    import gtsam  # noqa: F401  (a test dependency: fail loudly if missing)
    from cm3d import baselines

    graph, x, _ = problem
    with jax.enable_x64(True):
        g, values, _, point_ok = baselines.gtsam_graph(graph, x)
        f = graph.projection
        counts = np.bincount(np.asarray(f.point_idx)[np.asarray(f.weight) > 0], minlength=x.points.shape[0])
        mask = jnp.asarray((counts >= 2)[np.asarray(f.point_idx)])
        ours = float(factors.total_cost(graph, x, mask))
        assert ours == pytest.approx(g.error(values), rel=1e-10)


def test_build_graph_memory_scaling_and_padding():
    with jax.enable_x64(True):
        N = 4
        poses = jnp.tile(jnp.eye(4), (N, 1, 1)).at[:, 0, 3].set(jnp.arange(N) * 0.1)
        K = jnp.broadcast_to(jnp.array([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]]), (N, 3, 3))
        pose_idx = jnp.array([0, 1, 2, 0])
        point_idx = jnp.array([0, 0, 1, 1])
        uv = jnp.zeros((4, 2))
        valid = jnp.array([True, True, True, False])
        memory = jnp.array([False, True, False, False])
        cfg = GraphConfig(memory_alpha=0.25, sigma_proj=2.0)
        g = factors.build_graph(poses, K, pose_idx, point_idx, uv, valid, memory,
                                pose_valid=jnp.array([True, True, True, False]), cfg=cfg)
        np.testing.assert_allclose(factors.effective_sigma(g), [2.0, 1.0, 2.0, 2.0])
        np.testing.assert_allclose(g.projection.weight, [1, 1, 1, 0])
        np.testing.assert_allclose(g.motion.weight, [1, 1, 0])  # no factor into the padded pose
        np.testing.assert_allclose(g.prior.target[0], poses[0])
        # default: the paper's chain of consecutive poses
        np.testing.assert_array_equal(g.motion.idx_a, [0, 1, 2])
        np.testing.assert_allclose(g.motion.measured[1], se3.inverse(poses[1]) @ poses[2], atol=1e-15)
        anchor = factors.build_graph(poses, K, pose_idx, point_idx, uv, valid, memory,
                                     pose_valid=jnp.array([True, False, True, True]),
                                     cfg=GraphConfig(motion_pairs="anchor"))
        np.testing.assert_array_equal(anchor.motion.idx_a, [0, 0, 0])
        np.testing.assert_array_equal(anchor.motion.idx_b, [1, 2, 3])
        np.testing.assert_allclose(anchor.motion.weight, [0, 1, 1])
        np.testing.assert_allclose(anchor.motion.measured[1], se3.inverse(poses[0]) @ poses[2], atol=1e-15)
        ia, ib = factors.motion_pairs(N, "both")
        np.testing.assert_array_equal(ia, [0, 0, 0, 0, 1, 2])
        np.testing.assert_array_equal(ib, [1, 2, 3, 1, 2, 3])
        with pytest.raises(ValueError, match="memory_alpha"):
            GraphConfig(memory_alpha=0.0)
        with pytest.raises(ValueError, match="motion_pairs"):
            GraphConfig(motion_pairs="chain")


def test_anchor_motion_pairs_equal_gtsam_between_factors(problem):
    """Motion factors from the anchor to every pose (the default chain:
    test_total_cost_equals_gtsam_graph_error) are the same objective as GTSAM's BetweenFactors on
    those pairs, at poses off the prior."""
    import gtsam  # noqa: F401
    from cm3d import baselines

    _, x, _ = problem
    with jax.enable_x64(True):
        graph, _, _ = factors.random_problem(3, 6, 40, obs_per_point=4, pose_noise=0.05, outlier_frac=0.1,
                                             cfg=GraphConfig(motion_pairs="anchor"))
        np.testing.assert_array_equal(graph.motion.idx_a, 0)
        g, values, _, point_ok = baselines.gtsam_graph(graph, x)
        f = graph.projection
        mask = jnp.asarray(point_ok[np.asarray(f.point_idx)])
        assert float(factors.total_cost(graph, x, mask)) == pytest.approx(g.error(values), rel=1e-10)


def test_adaptive_threshold_and_rejection(problem):
    graph, _, truth = problem
    with jax.enable_x64(True):
        g2, inlier, tau = jax.jit(factors.reject_outliers, compiler_options=FAST)(graph, truth)
        err = jax.jit(factors.reprojection_errors, compiler_options=FAST)(graph, truth)
        valid = np.asarray(graph.projection.weight) > 0
        # planted outliers are 10-40 px, noise is 1 px: all outliers out, almost all inliers kept
        gross = np.asarray(err) > 8.0
        assert not np.any(np.asarray(inlier) & gross)
        assert np.mean(np.asarray(inlier)[valid & ~gross]) > 0.97
        assert 2.0 <= float(tau) < 8.0
        np.testing.assert_array_equal(np.asarray(g2.projection.weight) > 0, np.asarray(inlier))
        # tau = max(tau_min, median + 3 * 1.4826 * MAD) by hand
        e = np.asarray(err)[valid]
        med = np.median(e)
        mad = np.median(np.abs(e - med))
        assert float(tau) == pytest.approx(max(2.0, med + 3 * 1.4826 * mad), rel=1e-9)
        # empty input: no NaN
        t0 = factors.adaptive_threshold(err, jnp.zeros_like(valid))
        assert float(t0) == 2.0


def test_orthonormalize_poses_value_and_gradient():
    with jax.enable_x64(True):
        T = se3.exp(jnp.array([0.1, 0.2, 0.3, 0.4, -0.2, 0.1]))
        noisy = T.at[:3, :3].add(1e-6 * jnp.arange(9.0).reshape(3, 3))
        out = factors.orthonormalize_poses(noisy)
        R = out[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-14)
        g = jax.grad(lambda T: jnp.sum(factors.orthonormalize_poses(T)))(T)
        assert np.all(np.isfinite(np.asarray(g)))


def test_jit_and_vmap_invariance(problem):
    graph, x, _ = problem
    with jax.enable_x64(True):
        jitted = jax.jit(factors.total_cost, compiler_options=FAST)(graph, x)
        two = jax.tree.map(lambda a: jnp.stack([a, a]), (graph, x))
        batched = jax.jit(jax.vmap(factors.total_cost), compiler_options=FAST)(*two)
        np.testing.assert_allclose(batched, [jitted, jitted], rtol=1e-12)
        e1 = jax.jit(factors.projection_linearize, compiler_options=FAST)(graph, x)
        e2 = jax.jit(jax.vmap(factors.projection_linearize), compiler_options=FAST)(*two)
        for a, b in zip(e1, e2):
            np.testing.assert_allclose(b[1], a, rtol=1e-12)
        r1 = jax.jit(factors.reject_outliers, compiler_options=FAST)(graph, x)[1]
        r2 = jax.jit(jax.vmap(lambda g, v: factors.reject_outliers(g, v)[1]), compiler_options=FAST)(*two)
        np.testing.assert_array_equal(r2[0], r1)
