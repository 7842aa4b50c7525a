"""Sim(3) / SE(3) RANSAC on 3D correspondences ``src[i] -> dst[i]``: hypothesis generators, consensus
scoring and the refit on the inliers; the one RANSAC of the package.

Generators: :func:`triangle_hypotheses` (closed-form similarity of random triangles,
:func:`triangle_sim3`) and :func:`upright_pairs` (two correspondences when both frames' up axes are
known: the rotation is a yaw). :func:`sim3_consensus` scores hypotheses by inliers within a threshold
and refits the best by Umeyama (the memory's verification, :func:`ransac_sim3` = both).
:func:`ransac` is global registration's variant: Umeyama fits of random triples that pass an
edge-length check, the best *distinct* poses (greedy suppression) refitted (Open3D's
``registration_ransac_based_on_feature_matching``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from cm3d.ops import sim3
from cm3d.solvers.umeyama import umeyama, umeyama_transform


def draw(ok, key, shape):
    """Random indices ``shape`` of the correspondences where ``ok`` (N,) (uniform; index 0 when none)."""
    n_ok = jnp.sum(ok)
    order = jnp.argsort(~ok, stable=True)  # the usable correspondences first
    return order[jax.random.randint(key, shape, 0, jnp.maximum(n_ok, 1))]


def residual2(T, src, dst):
    """Squared distances (N,) between ``T src`` and ``dst`` (N, 3) for a 4x4 ``T``."""
    return jnp.sum((src @ T[:3, :3].T + T[:3, 3] - dst) ** 2, -1)


def _triangle_frame(p):
    """Orthonormal frame (3, 3) (columns), centroid and size (sum of edge lengths) of p (3, 3)."""
    e1 = p[1] - p[0]
    e3 = jnp.cross(e1, p[2] - p[0])
    e1 = e1 / jnp.maximum(jnp.linalg.norm(e1), 1e-12)
    e3 = e3 / jnp.maximum(jnp.linalg.norm(e3), 1e-12)
    F = jnp.stack([e1, jnp.cross(e3, e1), e3], axis=1)
    edges = jnp.linalg.norm(p - jnp.roll(p, 1, axis=0), axis=-1)
    return F, jnp.mean(p, 0), edges


def triangle_sim3(src, dst):
    """Closed-form similarity mapping triangle ``src`` (3, 3) onto ``dst`` (no SVD: a RANSAC
    hypothesis): rotation between the triangles' frames, scale from their perimeters.
    Returns (s, R, t, consistent) where consistent: every edge ratio within 15% of s and the
    triangle not degenerate."""
    Fs, cs, es = _triangle_frame(src)
    Fd, cd, ed = _triangle_frame(dst)
    s = jnp.sum(ed) / jnp.maximum(jnp.sum(es), 1e-12)
    R = Fd @ Fs.T
    t = cd - s * (R @ cs)
    ratio = ed / jnp.maximum(es, 1e-12)
    area = jnp.linalg.norm(jnp.cross(src[1] - src[0], src[2] - src[0]))
    ok = jnp.all(jnp.abs(ratio / jnp.maximum(s, 1e-12) - 1.0) < 0.15) & (area > 1e-3 * jnp.sum(es) ** 2)
    return s, R, t, ok


def triangle_hypotheses(src, dst, ok, key, num_hypotheses: int):
    """``num_hypotheses`` random 3-point Sim(3) hypotheses (:func:`triangle_sim3`) from the
    correspondences ``src[i] -> dst[i]`` where ``ok``: (s, R, t, consistent) with a leading axis."""
    idx = draw(ok, key, (num_hypotheses, 3))
    return jax.vmap(lambda i: triangle_sim3(src[i], dst[i]))(idx)


def upright_frame(up):
    """A rotation (3, 3) whose last row is the unit ``up`` (rows: x, y, up; right-handed): it maps a
    frame's points to coordinates where up is +z, so two such frames differ by a yaw about z."""
    up = up / jnp.maximum(jnp.linalg.norm(up), 1e-12)
    e = jnp.where(jnp.abs(up[0]) < 0.9, jnp.array([1.0, 0.0, 0.0], up.dtype), jnp.array([0.0, 1.0, 0.0], up.dtype))
    x = e - (e @ up) * up
    x = x / jnp.linalg.norm(x)
    return jnp.stack([x, jnp.cross(up, x), up])


