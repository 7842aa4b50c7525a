"""Global registration: FPFH features, feature matching, RANSAC and ICP refinement (Umeyama fits are
in :mod:`cm3d.solvers.umeyama`, re-exported here; the RANSAC in :mod:`cm3d.solvers.ransac`).

:func:`global_registration` aligns two clouds from any relative pose, with partial overlap and
optionally an unknown scale (all pure JAX, fixed shapes, deterministic per PRNG key):

1. voxel-downsample both clouds (voxel = ``voxel_fraction`` x the target's largest extent) and
   work in voxel units from there on, so every radius below is a static number of voxels;
2. normals by local PCA within ``normal_radius``, flipped towards the cloud's centroid: FPFH
   depends on normal signs, and consistent signs are what make it discriminative (Open3D's own
   pipeline succeeds twice as often on our synthetic rooms with them);
3. FPFH (Rusu et al. 2009, Open3D's definition) within ``feature_radius``;
4. mutual nearest neighbours in feature space;
5. RANSAC: random correspondence triples, an edge-length pre-check, Umeyama fits of those that pass,
   scored by correspondences within ``inlier_distance``; the best distinct hypotheses re-fitted;
6. each candidate refined by point-to-plane ICP (Sim(3) with ``with_scale``) on the downsampled
   clouds; the winner maximises sqrt(source fitness x target coverage).

An unknown scale: ``options.scales`` holds source -> target scale hypotheses, the source is
pre-scaled by each (vmapped) and RANSAC/ICP fit the residual similarity (:meth:`GlobalOptions.sim3`).
The result is an initial alignment: refine it with :func:`cm3d.solvers.icp.icp` at full resolution.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from cm3d.ops import sim3
from cm3d.ops.grid import RadiusNeighbors, grid_nearest, radius_neighbors, sort_by_cell
from cm3d.ops.normals import pca_normals
from cm3d.ops.voxel import adaptive_voxel_size, masked_bounds, valid_points, voxel_downsample
from cm3d.solvers.icp import ICPOptions, point_to_plane_update
from cm3d.solvers.ransac import ransac
from cm3d.solvers.umeyama import similarity_matrix, umeyama, umeyama_transform  # noqa: F401  (re-exported)


# --- FPFH features

_BINS = 11


def _pair_features(p1, n1, p2, n2):
    """Pair features (theta, alpha, phi) of point pairs (..., 3) with normals (Rusu et al. 2009).

    The pair's source is the point whose normal makes the smaller angle with the line ``d``; with
    its normal ``u``, ``v = d x u / |d x u|``, ``w = u x v`` and the other normal ``n_t``:
    ``phi = u . d / |d|``, ``alpha = v . n_t``, ``theta = atan2(w . n_t, u . n_t)`` (Open3D's
    conventions). All zero for coincident points or a normal along the line.
    """
    d = p2 - p1
    dist = jnp.sqrt(jnp.sum(d * d, -1))
    ok = dist > 0
    inv = 1.0 / jnp.where(ok, dist, 1.0)
    a1 = jnp.sum(n1 * d, -1) * inv
    a2 = jnp.sum(n2 * d, -1) * inv
    swap = jnp.abs(a1) < jnp.abs(a2)
    u = jnp.where(swap[..., None], n2, n1)
    nt = jnp.where(swap[..., None], n1, n2)
    d = jnp.where(swap[..., None], -d, d)
    phi = jnp.where(swap, -a2, a1)
    v = jnp.cross(d, u)
    vn = jnp.sqrt(jnp.sum(v * v, -1))
    ok = ok & (vn > 0)
    v = v / jnp.where(ok, vn, 1.0)[..., None]
    w = jnp.cross(u, v)
    alpha = jnp.sum(v * nt, -1)
    theta = jnp.arctan2(jnp.sum(w * nt, -1), jnp.sum(u * nt, -1))
    z = jnp.zeros_like(dist)
    return jnp.where(ok, theta, z), jnp.where(ok, alpha, z), jnp.where(ok, phi, z)


def fpfh(points, normals, neighbors: RadiusNeighbors) -> jnp.ndarray:
    """Fast point feature histograms (n, 33) (Rusu et al. 2009), Open3D's ``compute_fpfh_feature``.

    points, normals: (n, 3); neighbors: their :func:`~cm3d.ops.neighbors.radius_neighbors`.
    SPFH(p): histograms of theta, alpha and phi (11 bins each) over p's neighbours, each summing to
    100; FPFH(p) = SPFH(p) + sum_k SPFH(q_k) / |q_k - p|^2, the sum's three histograms rescaled to
    100 each (so every histogram of FPFH sums to 200). Zero for points without neighbours.
    Normal signs matter: orient them consistently (see :func:`describe`).
    """
    n, dtype = points.shape[0], points.dtype
    has = neighbors.idx >= 0
    ic = jnp.clip(neighbors.idx, 0)
    th, al, ph = _pair_features(points[:, None, :], normals[:, None, :], points[ic], normals[ic])

    def hist(x, lo, width):
        b = jnp.clip(jnp.floor(_BINS * (x - lo) / width), 0, _BINS - 1).astype(jnp.int32)
        return jnp.sum(jax.nn.one_hot(b, _BINS, dtype=dtype) * has[..., None].astype(dtype), axis=1)

    cnt = jnp.sum(has, axis=1).astype(dtype)
    h = jnp.concatenate([hist(th, -jnp.pi, 2 * jnp.pi), hist(al, -1.0, 2.0), hist(ph, -1.0, 2.0)], axis=-1)
    spfh = h * (100.0 / jnp.maximum(cnt, 1.0))[:, None]
    near = has & (neighbors.dist2 > 0)
    w = jnp.where(near, 1.0 / jnp.where(near, neighbors.dist2, 1.0), 0.0)
    agg = jnp.einsum("nk,nkf->nf", w, spfh[ic]).reshape(n, 3, _BINS)
    sums = jnp.sum(agg, axis=-1, keepdims=True)
    agg = agg * jnp.where(sums > 0, 100.0 / jnp.where(sums > 0, sums, 1.0), 0.0)
    return jnp.where((cnt > 0)[:, None], agg.reshape(n, 3 * _BINS) + spfh, 0.0)


# --- Global registration


@dataclasses.dataclass(frozen=True)
class GlobalOptions:
    """Static options of :func:`global_registration`. Distances are in *voxels* (the clouds are
    downsampled and rescaled to voxel units first), except ``voxel_size`` (target units).

    voxel_size: target units, or None for ``voxel_fraction`` x the target's largest bounding-box
    side. capacity: downsampled points kept per cloud (overflow is counted, not an error).
    normal_radius / normal_max_nn: PCA neighbourhood (Open3D's hybrid search, point included).
    feature_radius / max_nn / max_candidates: FPFH neighbourhood (nearest ``max_nn`` within radius).
    mutual / min_mutual: mutual nearest features, unless fewer than ``min_mutual`` are mutual.
    num_samples: random correspondence triples drawn; num_hypotheses: the first of them passing the
    edge-length check (``edge_ratio``; with_scale: edge ratios consistent and within
    ``scale_tolerance``) are fitted and scored by their correspondences within ``inlier_distance``.
    num_candidates: best distinct hypotheses (per scale) refined by point-to-plane ICP on the
    downsampled clouds (correspondences within ``icp_distance``: :func:`cm3d.ops.grid.grid_nearest`
    looking at ``icp_per_cell`` points per cell): ``screen_iterations`` steps each, then ``num_refined`` of them (over all scales) to
    ``icp_iterations``; the best sqrt(fitness x coverage) wins. scales: source -> target scale
    hypotheses (the source is pre-scaled by each); with_scale: Sim(3) RANSAC and ICP.
    """

    voxel_size: float | None = None
    voxel_fraction: float = 0.02
    capacity: int = 4096
    normal_radius: float = 2.0
    normal_max_nn: int = 30
    feature_radius: float = 5.0
    max_nn: int = 64
    max_candidates: int = 512
    mutual: bool = True
    min_mutual: int = 32
    max_correspondences: int = 1024
    num_samples: int = 32768
    num_hypotheses: int = 2048
    edge_ratio: float = 0.9
    inlier_distance: float = 1.5
    num_candidates: int = 8
    screen_iterations: int = 5
    num_refined: int = 4
    icp_iterations: int = 20
    icp_distance: float = 2.0
    icp_per_cell: int = 8
    scales: tuple[float, ...] = (1.0,)
    with_scale: bool = False
    scale_tolerance: float = 1.25

    def __post_init__(self):
        if self.voxel_size is not None and not self.voxel_size > 0:
            raise ValueError(f"voxel_size must be > 0 or None, got {self.voxel_size}")
        if not 0 < self.voxel_fraction < 1:
            raise ValueError(f"voxel_fraction must be in (0, 1), got {self.voxel_fraction}")
        if not 1 <= self.normal_max_nn - 1 <= self.max_nn:
            raise ValueError("normal_max_nn - 1 must be in [1, max_nn]")
        if not self.normal_radius <= self.feature_radius:
            raise ValueError("normal_radius must be <= feature_radius")
        if not self.scales or not all(s > 0 for s in self.scales):
            raise ValueError(f"scales must be positive, got {self.scales}")
        if self.num_candidates < 1 or self.num_hypotheses < self.num_candidates:
            raise ValueError("need 1 <= num_candidates <= num_hypotheses")
        if not 0 <= self.screen_iterations <= self.icp_iterations or self.num_refined < 1:
            raise ValueError("need 0 <= screen_iterations <= icp_iterations and num_refined >= 1")

    @classmethod
    def sim3(cls, lo: float = 0.6, hi: float = 1.6, num: int = 5, **kw) -> "GlobalOptions":
        """Options for an unknown scale ratio in [lo, hi]: ``num`` geometric scale hypotheses, Sim(3),
        4 RANSAC candidates per scale (other fields from ``kw``)."""
        r = (hi / lo) ** (1.0 / max(num - 1, 1))
        kw = {"num_candidates": 4, **kw}
        return cls(scales=tuple(float(lo * r**i) for i in range(num)), with_scale=True,
                   scale_tolerance=max(1.1, float(r)), **kw)


@struct.dataclass
class FeatureCloud:
    """A cloud prepared for global registration, in voxel units.

    points (C, 3): voxel means / voxel_size; normals (C, 3): PCA, oriented towards the centroid
    (zero where undefined); features (C, 33): FPFH; valid (C,) points; described (C,) points with a
    feature; voxel_size (): target units per voxel unit; overflow (): voxels beyond the capacity;
    truncated (): points with an incomplete FPFH neighbourhood.
    """

    points: jnp.ndarray
    normals: jnp.ndarray
    features: jnp.ndarray
    valid: jnp.ndarray
    described: jnp.ndarray
    voxel_size: jnp.ndarray
    overflow: jnp.ndarray
    truncated: jnp.ndarray


def orient_normals(points, normals, valid):
    """Flip normals (n, 3) to point towards the centroid of the valid points (a rigid-motion
    covariant sign, right for surfaces seen from inside a room and consistent for objects)."""
    w = valid.astype(points.dtype)[:, None]
    c = jnp.sum(points * w, 0) / jnp.maximum(jnp.sum(w), 1.0)
    return jnp.where((jnp.sum(normals * (c - points), -1) < 0)[:, None], -normals, normals)


def describe(points, valid=None, voxel_size=1.0, options: GlobalOptions = GlobalOptions()) -> FeatureCloud:
    """Voxel-downsample points (n, 3) (voxel_size: target units, may be traced), rescale to voxel
    units, estimate oriented normals and FPFH features -> :class:`FeatureCloud` (capacity
    ``options.capacity``). Cache it for a static cloud (a memory entry)."""
    o = options
    points = jnp.asarray(points)
    vox = voxel_downsample(points, voxel_size, valid, capacity=o.capacity)
    vs = vox.voxel_size
    ok = vox.valid & (vs > 0)
    p = jnp.where(ok[:, None], vox.points / jnp.where(vs > 0, vs, 1.0), 0.0)
    nb = radius_neighbors(p, ok, radius=o.feature_radius, max_nn=o.max_nn, max_candidates=o.max_candidates)
    m = o.normal_max_nn - 1
    near = (nb.idx[:, :m] >= 0) & (nb.dist2[:, :m] <= o.normal_radius**2)
    nbp = jnp.concatenate([p[:, None], p[jnp.clip(nb.idx[:, :m], 0)]], axis=1)
    nrm = pca_normals(nbp, jnp.concatenate([ok[:, None], near], axis=1))
    nrm = orient_normals(p, nrm, ok)
    has_n = jnp.sum(nrm * nrm, -1) > 0
    feats = fpfh(p, nrm, nb)
    described = ok & has_n & (nb.count > 0)
    return FeatureCloud(points=p, normals=nrm, features=feats, valid=ok, described=described, voxel_size=vs,
                        overflow=vox.overflow, truncated=nb.truncated)


def match_features(fs, fsv, ft, ftv, mutual: bool = True, min_mutual: int = 0):
    """Nearest target feature of each source feature (L2, brute force).

    fs (Ns, F), ft (Nt, F) with masks fsv, ftv -> (idx (Ns,) int32, valid (Ns,) bool). mutual: keep
    pairs that are also the nearest source of their target, unless fewer than ``min_mutual`` are.
    (``argmin |a - b|^2 = argmax 2 a.b - |b|^2``, by ``lax.top_k``: twice as fast as argmin on CPU.)
    """
    inf = jnp.asarray(jnp.inf, fs.dtype)
    nt = jnp.where(ftv, jnp.sum(ft * ft, 1), inf)
    j = jax.lax.top_k(2.0 * (fs @ ft.T) - nt[None, :], 1)[1][:, 0].astype(jnp.int32)
    ok = fsv & ftv[j]
    if mutual:
        ns = jnp.where(fsv, jnp.sum(fs * fs, 1), inf)
        back = jax.lax.top_k(2.0 * (ft @ fs.T) - ns[None, :], 1)[1][:, 0]
        mut = ok & (back[j] == jnp.arange(fs.shape[0]))
        ok = jnp.where(jnp.sum(mut) >= min_mutual, mut, ok)
    return j, ok


@struct.dataclass
class GlobalResult:
    """transform (4, 4) source -> target, ``[s R, t]`` (target units); scale (); fitness () share of
    the downsampled source within ``icp_distance`` voxels of the target after the ICP refinement;
    inlier_rmse () target units; coverage () share of the downsampled target within ``icp_distance``
    of the aligned source; correspondences () feature matches used by the winning scale;
    ransac_inliers () of the winning hypothesis; voxel_size () target units."""

    transform: jnp.ndarray
    scale: jnp.ndarray
    fitness: jnp.ndarray
    inlier_rmse: jnp.ndarray
    coverage: jnp.ndarray
    correspondences: jnp.ndarray
    ransac_inliers: jnp.ndarray
    voxel_size: jnp.ndarray


def _refine(P, V, Ts, tf: FeatureCloud, o: GlobalOptions):
    """Point-to-plane ICP (Sim(3) with ``with_scale``) of source voxels P (B, C, 3) (valid V) from
    candidates Ts (B, 4, 4) against the target voxels: Gauss-Newton steps with grid nearest
    neighbours within ``icp_distance``, one candidate at a time (lax.map). Every candidate gets
    ``screen_iterations`` steps; the ``num_refined`` best (by sqrt(fitness x coverage)) continue to
    ``icp_iterations``. -> (transforms (R, 4, 4), fitness (R,), inlier RMSE (R,) voxels, target
    coverage (R,), candidate index (R,)) of the refined ones."""
    cell = o.icp_distance
    origin, _ = masked_bounds(tf.points, tf.valid)
    has_normal = tf.valid & (jnp.sum(tf.normals**2, -1) > 0)
    pts, ok, normals, has_normal = sort_by_cell(tf.points, tf.valid, cell, tf.normals, has_normal, origin=origin)
    step_opts = ICPOptions(max_correspondence_distance=o.icp_distance, with_scale=o.with_scale)
    M = tf.points.shape[0]
    nt = jnp.maximum(jnp.sum(tf.valid), 1)

    def run(steps):
        def one(args):
            p, m, T = args

            def match(T):
                q = p @ T[:3, :3].T + T[:3, 3]
                j, d2 = grid_nearest(q, pts, ok, cell, per_cell=o.icp_per_cell, origin=origin)
                inside = d2 <= jnp.asarray(o.icp_distance, q.dtype) ** 2
                return q, j, jnp.where(inside, d2, jnp.inf), m & inside

            def step(T, _):
                q, j, _, inl = match(T)
                U = point_to_plane_update(q, pts[j], normals[j], inl & has_normal[j], step_opts)
                return U @ T, None

            T, _ = jax.lax.scan(step, T, None, length=steps)
            _, j, d2, inl = match(T)
            cnt = jnp.sum(inl)
            fit = (cnt / jnp.maximum(jnp.sum(m), 1)).astype(p.dtype)
            rmse = jnp.sqrt(jnp.sum(jnp.where(inl, d2, 0.0)) / jnp.maximum(cnt, 1))
            covered = jnp.zeros((M,), bool).at[jnp.where(inl, j, M)].set(True, mode="drop")
            # a Sim(3) refinement may collapse the scale onto a patch: such a candidate scores 0
            s = sim3.scale(T)
            sane = (s > 1.0 / o.scale_tolerance**2) & (s < o.scale_tolerance**2) & jnp.all(jnp.isfinite(T))
            return T, jnp.where(sane, fit, 0.0), rmse, jnp.where(sane, jnp.sum(covered) / nt, 0.0).astype(p.dtype)

        return one

    R = min(o.num_refined, Ts.shape[0])
    T1, fit1, _, cov1 = jax.lax.map(run(o.screen_iterations), (P, V, Ts))
    _, best = jax.lax.top_k(jnp.sqrt(fit1 * cov1), R)
    T2, fit2, rmse2, cov2 = jax.lax.map(run(o.icp_iterations - o.screen_iterations), (P[best], V[best], T1[best]))
    return T2, fit2, rmse2, cov2, best


def target_voxel_size(target, valid=None, options: GlobalOptions = GlobalOptions()):
    """The voxel of :func:`global_registration`: ``options.voxel_size`` or ``voxel_fraction`` of the
    target's largest bounding-box side (target units; 0 for an empty target)."""
    if options.voxel_size is not None:
        return jnp.asarray(options.voxel_size, jnp.asarray(target).dtype)
    return adaptive_voxel_size(target, valid, 1.0 / options.voxel_fraction)


def global_registration(source, target, source_valid=None, target_valid=None, key=None,
                        options: GlobalOptions = GlobalOptions(), target_features: FeatureCloud | None = None
                        ) -> GlobalResult:
    """Initial alignment source (N, 3) -> target (M, 3) from any pose, partial overlap and (with
    ``options.scales`` / ``with_scale``) an unknown scale: FPFH + mutual matching + RANSAC/Umeyama,
    the best candidates refined by ICP on the downsampled clouds (see the module docstring).

    key: jax PRNG key (default ``key(0)``); target_features: the cached :func:`describe` of the
    target (with :func:`target_voxel_size`), else computed here. Jittable with ``options`` static;
    refine the result with :func:`cm3d.solvers.icp.icp` at full resolution. Empty clouds give the
    identity with fitness 0.
    """
    o = options
    target = jnp.asarray(target)
    source = jnp.asarray(source, target.dtype)
    dtype = target.dtype
    key = jax.random.key(0) if key is None else key
    sv = valid_points(source, source_valid)
    scales = jnp.asarray(o.scales, dtype)
    S, K = len(o.scales), o.num_candidates
    if target_features is None:  # one vmapped describe of the target and every scaled source
        tv = valid_points(target, target_valid)
        v = target_voxel_size(target, tv, o)
        L = max(source.shape[0], target.shape[0])
        pad = lambda x, m: (jnp.pad(x, ((0, L - x.shape[0]), (0, 0))), jnp.pad(m, (0, L - m.shape[0])))  # noqa: E731
        (ps, ms), (pt, mt) = pad(source, sv), pad(target, tv)
        pts = jnp.concatenate([pt[None], jnp.broadcast_to(ps, (S, L, 3))])
        msk = jnp.concatenate([mt[None], jnp.broadcast_to(ms, (S, L))])
        pre = jnp.concatenate([jnp.ones((1,), dtype), scales])
        fc = jax.vmap(lambda p, m, s: describe(p * s, m, v, o))(pts, msk, pre)
        tf = jax.tree.map(lambda x: x[0], fc)
        sfs = jax.tree.map(lambda x: x[1:], fc)
    else:
        tf = target_features
        v = tf.voxel_size
        sfs = jax.vmap(lambda s: describe(source * s, sv, v, o))(scales)
    vpos = jnp.where(v > 0, v, 1.0)

    def per_scale(sf, k):
        j, ok = match_features(sf.features, sf.described, tf.features, tf.described, o.mutual, o.min_mutual)
        Ts, inl = ransac(sf.points, tf.points[j], ok, k, o)
        return sf.points, sf.valid, Ts, inl, jnp.sum(ok)

    P, V, Ts, inl, ncorr = jax.vmap(per_scale)(sfs, jax.random.split(key, S))
    rep = lambda x: jnp.repeat(x, K, axis=0)  # noqa: E731
    Tr, fit, rmse, coverage, cand = _refine(rep(P), rep(V), Ts.reshape(S * K, 4, 4), tf, o)
    # precision (source fitness) x recall (target coverage): the source fitness alone prefers a
    # shrunken source, the coverage alone an enlarged one
    r = jnp.argmax(jnp.sqrt(fit * coverage))
    b = cand[r]
    Tv = Tr[r]
    A = Tv[:3, :3] * scales[b // K]
    T = jnp.eye(4, dtype=dtype).at[:3, :3].set(A).at[:3, 3].set(Tv[:3, 3] * vpos)
    ok = (v > 0) & jnp.any(V) & jnp.all(jnp.isfinite(T)) & (fit[r] > 0)
    T = jnp.where(ok, T, jnp.eye(4, dtype=dtype))
    z = jnp.zeros((), dtype)
    return GlobalResult(transform=T, scale=jnp.where(ok, sim3.scale(A), 1.0).astype(dtype),
                        fitness=jnp.where(ok, fit[r], z), inlier_rmse=jnp.where(ok, rmse[r] * v, z),
                        coverage=jnp.where(ok, coverage[r], z).astype(dtype),
                        correspondences=jnp.where(ok, ncorr[b // K], 0).astype(jnp.int32),
                        ransac_inliers=jnp.where(ok, inl.reshape(-1)[b], 0).astype(jnp.int32), voxel_size=v)
