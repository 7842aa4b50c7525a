"""Sim(3) RANSAC (cm3d.solvers.ransac): triangle and upright-pair hypotheses, consensus and refit,
distinct counts; global registration's variant is tested in tests/test_align.py."""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from cm3d import memory
from cm3d.ops import sim3
from cm3d.solvers import ransac

_ransac = jax.jit(ransac.ransac_sim3, static_argnums=(5, 6))


def test_sim3_consensus_picks_and_refits_the_best_pose():
    """Correspondences from two similarities (60 for A, 35 for B) and outliers; hypotheses: noisy copies
    of A and B and random ones: the consensus picks A's pose, refitted to exactly its own inliers."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(6)
    src = rng.uniform(-1, 1, (120, 3)).astype(np.float32)
    poses = [(1.3, Rotation.from_rotvec([0.1, 0.9, -0.2]).as_matrix(), np.array([0.5, -1.0, 0.2])),
             (0.7, Rotation.from_rotvec([-1.2, 0.3, 0.4]).as_matrix(), np.array([-2.0, 0.5, 1.0]))]
    dst = rng.uniform(-3, 3, (120, 3)).astype(np.float32)
    for (s, R, t), sl in zip(poses, (slice(0, 60), slice(60, 95))):
        dst[sl] = s * src[sl] @ R.T + t
    hyp = []
    for i in range(24):
        s, R, t = poses[i % 3] if i % 3 < 2 else (rng.uniform(0.5, 2), Rotation.random(random_state=i).as_matrix(),
                                                  rng.normal(size=3))
        noise = Rotation.from_rotvec(rng.normal(scale=0.01, size=3)).as_matrix() if i % 3 < 2 else np.eye(3)
        hyp.append((s, noise @ R, t + rng.normal(scale=0.005, size=3)))
    hyps = (jnp.asarray([h[0] for h in hyp], jnp.float32), jnp.asarray(np.stack([h[1] for h in hyp]), jnp.float32),
            jnp.asarray(np.stack([h[2] for h in hyp]), jnp.float32), jnp.ones(24, bool))
    ok = np.ones(120, bool)
    T, scale, inl = jax.jit(ransac.sim3_consensus, static_argnums=5)(src, dst, hyps, ok, 0.05, (0.25, 4.0))
    inl = np.asarray(inl)
    np.testing.assert_allclose(float(scale), 1.3, rtol=1e-4)
    assert inl[:60].all() and inl.sum() == 60
    s, R, t = poses[0]
    np.testing.assert_allclose(np.asarray(T), sim3.from_parts(s, R, t), atol=1e-4)


def test_ransac_sim3_recovers_a_similarity_among_outliers():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(1)
    src = rng.uniform(-1, 1, (200, 3)).astype(np.float32)
    R = Rotation.from_rotvec([0.4, -1.0, 2.0]).as_matrix()
    s, t = 1.7, np.array([0.5, -2.0, 1.0])
    dst = (s * src @ R.T + t).astype(np.float32) + rng.normal(scale=0.005, size=(200, 3)).astype(np.float32)
    outlier = rng.random(200) < 0.6
    dst[outlier] = rng.uniform(-3, 3, (outlier.sum(), 3))
    ok = np.ones(200, bool)
    ok[-20:] = False
    T, scale, inl = _ransac(src, dst, ok, jax.random.PRNGKey(0), 0.05, 256, (0.25, 4.0), score_ok=ok)
    np.testing.assert_allclose(float(scale), s, rtol=1e-2)
    np.testing.assert_allclose(np.asarray(T[:3, :3]), s * R, atol=2e-2)
    inl = np.asarray(inl)
    assert not np.any(inl & ~ok) and np.mean(inl[ok & ~outlier]) > 0.95 and not np.any(inl & outlier & ok & False)
    # no usable correspondences: nothing is an inlier, nothing is NaN
    none = np.zeros(200, bool)
    T, scale, inl = _ransac(src, dst, none, jax.random.PRNGKey(0), 0.05, 256, (0.25, 4.0), score_ok=none)
    assert not np.any(np.asarray(inl)) and np.all(np.isfinite(np.asarray(T)))


def test_ransac_scores_on_a_looser_set_and_counts_distinct_points():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(4)
    src = rng.uniform(-1, 1, (200, 3)).astype(np.float32)  # the shapes of the test above: one compilation
    R, s, t = Rotation.from_rotvec([0.2, 0.5, -0.3]).as_matrix(), 0.8, np.array([1.0, 0.0, -1.0])
    dst = (s * src @ R.T + t).astype(np.float32)
    dst[100:] = rng.uniform(-3, 3, (100, 3))  # outliers
    sample = np.zeros(200, bool)
    sample[:8] = True  # a few safe matches to sample from ...
    sample[100:110] = True
    score = np.ones(200, bool)  # ... scored on all of them
    T, scale, inl = _ransac(src, dst, sample, jax.random.PRNGKey(1), 0.02, 256, (0.25, 4.0), score_ok=score)
    np.testing.assert_allclose(float(scale), s, rtol=1e-3)
    assert np.asarray(inl)[:100].all() and not np.asarray(inl)[100:].any()  # inliers beyond the sampled ones
    cluster = np.arange(200) // 2  # pairs of views of one point: half as many distinct points
    assert int(ransac.distinct_count(inl, jnp.asarray(cluster))) == 50


@functools.partial(jax.jit, static_argnums=4)
def _upright_fit(normals_s, up_d, src, dst, prior):
    up_s = memory.up_axis(normals_s, jnp.ones(normals_s.shape[0], bool), prior, 35.0)
    F_s, F_d = ransac.upright_frame(up_s), ransac.upright_frame(up_d)
    ok = jnp.ones(src.shape[0], bool)
    hyps = ransac.upright_pairs(src, dst, ok, jax.random.PRNGKey(0), 256, F_s, F_d, 0.1, (0.25, 4.0))
    none = memory.up_axis(jnp.zeros((5, 3)), jnp.ones(5, bool), prior, 35.0)  # no normals: the prior
    return up_s, F_s, F_d, hyps, ransac.sim3_consensus(src, dst, hyps, ok, 0.05, (0.25, 4.0)), none


def test_up_axis_and_upright_pairs_recover_a_yaw_similarity():
    """Floor/ceiling normals give each frame's up axis; then two matches fix a Sim(3) whose rotation
    is a yaw about up, and the consensus picks it among outliers (reference: the true transform)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(7)
    tilt_s, tilt_d = Rotation.from_rotvec([0.3, 0.1, -0.2]), Rotation.from_rotvec([-0.25, 0.05, 0.3])
    # a box room's normals (floor/ceiling vertical, walls horizontal, noisy) seen in a tilted frame
    world_n = np.repeat(np.eye(3)[[2, 0, 1]], 60, axis=0)
    world_n = world_n + rng.normal(scale=0.02, size=world_n.shape)
    world_n /= np.linalg.norm(world_n, axis=1, keepdims=True)
    up_d = tilt_d.apply([0, 0, 1.0]).astype(np.float32)
    # truth: dst = s R src + t with R a yaw of 1.1 rad about up (from the source's to the target's
    # frame); any rotations whose last rows are the up axes serve as frames
    F_s0, F_d0 = tilt_s.as_matrix().T, tilt_d.as_matrix().T
    c, sn = np.cos(1.1), np.sin(1.1)
    R = F_d0.T @ np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1]]) @ F_s0
    s, t = 1.6, np.array([0.5, -1.0, 2.0])
    src = rng.uniform(-2, 2, (80, 3)).astype(np.float32)
    dst = (s * src @ R.T + t).astype(np.float32)
    dst[30:] = rng.uniform(-4, 4, (50, 3))  # outliers
    up_s, F_s, F_d, hyps, (T, scale, inl), none = _upright_fit(
        jnp.asarray(tilt_s.apply(world_n), jnp.float32), up_d, src, dst, (0.0, 0.0, 1.0))
    assert np.degrees(np.arccos(np.clip(np.asarray(up_s) @ tilt_s.apply([0, 0, 1.0]), -1, 1))) < 1.0
    np.testing.assert_allclose(np.asarray(none), [0, 0, 1.0])
    np.testing.assert_allclose(np.asarray(F_s @ F_s.T), np.eye(3), atol=1e-5)
    np.testing.assert_allclose(np.asarray(F_s)[2], np.asarray(up_s), atol=1e-6)
    np.testing.assert_allclose(float(scale), s, rtol=2e-3)
    np.testing.assert_allclose(np.asarray(T[:3, :3]), s * R, atol=1e-2)
    np.testing.assert_allclose(np.asarray(T[:3, 3]), t, atol=2e-2)
    assert np.asarray(inl)[:30].all() and not np.asarray(inl)[30:].any()
    # the minimal solver itself: a pair of right matches in the estimated frames gives the true
    # transform up to the up-axis estimate (within a degree)
    hs, hR, ht, good = (np.asarray(a) for a in hyps)
    close = good & np.all(np.abs(hs[:, None, None] * hR - s * R) < 0.05, (1, 2)) & (np.abs(hs - s) < 0.02)
    assert close.sum() >= 10


def test_distinct_count_counts_cluster_ids():
    rng = np.random.default_rng(3)
    cid = rng.integers(0, 12, 60)
    masks = rng.random((4, 60)) < 0.5
    counts = np.asarray(ransac.distinct_count(jnp.asarray(masks), jnp.asarray(cid)))
    assert list(counts) == [len(set(cid[m])) for m in masks]