def upright_pairs(src, dst, ok, key, num_hypotheses: int, frame_src, frame_dst, min_separation, scale_range):
    """Sim(3) hypotheses from *two* correspondences each, for frames whose up axes are known
    (``frame_*`` = :func:`upright_frame`): the rotation is then a yaw about up, so a pair fixes yaw
    (horizontal direction of the pair), scale (its length ratio) and translation. Pairs closer than
    ``min_separation`` (src units), nearly vertical, or whose horizontal / vertical extents disagree
    with the scale by more than 15% are inconsistent. With few right matches among many this finds a
    pose far more often than 3-point samples (a right pair is ~1/w times likelier than a right triple).
    Returns (s, R, t, consistent) with a leading (num_hypotheses,) axis."""
    src, dst, ok = jnp.asarray(src, jnp.float32), jnp.asarray(dst, jnp.float32), jnp.asarray(ok, bool)
    n_ok = jnp.sum(ok)
    idx = draw(ok, key, (num_hypotheses, 2))
    a = jnp.einsum("ij,hkj->hki", frame_src, src[idx])  # (H, 2, 3) upright coordinates
    b = jnp.einsum("ij,hkj->hki", frame_dst, dst[idx])
    da, db = a[:, 1] - a[:, 0], b[:, 1] - b[:, 0]
    la, lb = jnp.linalg.norm(da, axis=-1), jnp.linalg.norm(db, axis=-1)
    ha, hb = jnp.linalg.norm(da[:, :2], axis=-1), jnp.linalg.norm(db[:, :2], axis=-1)
    s = lb / jnp.maximum(la, 1e-12)
    yaw = jnp.arctan2(db[:, 1], db[:, 0]) - jnp.arctan2(da[:, 1], da[:, 0])
    c, si = jnp.cos(yaw), jnp.sin(yaw)
    zero, one = jnp.zeros_like(c), jnp.ones_like(c)
    Rz = jnp.stack([jnp.stack([c, -si, zero], -1), jnp.stack([si, c, zero], -1), jnp.stack([zero, zero, one], -1)], -2)
    R = jnp.einsum("ji,hjk,kl->hil", frame_dst, Rz, frame_src)  # frame_dst^T Rz frame_src
    t = jnp.mean(dst[idx], 1) - s[:, None] * jnp.einsum("hij,hj->hi", R, jnp.mean(src[idx], 1))
    horizontal_ok = jnp.abs(hb / jnp.maximum(ha, 1e-12) / jnp.maximum(s, 1e-12) - 1) < 0.15
    vertical_ok = jnp.abs(db[:, 2] - s * da[:, 2]) < 0.15 * lb
    good = ((la > min_separation) & (ha > 0.3 * la) & horizontal_ok & vertical_ok & (s >= scale_range[0])
            & (s <= scale_range[1]) & (n_ok >= 2))
    return s, R, t, good


def ransac_sim3(src, dst, ok, key, threshold, num_hypotheses: int, scale_range, score_ok=None, cluster=None):
    """Sim(3) RANSAC on correspondences ``src[i] -> dst[i]`` (N, 3) where ``ok``: a fixed number of
    random 3-point hypotheses (:func:`triangle_sim3`; inconsistent edge ratios or a scale outside
    ``scale_range`` score 0) scored by inliers within ``threshold``; the best refitted by Umeyama
    on its inliers (twice). Returns (transform (4, 4), scale, inliers (N,) bool).

    ``score_ok`` (N,): the correspondences that score and refit (default ``ok``; hypotheses are
    always drawn from ``ok``), e.g. a looser set than the one that is safe to sample from;
    ``cluster`` (N,): cluster ids of ``src`` (e.g. :func:`cm3d.memory.keypoint_clusters`), so a refit is
    kept when it does not lose distinct 3D points (several views of one point count once).
    """
    src, dst, ok = jnp.asarray(src, jnp.float32), jnp.asarray(dst, jnp.float32), jnp.asarray(ok, bool)
    hyps = triangle_hypotheses(src, dst, ok, key, num_hypotheses)
    return sim3_consensus(src, dst, hyps, ok if score_ok is None else score_ok, threshold, scale_range, cluster)


def distinct_count(mask, cluster):
    """Number of distinct ``cluster`` ids among the True entries of ``mask`` (..., N)."""
    n = mask.shape[-1]
    hit = jnp.zeros(mask.shape[:-1] + (n,), jnp.int32).at[..., cluster].max(mask.astype(jnp.int32))
    return jnp.sum(hit, -1)


def sim3_consensus(src, dst, hypotheses, score_ok, threshold, scale_range, cluster=None):
    """The best of the Sim(3) ``hypotheses`` ``(s (H,), R (H, 3, 3), t (H, 3), consistent (H,))`` by
    correspondences ``src[i] -> dst[i]`` (where ``score_ok``) within ``threshold``, refitted by
    Umeyama on its inliers twice (a refit is kept when it loses no inlier, distinct ids of
    ``cluster`` (N,) when given, and keeps the scale in ``scale_range``). Returns (transform (4, 4),
    scale, inliers (N,) bool; none if no hypothesis is consistent, with a plausible scale, and has an
    inlier)."""
    src, dst = jnp.asarray(src, jnp.float32), jnp.asarray(dst, jnp.float32)
    score_ok = jnp.asarray(score_ok, bool)
    count = jnp.sum if cluster is None else (lambda m: distinct_count(m, cluster))
    s, R, t, good = hypotheses
    pred = s[:, None, None] * jnp.einsum("hij,nj->hni", R, src) + t[:, None, :]
    inl = score_ok[None] & (jnp.sum((pred - dst[None]) ** 2, -1) < threshold**2)
    plausible = good & (s >= scale_range[0]) & (s <= scale_range[1]) & jnp.all(jnp.isfinite(pred), (1, 2))
    score = jnp.where(plausible, jnp.sum(inl, 1), 0)
    h = jnp.argmax(score)
    best = inl[h]
    T = sim3.from_parts(s[h], R[h], t[h])
    for _ in range(2):
        s2, R2, t2 = umeyama(src, dst, best, with_scale=True)
        T2 = sim3.from_parts(s2, R2, t2)
        inl2 = score_ok & (residual2(T2, src, dst) < threshold**2)
        better = ((count(inl2) >= count(best)) & (s2 >= scale_range[0]) & (s2 <= scale_range[1])
                  & jnp.all(jnp.isfinite(T2)))
        T = jnp.where(better, T2, T)
        best = jnp.where(better, inl2, best)
    return T, sim3.scale(T), best & (score[h] > 0)


