"""Neighbour search: exact radius search vs a KD-tree, k-NN graph, radius neighbours, normals vs
Open3D, the walk. All indices are built on (3000, 3) clouds with radius 0.3 (the shape and radius
tests/test_icp.py uses), so the file compiles few programs."""

import jax
import jax.numpy as jnp
import numpy as np
import open3d as o3d
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from cm3d.ops.neighbors import (
    build_target_index,
    certified_nearest,
    empty_cache,
    exact_nearest,
    knn_graph,
    nearest_within_radius,
    radius_neighbors,
    seed,
    walk,
    walk_to_convergence,
)
from cm3d.ops.voxel import cell_coords, hash_lookup

N, R = 3000, 0.3
_build = jax.jit(build_target_index, static_argnames=("radius",))
_nearest = jax.jit(nearest_within_radius)
_radius_nb = jax.jit(radius_neighbors, static_argnames=("max_nn", "max_candidates"))


def _plane_cloud(rng, n=N):
    """Points on three planes (surfaces, as ICP sees them) with 1 cm noise."""
    k = rng.integers(0, 3, n)
    uv = rng.uniform(-1, 1, (n, 2))
    p = np.zeros((n, 3))
    for i in range(3):
        m = k == i
        axes = [a for a in range(3) if a != i]
        q = np.zeros((m.sum(), 3))
        q[:, axes[0]], q[:, axes[1]] = uv[m, 0], uv[m, 1]
        q[:, i] = 0.3 * i
        p[m] = q
    return (p + rng.normal(scale=0.01, size=p.shape)).astype(np.float32)


@settings(max_examples=6, deadline=None)
@given(seed_=st.integers(0, 10_000), n=st.integers(1, N), scale=st.floats(0.5, 4.0), radius=st.floats(0.05, R))
def test_nearest_within_radius_equals_kdtree(seed_, n, scale, radius):
    rng = np.random.default_rng(seed_)
    pts = rng.uniform(-scale, scale, (N, 3)).astype(np.float32)
    valid = np.arange(N) < n
    q = rng.uniform(-1.2 * scale, 1.2 * scale, (N, 3)).astype(np.float32)
    index = _build(jnp.asarray(pts), jnp.asarray(valid), radius=R)
    idx, dist = _nearest(index, jnp.asarray(q), jnp.float32(radius))
    d_ref, i_ref = cKDTree(pts[:n]).query(q, distance_upper_bound=radius)
    found = np.isfinite(d_ref)
    np.testing.assert_array_equal(np.asarray(idx), np.where(found, i_ref, -1))
    np.testing.assert_allclose(np.asarray(dist)[found], d_ref[found], rtol=1e-5, atol=1e-6)


def test_knn_graph_and_normals_match_references():
    p = _plane_cloud(np.random.default_rng(0))
    index = _build(jnp.asarray(p), jnp.ones(N, bool), radius=R)
    assert int(index.overflow) == 0
    g, exact = knn_graph(index)
    g, exact = np.asarray(g), np.asarray(exact)
    _, i_ref = cKDTree(p).query(p, 16)
    same = np.array([set(a) == set(b) for a, b in zip(g, i_ref)])
    assert exact.mean() > 0.1 and same.mean() > 0.75
    assert same[exact].all()  # flagged exact -> equals the KD-tree
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p.astype(np.float64)))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(16))
    inv = np.empty(len(p), int)
    inv[np.asarray(index.order)] = np.arange(len(p))
    dots = np.abs(np.sum(np.asarray(index.normals)[inv] * np.asarray(pc.normals), 1))
    assert np.all(dots[same] > 0.999)  # same neighbours -> same normal up to sign
    assert np.median(dots) > 0.999 and np.mean(dots > 0.99) > 0.95


def test_radius_neighbors_equal_kdtree_and_vmap():
    rng = np.random.default_rng(3)
    pts = np.stack([_plane_cloud(rng), rng.uniform(0, 2, (N, 3)).astype(np.float32)])
    valid = rng.random((2, N)) > 0.1
    out = jax.jit(jax.vmap(lambda p, m: radius_neighbors(p, m, radius=0.15, max_nn=32, max_candidates=256)))(
        jnp.asarray(pts), jnp.asarray(valid))
    for b in range(2):
        one = _radius_nb(jnp.asarray(pts[b]), jnp.asarray(valid[b]), radius=0.15, max_nn=32, max_candidates=256)
        np.testing.assert_array_equal(out.idx[b], one.idx)
        vi = np.nonzero(valid[b])[0]
        tree = cKDTree(pts[b][vi])
        assert int(one.truncated) == 0
        for i in range(0, N, 7):
            got = np.asarray(one.idx[i])[: int(one.count[i])]
            if not valid[b, i]:
                assert len(got) == 0
                continue
            d, j = tree.query(pts[b][i], k=33, distance_upper_bound=0.15)
            ref = [vi[x] for x, dd in zip(j, d) if np.isfinite(dd) and vi[x] != i][:32]
            assert set(got) == set(ref), (b, i)
            assert np.all(np.diff(np.asarray(one.dist2[i])[: len(got)]) >= 0)  # ascending