# --- Global registration's RANSAC


def _pose_distance(A, B):
    """(rotation-block Frobenius distance, translation distance) between 4x4 transforms."""
    return jnp.sqrt(jnp.sum((A[..., :3, :3] - B[..., :3, :3]) ** 2, (-2, -1))), \
        jnp.linalg.norm(A[..., :3, 3] - B[..., :3, 3], axis=-1)


def ransac(src, dst, valid, key, options):
    """Robust rigid (or similarity) fits of correspondences ``src[i] -> dst[i]`` (N, 3), valid (N,).

    Draws ``num_samples`` triples among the valid correspondences (the first
    ``max_correspondences``), keeps the first
    ``num_hypotheses`` whose edge lengths agree (and whose edges exceed ``inlier_distance``), fits
    each by Umeyama and scores it by the correspondences within ``inlier_distance`` (in the units of
    src/dst); the best ``num_candidates`` *distinct* hypotheses (greedy suppression of poses within
    ~8 deg and 2 inlier distances of a better one) are re-fitted on their inliers.
    -> (transforms (K, 4, 4) best first, inlier counts (K,)). Fewer than 3 valid correspondences
    give identities with 0 inliers. Deterministic per key. ``options``: a
    :class:`cm3d.solvers.align.GlobalOptions`.
    """
    o = options
    dtype = src.dtype
    K, H = o.num_candidates, o.num_hypotheses
    tau2 = jnp.asarray(o.inlier_distance, dtype) ** 2
    # the valid correspondences first (at most max_correspondences of them, in index order)
    n = min(src.shape[0], o.max_correspondences)
    (vidx,) = jnp.nonzero(valid, size=n, fill_value=0)
    nv = jnp.minimum(jnp.sum(valid), n)
    src, dst, valid = src[vidx], dst[vidx], jnp.arange(n) < nv
    tri = jax.random.randint(key, (o.num_samples, 3), 0, jnp.maximum(nv, 1))

    def edges(x):
        return jnp.linalg.norm(x - jnp.roll(x, 1, axis=-2), axis=-1)

    ea, eb = edges(src[tri]), edges(dst[tri])
    ratio = eb / jnp.maximum(ea, 1e-12)
    lo, hi = (1 / o.scale_tolerance, o.scale_tolerance) if o.with_scale else (o.edge_ratio, 1 / o.edge_ratio)
    good = (jnp.all(ea > o.inlier_distance, -1) & jnp.all(eb > o.inlier_distance, -1)
            & (jnp.min(ratio, -1) > o.edge_ratio * jnp.max(ratio, -1))
            & jnp.all((ratio > lo) & (ratio < hi), -1))
    (hid,) = jnp.nonzero(good, size=H, fill_value=0)
    hok = jnp.arange(H) < jnp.sum(good)
    a, b = src[tri[hid]], dst[tri[hid]]
    T = jax.vmap(lambda x, y: umeyama_transform(x, y, None, o.with_scale))(a, b)

    check = jnp.all(jax.vmap(residual2)(T, a, b) < tau2, -1)

    def score(Tm):
        return jnp.sum(valid & (residual2(Tm, src, dst) < tau2))

    scores = jnp.where(hok & check & (nv >= 3), jax.lax.map(score, T, batch_size=64), -1)

    def pick(sc, _):  # greedy non-maximum suppression: the best remaining, then mute its neighbours
        i = jnp.argmax(sc)
        dr, dt = _pose_distance(T, T[i])
        same = (dr < 0.2) & (dt < 2.0 * o.inlier_distance)
        return jnp.where(same, -1, sc).at[i].set(-1), (i, sc[i])

    _, (sel, sel_score) = jax.lax.scan(pick, scores, None, length=K)

    def refine(Tm):
        def step(Tm, _):
            inl = valid & (residual2(Tm, src, dst) < tau2)
            Tn = umeyama_transform(src, dst, inl, o.with_scale)
            return jnp.where((jnp.sum(inl) >= 3) & jnp.all(jnp.isfinite(Tn)), Tn, Tm), None

        return jax.lax.scan(step, Tm, None, length=3)[0]

    ok = sel_score >= 3
    Tk = jnp.where(ok[:, None, None], jax.vmap(refine)(T[sel]), jnp.eye(4, dtype=dtype))
    return Tk, jnp.where(ok, jax.vmap(score)(Tk), 0).astype(jnp.int32)