def test_walk_then_certified_search_is_exact():
    rng = np.random.default_rng(1)
    p = _plane_cloud(rng)
    index = _build(jnp.asarray(p), jnp.ones(N, bool), radius=R)
    q = jnp.asarray(p + rng.normal(scale=0.03, size=p.shape).astype(np.float32))
    active = jnp.ones(N, bool)

    q2 = q + jnp.asarray(rng.normal(scale=1e-3, size=p.shape).astype(np.float32))  # a small move

    @jax.jit
    def run(index, q, q2):
        m = seed(index, q, active)
        # one walk step from the seeds: the matches that moved are not local minima yet, so only the
        # settled ones may be certified (the others are searched)
        m1, d1, moved = walk(index, q, m)
        early = certified_nearest(index, q, m1, d1, active, 0.2, settled=~moved)
        m, d2 = walk_to_convergence(index, q, m)
        first = certified_nearest(index, q, m, d2, active, 0.2)
        _, _, _, cache = exact_nearest(index, q, m, d2, active, 0.2, empty_cache(q))
        m, d2 = walk_to_convergence(index, q2, m)
        return early, first, exact_nearest(index, q2, m, d2, active, 0.2, cache)[:3]  # reuses the cache

    # crowded blocks (plane intersections) overflow the exact-search tables, and queries in empty fine
    # cells (no stored table row) gather theirs from the fine grid: both exercised below
    assert int(index.truncated) > 0 and int(jnp.sum(index.block_total > index.block_cand.shape[1])) > 0
    assert int(jnp.sum(hash_lookup(index.fine, cell_coords(q, index.origin, index.fine_cell)) < 0)) > 0
    tree = cKDTree(p)
    early, first, second = run(index, q, q2)
    for (pos, d2, searched), qq, most in zip((early, first, second), (q, q, q2), (N, N // 2, int(first[2]) // 2)):
        idx = np.where(np.asarray(pos) >= 0, np.asarray(index.order)[np.clip(np.asarray(pos), 0, None)], -1)
        d_ref, i_ref = tree.query(np.asarray(qq), distance_upper_bound=0.2)
        np.testing.assert_array_equal(idx, np.where(np.isfinite(d_ref), i_ref, -1))
        np.testing.assert_allclose(np.sqrt(np.asarray(d2))[np.isfinite(d_ref)], d_ref[np.isfinite(d_ref)],
                                   rtol=1e-5, atol=1e-6)
        assert int(searched) < most  # most matches are certified by the graph or by the cache


def test_jit_vmap_invariance_and_empty():
    rng = np.random.default_rng(2)
    pts = jnp.asarray(rng.uniform(0, 1, (2, N, 3)).astype(np.float32))
    q = jnp.asarray(rng.uniform(0, 1, (2, N, 3)).astype(np.float32))
    bi = jax.jit(jax.vmap(lambda x: build_target_index(x, jnp.ones(N, bool), radius=R)))(pts)
    bidx, bd = jax.jit(jax.vmap(lambda i, x: nearest_within_radius(i, x, jnp.float32(R))))(bi, q)
    for b in range(2):
        one = _build(pts[b], jnp.ones(N, bool), radius=R)
        i1, d1 = _nearest(one, q[b], jnp.float32(R))
        np.testing.assert_array_equal(bidx[b], i1)
        np.testing.assert_array_equal(bd[b], d1)
        np.testing.assert_array_equal(bi.graph[b], one.graph)
    empty = _build(jnp.zeros((N, 3)), jnp.zeros(N, bool), radius=R)
    i0, d0 = _nearest(empty, q[0], jnp.float32(R))
    assert bool(jnp.all(i0 == -1)) and bool(jnp.all(jnp.isinf(d0)))
    nb = _radius_nb(jnp.zeros((N, 3)), jnp.zeros(N, bool), radius=0.15, max_nn=32, max_candidates=256)
    assert int(jnp.sum(nb.count)) == 0 and bool(jnp.all(nb.idx == -1))
