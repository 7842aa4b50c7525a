"""The cognitive memory bank: an immutable pytree of static maps, recalled by descriptors.

Layout (capacities from :class:`MemoryConfig`, all static): per map ``m < max_maps`` a static point
cloud (``points``, ``normals``, ``conf``, ``colors``, ``point_valid``; voxel downsampled, in the
map's own frame and scale), its 3D descriptor ``cloud_desc`` and up to ``max_keyframes`` keyframe
descriptors ``kf_desc`` with hash codes ``kf_codes``. The *global feature table* is the flat view
``kf_desc.reshape(max_maps * max_keyframes, dim)`` with ``map_id = row // max_keyframes``
(:func:`global_table`), so it never goes out of sync with the maps. Each map also holds up to
``max_keypoints`` 3D keypoints (local RootSIFT descriptors lifted to the map frame) and up to
``max_floor_keypoints`` *floor* keypoints (SIFT of a top-down orthophoto of the floor,
:func:`cm3d.ops.keypoints.floor_features`: viewpoint-normalised, matched only among themselves); its
points are kept sorted by grid cell (:func:`sort_by_cell`) for neighbour search by binary search.

Recognition (:func:`identify`, pure and vmappable over queries): hashed 2D :func:`recall` of
``top_k`` candidates -> keypoint matching + Sim(3) RANSAC per candidate (3-point hypotheses, and
2-point hypotheses about both frames' estimated up axes: :func:`up_axis`, :func:`upright_pairs`)
-> of the best candidate's poses, the one with the most colour-consistent overlap -> Sim(3) ICP ->
accepted by the *acceptance model*: a linear score of the weak signals (vote share, keypoint
matches and inliers, their margin over the other candidates, screening overlap, ICP fitness / RMSE,
colour agreement: :data:`ACCEPTANCE_FEATURES`, :func:`acceptance_features`) with weights fitted on the
benchmark's tuning split (``MemoryConfig.accept_*``; empty weights: the AND of the hard thresholds of
:func:`verify`). Optionally (``cfg.fallback_yaws > 0``, off by default) a query the keypoint path
rejects gets a keypoint-free check of the same candidate: yaw hypotheses about both clouds' up axes
with scale from their floor-to-ceiling spans and translation from FFT-correlated wall occupancy grids
(:func:`global_hypotheses`), colour-gated Sim(3) ICP, stricter thresholds (:func:`_fallback_stage`).
:func:`remember` then updates the recalled map (:func:`update_map`) or stores a new one. Every visit
has its own unknown scale, so all transforms are Sim(3).

Capacity policy: inserting into a full bank is refused. The pure :func:`insert_map` returns the
bank unchanged and ``map_id = -1``; the host-side :func:`add_map` raises :class:`MemoryFullError`.
Maps are never evicted silently; :func:`remove_map` frees a slot explicitly.

Persistence (:func:`save` / :func:`load`): one file, ``MAGIC`` + a JSON header (format version,
config, array names, shapes, dtypes, SHA-256 of the payload) + the raw arrays; written atomically
(temporary file, fsync, rename), so an interrupted save leaves the previous bank intact. A
truncated or altered file fails to load with :class:`MemoryFileError`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import struct as pystruct

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from cm3d.data.atomic import atomic_write
from cm3d.ops import descriptors

MAGIC = b"CM3DMEM\x00"
GRID_CELL = 1.5  # a map's points are stored sorted by grid cells of this many map voxels (see
# sort_by_cell); the verifying ICP searches the 27 cells around a point, so its correspondence
# distance is one cell
FORMAT_VERSION = 3  # 2: 3D keypoints (kp_points, kp_desc, kp_valid); 3: floor keypoints (floor_kp_*)
READ_VERSIONS = (2, 3)  # a version-2 file loads with no floor keypoints (max_floor_keypoints = 0)


DESCRIPTOR_3D_DIMS = {"handcrafted": descriptors.CLOUD_DIM, "pointnet2": 512}

# the scores identify computes for its verified candidate, in the order of acceptance_features' vector (the
# acceptance model's inputs; counts enter as log(1 + n))
ACCEPTANCE_FEATURES = (
    "vote_share",  # share of the query's keyframes voting for the candidate (2D recall)
    "score_margin",  # its recall score (votes + w_cloud x 3D similarity) minus the best other candidate's
    "cloud_similarity",  # cosine of the 3D global descriptors
    "log_matches",  # strict keypoint matches (mutual + ratio test)
    "log_triangle_inliers",  # distinct RANSAC inliers of the triangle hypotheses
    "log_upright_inliers",  # ... of the upright pairs (= triangle's without them)
    "log_pose_inliers",  # distinct RANSAC inliers of the verified pose
    "inlier_margin",  # log(1 + keypoint inliers) minus the best other candidate's
    "screen_overlap",  # share of the screening voxels with a colour-consistent map point, chosen pose
    "log_icp_inliers",  # ICP inlier count
    "fitness",  # ICP fitness
    "rmse_voxels",  # ICP inlier RMSE in map voxels
    "colour_agreement",  # share of ICP inliers whose colours agree
    "scale_change",  # |log(ICP scale / RANSAC scale)|, at most 2 (a collapsed ICP is no outlier to the model)
    "log_scale",  # |log(ICP scale)| (query -> map), at most 2
)


class MemoryFullError(RuntimeError):
    """The bank has no free map slot (capacity policy: refuse, never evict silently)."""


class MemoryFileError(ValueError):
    """A bank file is missing, truncated, altered or of another version."""


@dataclasses.dataclass(frozen=True)
class MemoryConfig:
    """Capacities (static, shape-affecting) and recall thresholds of the memory bank."""

    max_maps: int = 64
    max_points: int = 8192
    max_keyframes: int = 16
    image_dim: int = descriptors.IMAGE_DIM
    cloud_dim: int | None = None  # 3D descriptor size: set from descriptor_3d when None
    descriptor_3d: str = "handcrafted"  # "handcrafted" (ops.descriptors) or "pointnet2" (cm3d.models.pointnet2)
    hash_bits: int = 64
    hash_seed: int = 0
    hash_radius: int = 22  # a table row is a candidate when its code is this close (Hamming)
    match_radius: float = 0.45  # ... and its exact L2 distance to the query is below this
    top_k: int = 3  # candidate maps passed on to verification
    w_cloud: float = 0.5  # weight of the 3D-descriptor similarity when re-ranking
    voxel_resolution: float = 60.0  # map voxel = largest extent / this (grown while over capacity)
    min_conf_quantile: float = 0.3  # static points: confidence above this quantile of the sequence
    pixel_stride: int = 4  # static points: every stride-th pixel
    # verification thresholds: tuned on the tuning split of experiments/memory_recall.py (never on its test split)
    min_fitness: float = 0.15  # verification: share of the query's ICP points with a map point nearby
    max_rmse: float = 0.775  # verification: ICP inlier RMSE, in map voxels
    normal_radius: float = 0.2  # neighbourhood cell for map normals (map units: VGGT-normalised)
    min_inliers: int = 38  # verification: absolute number of ICP inliers
    max_keypoints: int = 512  # 3D keypoints (local descriptors lifted to the map frame) per map
    max_floor_keypoints: int = 0  # floor orthophoto keypoints per map (ops.keypoints.floor_features; 0: none)
    keypoint_dim: int = 128  # local descriptor size (RootSIFT)
    ratio: float = 0.85  # keypoint matching: Lowe ratio against the best match elsewhere in 3D
    ransac_hypotheses: int = 256  # Sim(3) RANSAC: 3-point hypotheses per candidate
    upright_hypotheses: int = 128  # + 2-point hypotheses with both frames' up axes known (0: off; see upright_pairs)
    pose_candidates: int = 1  # distinct RANSAC poses kept per hypothesis generator (sim3_consensus_top), screened
    up_prior: tuple[float, float, float] = (0.0, -1.0, 0.0)  # a camera's rough up (OpenCV: -y) in its own frame
    up_max_angle: float = 35.0  # degrees: normals this close to up_prior vote for the up axis (floor, ceiling)
    ransac_scored: int = 128  # RANSAC scores at most this many matches (one per query keypoint cluster)
    screen_points: int = 64  # query voxels that pick between the RANSAC poses by colour-consistent overlap
    ransac_distance: float = 2.0  # keypoint inlier distance, in map voxels
    min_keypoint_inliers: int = 6  # verification: RANSAC inliers, distinct 3D points (keypoint_clusters)
    loose_descriptor: float = 0.6  # RANSAC scoring also counts mutual matches (no ratio test) below this L2
    cluster_separation: float = 2.0  # query keypoints closer than this (query voxels) are one 3D point
    scale_range: tuple[float, float] = (0.25, 4.0)  # plausible query -> map scale ratios
    icp_points: int = 256  # query voxels used by the verifying ICP (an even subsample)
    icp_iterations: int = 5
    max_colour_difference: float = 40.0  # RGB (0-255) distance for a colour-consistent ICP inlier
    min_colour_agreement: float = 0.725  # verification: share of colour-consistent ICP inliers
    grid_per_cell: int = 3  # ICP neighbour search: points looked at per grid cell (see GRID_CELL)
    verification: str = "full"  # "none" (2D recall only), "keypoints" (+ 3D RANSAC), "full" (+ ICP)
    # keypoint-free fallback (see global_hypotheses / _fallback_stage): when the keypoint path rejects, its
    # best candidate is registered from the clouds alone (+ its RANSAC poses) and accepted on stricter thresholds
    fallback_yaws: int = 0  # yaw hypotheses about the shared up axis (0: no fallback)
    fallback_grid: int = 64  # cells per side of the horizontal occupancy grids correlated by FFT
    fallback_points: int = 1024  # query wall voxels rasterised per yaw (an even subsample)
    fallback_refine: int = 4  # hypotheses refined by colour-gated ICP (the best screened ones)
    fallback_min_fitness: float = 0.8  # fallback acceptance (tuned like the above): ICP fitness ...
    fallback_max_rmse: float = 0.6  # ... inlier RMSE (map voxels) ...
    fallback_colour_difference: float = 15.0  # ... and the share of inliers within this RGB distance ...
    fallback_min_colour: float = 0.7  # ... at least this
    # acceptance model (see ACCEPTANCE_FEATURES, acceptance_features): when accept_weights is set (and
    # verification is "full"), identify accepts its candidate on the linear score
    #   sum(accept_weights * (features - accept_mean) / accept_scale) + accept_bias >= 0
    # instead of the AND of the thresholds above (hard checks kept: a stored map, finite transform, scale in
    # scale_range). A logistic regression on standardised features fitted on the tuning split of
    # experiments/memory_recall.py (--fit-acceptance prints these numbers); the operating threshold is folded
    # into accept_bias. Empty: the thresholds decide. The defaults: `memory_recall.py --fit-acceptance` (200 maps,
    # 1024 map keypoints + 512 floor keypoints, top_k=2, icp_points=256, cluster_separation=1.5: the experiment's
    # configuration).
    accept_weights: tuple[float, ...] = (0.30509, 0, 0, 0.53475, 0.63843, 0.52652, 0.57809, 0.37127, 0.30781, 0,
                                         -0.23286, -0.19504, 0.62967, 0, 0)
    accept_mean: tuple[float, ...] = (0.7018, 0, 0, 3.40222, 2.47035, 2.67332, 2.64383, 1.65895, 0.50891, 0, 0.70469,
                                      0.61156, 0.72638, 0, 0)
    accept_scale: tuple[float, ...] = (0.30617, 1, 1, 0.84247, 1.18459, 0.94767, 1.01166, 1.51742, 0.29364, 1, 0.25586,
                                       0.13643, 0.2478, 1, 1)
    accept_bias: float = 0.54522

    def __post_init__(self):
        if self.descriptor_3d not in DESCRIPTOR_3D_DIMS:
            raise ValueError(f"MemoryConfig.descriptor_3d: unknown {self.descriptor_3d!r} ({', '.join(DESCRIPTOR_3D_DIMS)})")
        if self.cloud_dim is None:
            object.__setattr__(self, "cloud_dim", DESCRIPTOR_3D_DIMS[self.descriptor_3d])
        elif self.cloud_dim != DESCRIPTOR_3D_DIMS[self.descriptor_3d]:
            raise ValueError(f"MemoryConfig.cloud_dim: {self.descriptor_3d} descriptors have "
                             f"{DESCRIPTOR_3D_DIMS[self.descriptor_3d]} dimensions, got {self.cloud_dim}")
        if self.verification not in ("none", "keypoints", "full"):
            raise ValueError(f"MemoryConfig.verification: unknown {self.verification!r} (none, keypoints, full)")
        if self.top_k < 1 or self.max_maps < 1 or self.max_points < 1 or self.max_keyframes < 1:
            raise ValueError("MemoryConfig: top_k, max_maps, max_points and max_keyframes must be >= 1")
        if self.max_keypoints < 3 or self.icp_points < 3 or self.ransac_hypotheses < 1:
            raise ValueError("MemoryConfig: max_keypoints and icp_points must be >= 3, ransac_hypotheses >= 1")
        if self.fallback_yaws < 0 or self.fallback_grid < 8 or self.fallback_points < 3 or self.fallback_refine < 1:
            raise ValueError("MemoryConfig: fallback_yaws must be >= 0, fallback_grid >= 8, fallback_points >= 3, "
                             "fallback_refine >= 1")
        if self.max_floor_keypoints < 0:
            raise ValueError(f"MemoryConfig.max_floor_keypoints: must be >= 0, got {self.max_floor_keypoints}")
        if self.pose_candidates < 1:
            raise ValueError(f"MemoryConfig.pose_candidates: must be >= 1, got {self.pose_candidates}")
        if self.upright_hypotheses < 0:
            raise ValueError(f"MemoryConfig.upright_hypotheses: must be >= 0, got {self.upright_hypotheses}")
        if len(self.up_prior) != 3 or not 0 < float(np.linalg.norm(self.up_prior)) < np.inf:
            raise ValueError(f"MemoryConfig.up_prior: need a non-zero 3-vector, got {self.up_prior}")
        if not 0 < self.up_max_angle < 90:
            raise ValueError(f"MemoryConfig.up_max_angle: need 0 < degrees < 90, got {self.up_max_angle}")
        if not 0 < self.scale_range[0] < self.scale_range[1]:
            raise ValueError(f"MemoryConfig.scale_range: need 0 < lo < hi, got {self.scale_range}")
        if self.accept_weights or self.accept_mean or self.accept_scale:
            n = len(ACCEPTANCE_FEATURES)
            for name in ("accept_weights", "accept_mean", "accept_scale"):
                v = getattr(self, name)
                if len(v) != n or not all(np.isfinite(v)):
                    raise ValueError(f"MemoryConfig.{name}: need {n} finite numbers (one per ACCEPTANCE_FEATURES "
                                     f"entry), got {len(v)}: {v}")
            if not all(x > 0 for x in self.accept_scale):
                raise ValueError(f"MemoryConfig.accept_scale: need positive numbers, got {self.accept_scale}")


@struct.dataclass
class MemoryBank:
    """See the module docstring. ``M = max_maps``, ``P = max_points``, ``K = max_keyframes``."""

    points: jax.Array  # (M, P, 3) float32
    normals: jax.Array  # (M, P, 3) float32
    conf: jax.Array  # (M, P) float32
    colors: jax.Array  # (M, P, 3) uint8
    point_valid: jax.Array  # (M, P) bool
    cloud_desc: jax.Array  # (M, D3) float32
    kf_desc: jax.Array  # (M, K, D2) float32
    kf_codes: jax.Array  # (M, K, W) uint32
    kf_valid: jax.Array  # (M, K) bool
    map_valid: jax.Array  # (M,) bool
    visits: jax.Array  # (M,) int32: how many sequences built or updated the map
    voxel_size: jax.Array  # (M,) float32: the map's voxel size (its own units)
    planes: jax.Array  # (bits, D2) float32: the LSH hyperplanes the codes were made with
    kp_points: jax.Array  # (M, N, 3) float32: 3D keypoints in the map frame (N = max_keypoints)
    kp_desc: jax.Array  # (M, N, Dk) float32: their unit local descriptors
    kp_valid: jax.Array  # (M, N) bool
    floor_kp_points: jax.Array  # (M, F, 3) float32: floor keypoints (F = max_floor_keypoints), map frame
    floor_kp_desc: jax.Array  # (M, F, Dk) float32
    floor_kp_valid: jax.Array  # (M, F) bool

    @property
    def num_maps(self) -> jax.Array:
        return jnp.sum(self.map_valid)


@struct.dataclass
class MapCloud:
    """One stored map's voxel cloud, in the map's frame: points, normals (P, 3), colours (P, 3) uint8,
    validity (P,) (all False when the map id was negative) and the map's voxel size."""

    points: jax.Array
    normals: jax.Array
    colors: jax.Array
    valid: jax.Array
    voxel_size: jax.Array


def map_cloud(bank: MemoryBank, map_id) -> MapCloud:
    """The cloud of map ``map_id`` (jittable; ``map_id < 0`` gives an all-invalid cloud)."""
    m = jnp.maximum(map_id, 0)
    return MapCloud(points=bank.points[m], normals=bank.normals[m], colors=bank.colors[m],
                    valid=bank.point_valid[m] & (map_id >= 0), voxel_size=bank.voxel_size[m])


def without_map(bank: MemoryBank, map_id) -> MemoryBank:
    """The bank with map ``map_id`` hidden from recall (jittable; ``map_id < 0`` hides nothing)."""
    M = bank.map_valid.shape[0]
    return bank.replace(map_valid=bank.map_valid & (jnp.arange(M) != map_id))


def capacities(bank: MemoryBank) -> dict[str, int]:
    """The bank's shape-fixing capacities, by their :class:`MemoryConfig` field names."""
    return dict(max_maps=bank.points.shape[0], max_points=bank.points.shape[1],
                max_keyframes=bank.kf_desc.shape[1], max_keypoints=bank.kp_points.shape[1],
                max_floor_keypoints=bank.floor_kp_points.shape[1])


def empty(cfg: MemoryConfig = MemoryConfig()) -> MemoryBank:
    """A bank with every slot free."""
    if cfg.hash_bits % 32:
        raise ValueError(f"MemoryConfig.hash_bits: must be a multiple of 32, got {cfg.hash_bits}")
    M, P, K = cfg.max_maps, cfg.max_points, cfg.max_keyframes
    return MemoryBank(
        points=jnp.zeros((M, P, 3), jnp.float32), normals=jnp.zeros((M, P, 3), jnp.float32),
        conf=jnp.zeros((M, P), jnp.float32), colors=jnp.zeros((M, P, 3), jnp.uint8),
        point_valid=jnp.zeros((M, P), bool), cloud_desc=jnp.zeros((M, cfg.cloud_dim), jnp.float32),
        kf_desc=jnp.zeros((M, K, cfg.image_dim), jnp.float32),
        kf_codes=jnp.zeros((M, K, cfg.hash_bits // 32), jnp.uint32), kf_valid=jnp.zeros((M, K), bool),
        map_valid=jnp.zeros((M,), bool), visits=jnp.zeros((M,), jnp.int32), voxel_size=jnp.zeros((M,), jnp.float32),
        planes=descriptors.hash_planes(cfg.image_dim, cfg.hash_bits, cfg.hash_seed).astype(jnp.float32),
        kp_points=jnp.zeros((M, cfg.max_keypoints, 3), jnp.float32),
        kp_desc=jnp.zeros((M, cfg.max_keypoints, cfg.keypoint_dim), jnp.float32),
        kp_valid=jnp.zeros((M, cfg.max_keypoints), bool),
        floor_kp_points=jnp.zeros((M, cfg.max_floor_keypoints, 3), jnp.float32),
        floor_kp_desc=jnp.zeros((M, cfg.max_floor_keypoints, cfg.keypoint_dim), jnp.float32),
        floor_kp_valid=jnp.zeros((M, cfg.max_floor_keypoints), bool),
    )


@struct.dataclass
class Keypoints:
    """3D keypoints of a sequence or map in its own frame: points (N, 3), unit local descriptors
    desc (N, Dk), valid (N,)."""

    points: jax.Array
    desc: jax.Array
    valid: jax.Array


def lift_keypoints(uv, desc, valid, depth, K, cam_to_world, capacity: int) -> Keypoints:
    """Detected keypoints lifted to 3D with the prior depth and poses, up to ``capacity``.

    uv (S, N, 2) pixels, desc (S, N, Dk), valid (S, N) (per frame, strongest first: e.g.
    :func:`cm3d.ops.keypoints.detect_sequence` on static pixels); depth (S, H, W); K (S, 3, 3);
    cam_to_world (S, 4, 4). A keypoint is kept when the depth at its pixel is positive and finite;
    the kept ones are taken round robin over frames (each frame's strongest first), so every
    frame is represented. Returns :class:`Keypoints` with N = ``capacity``.
    """
    uv, desc, valid, depth, K, cam_to_world = (jnp.asarray(a) for a in (uv, desc, valid, depth, K, cam_to_world))
    S, N = valid.shape
    H, W = depth.shape[1:]
    ui = jnp.clip(jnp.round(uv[..., 0]).astype(jnp.int32), 0, W - 1)
    vi = jnp.clip(jnp.round(uv[..., 1]).astype(jnp.int32), 0, H - 1)
    d = depth[jnp.arange(S)[:, None], vi, ui]
    ok = valid & (d > 0) & jnp.isfinite(d)
    pix = jnp.stack([uv[..., 0], uv[..., 1], jnp.ones_like(uv[..., 0])], -1)
    ray = jnp.einsum("sij,snj->sni", jnp.linalg.inv(K), pix)
    cam = ray * jnp.where(ok, d, 0.0)[..., None]
    world = jnp.einsum("sij,snj->sni", cam_to_world[:, :3, :3], cam) + cam_to_world[:, None, :3, 3]
    rank = jnp.cumsum(ok, axis=1) - 1
    priority = jnp.where(ok, rank * S + jnp.arange(S)[:, None], S * N + 1).reshape(-1)
    order = jnp.argsort(priority, stable=True)
    order = order[jnp.arange(capacity) % (S * N)]
    kv = ok.reshape(-1)[order] & (jnp.arange(capacity) < S * N)
    return Keypoints(points=jnp.where(kv[:, None], world.reshape(-1, 3)[order], 0.0),
                     desc=jnp.where(kv[:, None], desc.reshape(S * N, -1)[order], 0.0), valid=kv)


def _fit_keypoints(kp: "Keypoints | None", capacity: int, dim: int) -> Keypoints:
    """Keypoints padded (invalid) or cut to ``capacity`` (static shapes); None gives none."""
    if kp is None:
        return Keypoints(jnp.zeros((capacity, 3), jnp.float32), jnp.zeros((capacity, dim), jnp.float32),
                         jnp.zeros((capacity,), bool))
    n = kp.valid.shape[-1]
    if kp.desc.shape[-1] != dim:
        raise ValueError(f"keypoint descriptors: expected dimension {dim}, got {kp.desc.shape[-1]}")
    if n >= capacity:
        return Keypoints(kp.points[:capacity].astype(jnp.float32), kp.desc[:capacity].astype(jnp.float32),
                         kp.valid[:capacity].astype(bool))
    pad = capacity - n
    return Keypoints(jnp.pad(jnp.asarray(kp.points, jnp.float32), ((0, pad), (0, 0))),
                     jnp.pad(jnp.asarray(kp.desc, jnp.float32), ((0, pad), (0, 0))),
                     jnp.pad(jnp.asarray(kp.valid, bool), (0, pad)))


@struct.dataclass
class MapEntry:
    """One map's contents, already at the bank's capacities (P points, K keyframes); ``keypoints`` and
    ``floor_keypoints`` may have any capacity (padded or cut to the bank's when stored) or be None."""

    points: jax.Array  # (P, 3)
    normals: jax.Array  # (P, 3)
    conf: jax.Array  # (P,)
    colors: jax.Array  # (P, 3) uint8
    point_valid: jax.Array  # (P,)
    kf_desc: jax.Array  # (K, D2)
    kf_valid: jax.Array  # (K,)
    cloud_desc: jax.Array  # (D3,)
    voxel_size: jax.Array  # ()
    keypoints: Keypoints | None = None  # (Nq,) 3D keypoints in the entry's frame
    floor_keypoints: Keypoints | None = None  # (Fq,) floor orthophoto keypoints (ops.keypoints.floor_features)


def insert_map(bank: MemoryBank, entry: MapEntry) -> tuple[MemoryBank, jax.Array]:
    """Put ``entry`` in the first free slot: ``(bank, map_id)``; a full bank is returned
    unchanged with ``map_id = -1`` (pure and jittable; see :func:`add_map` for the host check)."""
    free = ~bank.map_valid
    slot = jnp.argmax(free)
    ok = free[slot]
    codes = descriptors.hash_codes(entry.kf_desc, bank.planes)
    kp = _fit_keypoints(entry.keypoints, bank.kp_valid.shape[1], bank.kp_desc.shape[2])
    fkp = _fit_keypoints(entry.floor_keypoints, bank.floor_kp_valid.shape[1], bank.floor_kp_desc.shape[2])
    vs = jnp.maximum(jnp.asarray(entry.voxel_size, jnp.float32), 1e-12)
    points, point_valid, normals, conf, colors = sort_by_cell(
        jnp.asarray(entry.points, jnp.float32), jnp.asarray(entry.point_valid, bool), vs * GRID_CELL,
        jnp.asarray(entry.normals), jnp.asarray(entry.conf), jnp.asarray(entry.colors))

    def put(field, value):
        return field.at[slot].set(jnp.where(ok, value.astype(field.dtype), field[slot]))

    new = bank.replace(
        points=put(bank.points, points), normals=put(bank.normals, normals),
        conf=put(bank.conf, conf), colors=put(bank.colors, colors),
        point_valid=put(bank.point_valid, point_valid), cloud_desc=put(bank.cloud_desc, entry.cloud_desc),
        kf_desc=put(bank.kf_desc, entry.kf_desc), kf_codes=put(bank.kf_codes, codes),
        kf_valid=put(bank.kf_valid, entry.kf_valid), map_valid=put(bank.map_valid, jnp.bool_(True)),
        visits=put(bank.visits, jnp.int32(1)), voxel_size=put(bank.voxel_size, entry.voxel_size),
        kp_points=put(bank.kp_points, kp.points), kp_desc=put(bank.kp_desc, kp.desc),
        kp_valid=put(bank.kp_valid, kp.valid), floor_kp_points=put(bank.floor_kp_points, fkp.points),
        floor_kp_desc=put(bank.floor_kp_desc, fkp.desc), floor_kp_valid=put(bank.floor_kp_valid, fkp.valid),
    )
    return new, jnp.where(ok, slot, -1).astype(jnp.int32)


def add_map(bank: MemoryBank, entry: MapEntry) -> tuple[MemoryBank, int]:
    """Host-side :func:`insert_map` that raises :class:`MemoryFullError` instead of returning -1."""
    if bool(jnp.all(bank.map_valid)):
        raise MemoryFullError(f"memory bank is full ({bank.map_valid.shape[0]} maps): remove a map "
                              "(cm3d memory rm) or use a larger MemoryConfig.max_maps")
    bank, map_id = insert_map(bank, entry)
    return bank, int(map_id)


def remove_map(bank: MemoryBank, map_id) -> MemoryBank:
    """Free slot ``map_id`` (its data is zeroed)."""
    keep = jnp.arange(bank.map_valid.shape[0]) != map_id

    def clear(x):
        return jnp.where(keep.reshape((-1,) + (1,) * (x.ndim - 1)), x, jnp.zeros_like(x))

    fields = {f.name: clear(getattr(bank, f.name)) for f in dataclasses.fields(bank) if f.name != "planes"}
    return bank.replace(**fields)


def global_table(bank: MemoryBank):
    """The global feature table: descriptors (M*K, D2), codes (M*K, W), valid (M*K,), map_id (M*K,)."""
    M, K, D = bank.kf_desc.shape
    valid = (bank.kf_valid & bank.map_valid[:, None]).reshape(-1)
    return (bank.kf_desc.reshape(M * K, D), bank.kf_codes.reshape(M * K, -1), valid,
            jnp.repeat(jnp.arange(M, dtype=jnp.int32), K))


@struct.dataclass
class Recall:
    """Recall of one query sequence: ``votes`` (M,) per map, ``scores`` (M,) after 3D re-ranking,
    ``candidates`` (top_k,) map ids best first (-1 = none), ``candidate_scores`` (top_k,)."""

    votes: jax.Array
    scores: jax.Array
    candidates: jax.Array
    candidate_scores: jax.Array


def recall(bank: MemoryBank, query_desc, query_valid, query_cloud_desc, cfg: MemoryConfig) -> Recall:
    """Vote for stored maps with a sequence's keyframe descriptors (Q, D2) and re-rank by 3D.

    Each valid query keyframe looks up the table rows whose hash code is within
    ``cfg.hash_radius`` bits (approximate), re-checks them by exact L2 (< ``cfg.match_radius``)
    and votes for the map of its nearest surviving row. Scores are the fraction of query keyframes
    voting for a map plus ``cfg.w_cloud`` times the cosine similarity of the 3D descriptors; maps
    without votes are never candidates.
    """
    table, codes, valid, map_id = global_table(bank)
    qcodes = descriptors.hash_codes(query_desc, bank.planes)
    near = descriptors.hamming(qcodes[:, None, :], codes[None, :, :]) <= cfg.hash_radius
    d2 = jnp.sum((query_desc[:, None, :] - table[None]) ** 2, -1)
    ok = near & valid[None] & query_valid[:, None] & (d2 < cfg.match_radius**2)
    best = first_argmin(jnp.where(ok, d2, jnp.inf), 1)
    has = jnp.any(ok, axis=1)
    M = bank.map_valid.shape[0]
    votes = jnp.zeros(M).at[map_id[best]].add(has.astype(jnp.float32))
    frac = votes / jnp.maximum(jnp.sum(query_valid), 1)
    sim3d = bank.cloud_desc @ query_cloud_desc
    scores = jnp.where((votes > 0) & bank.map_valid, frac + cfg.w_cloud * sim3d, -jnp.inf)
    top_scores, top = jax.lax.top_k(scores, min(cfg.top_k, M))
    if cfg.top_k > M:  # fewer maps than candidates: pad with "none"
        top_scores = jnp.concatenate([top_scores, jnp.full((cfg.top_k - M,), -jnp.inf, top_scores.dtype)])
        top = jnp.concatenate([top, jnp.zeros((cfg.top_k - M,), top.dtype)])
    return Recall(votes=votes, scores=scores, candidates=jnp.where(jnp.isfinite(top_scores), top, -1),
                  candidate_scores=top_scores)


def select_keyframes(desc, valid, threshold: float, max_keyframes: int):
    """Keyframes spaced evenly in feature space: frame 0 (the first valid one), then every frame
    whose descriptor is farther than ``threshold`` (L2) from the last keyframe's.

    desc (S, D), valid (S,) -> (indices (max_keyframes,) int32, kf_valid (max_keyframes,) bool).
    When more frames qualify than the capacity holds, an evenly spaced subset of them is kept
    (first and last included), so coverage of the sequence is preserved.
    """
    S = desc.shape[0]

    def body(last, x):
        d, ok = x
        far = jnp.sum((d - last) ** 2) > threshold**2
        first = jnp.all(last == 0)
        take = ok & (far | first)
        return jnp.where(take, d, last), take

    _, take = jax.lax.scan(body, jnp.zeros(desc.shape[1], desc.dtype), (desc, valid))
    n = jnp.sum(take)
    order = jnp.argsort(~take, stable=True)  # selected frames first, in time order
    pos = jnp.round(jnp.linspace(0.0, 1.0, max_keyframes) * jnp.maximum(n - 1, 0)).astype(jnp.int32)
    spread = order[pos]
    direct = order[jnp.arange(max_keyframes) % S]
    idx = jnp.where(n > max_keyframes, spread, direct)
    kf_valid = jnp.arange(max_keyframes) < jnp.minimum(n, max_keyframes)
    return jnp.where(kf_valid, idx, 0).astype(jnp.int32), kf_valid


# ----------------------------------------------------------------------------------------------
# Building, verifying, relocalising and updating maps


@struct.dataclass
class SequenceCloud:
    """The static, confident part of one sequence in its own (prior) frame: points (N, 3),
    colors (N, 3) uint8, conf (N,), valid (N,); N = frames x pixels / stride^2."""

    points: jax.Array
    colors: jax.Array
    conf: jax.Array
    valid: jax.Array


def sequence_cloud(depth, conf, K, cam_to_world, images, static, cfg: MemoryConfig) -> SequenceCloud:
    """Lift every ``cfg.pixel_stride``-th static pixel whose confidence is above the sequence's
    ``cfg.min_conf_quantile`` quantile (and depth > 0) to the world: (S, H, W) inputs."""
    from cm3d.ops import camera

    st = cfg.pixel_stride
    d = depth[:, ::st, ::st]
    c = conf[:, ::st, ::st]
    Ks = K.at[..., :2, :].divide(st)  # pixel (u, v) of the strided grid is (st u, st v) in full
    pts = camera.unproject(d, Ks, cam_to_world)
    ok = static[:, ::st, ::st] & (d > 0) & jnp.isfinite(d)
    thr = jnp.nanquantile(jnp.where(ok, c, jnp.nan), cfg.min_conf_quantile)
    ok = ok & (c >= thr)
    return SequenceCloud(points=pts.reshape(-1, 3), colors=images[:, ::st, ::st].reshape(-1, 3),
                         conf=c.reshape(-1), valid=ok.reshape(-1))


def cloud_descriptor(points, valid, cfg: MemoryConfig):
    """The map's 3D global descriptor (cfg.cloud_dim,) of a voxelised cloud, per ``cfg.descriptor_3d``:
    the handcrafted similarity-invariant histogram or the learned PointNet++ encoder (shipped weights)."""
    if cfg.descriptor_3d == "pointnet2":
        from cm3d.models import pointnet2  # imported on use: the handcrafted default needs no model

        return pointnet2.cloud_descriptor(points, valid)
    return descriptors.cloud_descriptor(points, valid)


def _downsample_to_capacity(points, valid, features, voxel_size, capacity: int):
    """Voxel downsample, growing the voxel by 1.25x until the occupied voxels fit ``capacity``."""
    from cm3d.ops.voxel import voxel_downsample

    def grid(vs):
        return voxel_downsample(points, vs, valid, features, capacity=capacity)

    def cond(c):
        vs, i = c
        return (grid(vs).count > capacity) & (i < 12)

    vs, _ = jax.lax.while_loop(cond, lambda c: (c[0] * 1.25, c[1] + 1), (jnp.asarray(voxel_size, jnp.float32), 0))
    return grid(vs), vs


def _entry_from_points(points, colors, conf, valid, kf_desc, kf_valid, voxel_size, cfg: MemoryConfig,
                       min_support: float = 0.0) -> MapEntry:
    """Downsample to the bank's capacity and describe (see :func:`build_entry`)."""
    from cm3d.ops.neighbors import estimate_normals

    feats = jnp.concatenate([colors.astype(jnp.float32), conf[:, None]], axis=1)
    vox, vs = _downsample_to_capacity(points, valid, feats, voxel_size, cfg.max_points)
    if min_support > 0:  # voxels that few samples fell into: stray points, not surface (build_entry)
        med = jnp.nanmedian(jnp.where(vox.valid, vox.weight, jnp.nan))
        keep = vox.valid & (vox.weight >= min_support * med)
        vox = vox.replace(points=jnp.where(keep[:, None], vox.points, 0.0), valid=keep)
    normals = estimate_normals(vox.points, vox.valid, k=16, radius=cfg.normal_radius)
    return MapEntry(points=vox.points, normals=jnp.where(vox.valid[:, None], normals, 0.0),
                    conf=vox.features[:, 3], colors=jnp.clip(jnp.round(vox.features[:, :3]), 0, 255).astype(jnp.uint8),
                    point_valid=vox.valid, kf_desc=kf_desc, kf_valid=kf_valid,
                    cloud_desc=cloud_descriptor(vox.points, vox.valid, cfg), voxel_size=vs)


def _clean_keypoints(kp: Keypoints | None) -> Keypoints | None:
    """Keypoints with non-finite points or descriptors marked invalid (and zeroed), float32."""
    if kp is None:
        return None
    ok = jnp.asarray(kp.valid, bool) & jnp.all(jnp.isfinite(kp.points), -1) & jnp.all(jnp.isfinite(kp.desc), -1)
    return Keypoints(jnp.where(ok[:, None], kp.points, 0.0).astype(jnp.float32),
                     jnp.where(ok[:, None], kp.desc, 0.0).astype(jnp.float32), ok)


def build_entry(cloud: SequenceCloud, kf_desc, kf_valid, cfg: MemoryConfig,
                keypoints: Keypoints | None = None, min_support: float = 0.0,
                floor_keypoints: Keypoints | None = None) -> MapEntry:
    """A new map from a sequence: adaptive voxel size from the scene extent, mean point, colour and
    confidence per voxel, PCA normals, the 3D descriptor, the keyframe descriptors and (optional)
    the sequence's 3D keypoints (:func:`lift_keypoints`, same frame as ``cloud``) and (optional) its
    floor keypoints (:func:`cm3d.ops.keypoints.floor_features` on the same priors, as :class:`Keypoints`).

    ``min_support`` (a share, 0 = keep all): voxels with fewer samples than this share of the median
    voxel's are dropped. A map is capacity-bound, so its voxels are coarse (0.09-0.13 m at 384x512)
    and a stray sample (a mover the mask missed, a grazing or far pixel) weighs as much as a voxel of
    surface; measured on the camera-pose revisits, 0.2 lowers a window map's accuracy error
    (mean distance to the true surface) by 20-30 % for 20-25 % fewer voxels."""
    from cm3d.ops.voxel import adaptive_voxel_size

    vs = adaptive_voxel_size(cloud.points, cloud.valid, cfg.voxel_resolution)
    entry = _entry_from_points(cloud.points, cloud.colors, cloud.conf, cloud.valid, kf_desc, kf_valid, vs, cfg,
                               min_support)
    return entry.replace(keypoints=_clean_keypoints(keypoints), floor_keypoints=_clean_keypoints(floor_keypoints))


@struct.dataclass
class Verification:
    """Geometric verification of one candidate map: accepted; transform (4, 4) query -> map
    (Sim(3) ``[s R, t]``) and its scale; keypoint ``matches`` and RANSAC ``keypoint_inliers``;
    ICP ``fitness`` (share of the query's ICP points with a map point within ``icp_distance``),
    ``inlier_count``, ``inlier_rmse`` (map units) and ``colour_agreement`` (share of ICP inliers
    whose stored colour agrees with the query's)."""

    accepted: jax.Array
    transform: jax.Array
    scale: jax.Array
    matches: jax.Array
    keypoint_inliers: jax.Array
    fitness: jax.Array
    inlier_count: jax.Array
    inlier_rmse: jax.Array
    colour_agreement: jax.Array


def first_argmin(x, axis: int):
    """``jnp.argmin(x, axis)`` for arrays without NaN (the first index of the minimum) as two plain
    reductions (the min, then the smallest index reaching it): XLA's CPU backend runs them faster than
    argmin's (value, index) reduction, which was a large part of keypoint matching's time."""
    x = jnp.asarray(x)
    low = jnp.min(x, axis=axis, keepdims=True)
    shape = [1] * x.ndim
    shape[axis] = x.shape[axis]
    iota = jnp.arange(x.shape[axis], dtype=jnp.int32).reshape(shape)
    return jnp.min(jnp.where(x == low, iota, x.shape[axis] - 1), axis=axis)


def _nearest_descriptors(d2, m_points, ratio: float, min_separation):
    """From squared descriptor distances d2 (Nq, Nm) (inf for invalid pairs): the nearest map keypoint j
    (Nq,), its distance (Nq,), whether the match is mutual (Nq,) and whether it passes the 3D-aware ratio
    test (Nq,) (see :func:`match_keypoints`). Squared 3D distances to the best match's point are expanded
    as |a|^2 + |b|^2 - 2 a.b (one small matrix product instead of an (Nq, Nm, 3) difference)."""
    j = first_argmin(d2, 1)
    best = jnp.min(d2, axis=1)
    pj = m_points[j]
    sq = jnp.sum(m_points**2, -1)
    far = sq[None, :] + sq[j][:, None] - 2.0 * (pj @ m_points.T) > min_separation**2
    second = jnp.min(jnp.where(far, d2, jnp.inf), axis=1)
    mutual = first_argmin(d2, 0)[j] == jnp.arange(d2.shape[0])
    return j, best, mutual, jnp.isfinite(best) & (best <= ratio**2 * second)


def _descriptor_d2(q: Keypoints, m: Keypoints):
    """(Nq, Nm) squared L2 distances of unit descriptors, inf for pairs with an invalid keypoint."""
    return jnp.where(q.valid[:, None] & m.valid[None, :], 2.0 - 2.0 * (q.desc @ m.desc.T), jnp.inf)


def match_keypoints(q: Keypoints, m: Keypoints, ratio: float, min_separation):
    """Mutual nearest neighbours in descriptor space with a 3D-aware ratio test.

    The second-best match is searched among map keypoints farther than ``min_separation`` (map
    units) from the best one, so repeated views of one 3D point do not fail the ratio test.
    Returns (j (Nq,) map index per query keypoint, ok (Nq,) bool).
    """
    q = jax.tree.map(jnp.asarray, q)
    m = jax.tree.map(jnp.asarray, m)
    j, _, mutual, ratio_ok = _nearest_descriptors(_descriptor_d2(q, m), m.points, ratio, min_separation)
    return j, q.valid & mutual & ratio_ok


def _similarity(s, R, t):
    from cm3d.solvers.align import similarity_matrix

    return similarity_matrix(s, R, t)


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


def keypoint_clusters(points, valid, separation):
    """Cluster id (N,) int32 of each keypoint: the index of the first valid keypoint closer than
    ``separation`` (itself when none is earlier). Keypoints of one 3D point seen in several frames
    share an id, so counting distinct ids counts 3D points, not views (:func:`distinct_count`)."""
    points, valid = jnp.asarray(points), jnp.asarray(valid, bool)
    near = (jnp.sum((points[:, None] - points[None]) ** 2, -1) < separation**2) & valid[None, :] & valid[:, None]
    first = jnp.argmax(near, axis=1)  # the earliest close keypoint (itself at worst)
    return jnp.where(valid, first, jnp.arange(points.shape[0])).astype(jnp.int32)


def distinct_count(mask, cluster):
    """Number of distinct ``cluster`` ids among the True entries of ``mask`` (..., N)."""
    n = mask.shape[-1]
    hit = jnp.zeros(mask.shape[:-1] + (n,), jnp.int32).at[..., cluster].max(mask.astype(jnp.int32))
    return jnp.sum(hit, -1)


def up_axis(normals, valid, prior=(0.0, -1.0, 0.0), max_angle: float = 35.0):
    """The up (gravity) axis (3,) of a cloud in its own frame, from its normals (N, 3): the principal
    direction of the unit normals within ``max_angle`` degrees of ``prior`` (up or down: floor, ceiling,
    table tops), signed like ``prior``; ``prior`` (normalised) when fewer than 3 normals qualify.
    A camera held roughly upright (the first camera defines a visit's frame) makes the prior good to a
    few tens of degrees; the floor and ceiling make the estimate good to about a degree."""
    normals = jnp.asarray(normals, jnp.float32)
    prior = jnp.asarray(prior, jnp.float32)
    prior = prior / jnp.linalg.norm(prior)
    unit = jnp.abs(jnp.sum(normals**2, -1) - 1.0) < 0.1
    near = jnp.abs(normals @ prior) > np.cos(np.radians(max_angle))
    w = (jnp.asarray(valid, bool) & unit & near).astype(jnp.float32)
    _, vecs = jnp.linalg.eigh(jnp.einsum("n,ni,nj->ij", w, normals, normals))
    u = vecs[:, -1]
    u = jnp.where(u @ prior < 0, -u, u)
    return jnp.where(jnp.sum(w) >= 3, u, prior)


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
    order = jnp.argsort(~ok, stable=True)
    idx = order[jax.random.randint(key, (num_hypotheses, 2), 0, jnp.maximum(n_ok, 1))]
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
    ``cluster`` (N,): :func:`keypoint_clusters` of ``src``, so a refit is kept when it does not
    lose distinct 3D points (several views of one point count once). See :func:`sim3_consensus`.
    """
    src, dst, ok = jnp.asarray(src, jnp.float32), jnp.asarray(dst, jnp.float32), jnp.asarray(ok, bool)
    hyps = triangle_hypotheses(src, dst, ok, key, num_hypotheses)
    return sim3_consensus(src, dst, hyps, ok if score_ok is None else score_ok, threshold, scale_range, cluster)


def triangle_hypotheses(src, dst, ok, key, num_hypotheses: int):
    """``num_hypotheses`` random 3-point Sim(3) hypotheses (:func:`triangle_sim3`) from the
    correspondences ``src[i] -> dst[i]`` where ``ok``: (s, R, t, consistent) with a leading axis."""
    n_ok = jnp.sum(ok)
    order = jnp.argsort(~ok, stable=True)  # the usable correspondences first
    idx = order[jax.random.randint(key, (num_hypotheses, 3), 0, jnp.maximum(n_ok, 1))]
    return jax.vmap(lambda i: triangle_sim3(src[i], dst[i]))(idx)


def sim3_consensus(src, dst, hypotheses, score_ok, threshold, scale_range, cluster=None):
    """The best of the Sim(3) ``hypotheses`` ``(s (H,), R (H, 3, 3), t (H, 3), consistent (H,))`` by
    correspondences ``src[i] -> dst[i]`` (where ``score_ok``) within ``threshold``, refitted by
    Umeyama on its inliers twice (a refit is kept when it loses no inlier, distinct 3D points when
    ``cluster`` is given). Returns (transform (4, 4), scale, inliers (N,) bool; none if no
    hypothesis is consistent, with a plausible scale, and has an inlier)."""
    T, scale, inl = sim3_consensus_top(src, dst, hypotheses, score_ok, threshold, scale_range, cluster, keep=1)
    return T[0], scale[0], inl[0]


def distinct_best(pred, score, score_ok, threshold, keep: int, same_share: float = 0.5):
    """Greedy non-maximum suppression of pose hypotheses: indices (keep,) of the best-scoring ones that
    are *distinct* poses, and whether each exists (keep,) bool. ``pred`` (H, N, 3): each hypothesis's
    prediction of the correspondences' sources; two hypotheses are the same pose when they predict at
    least ``same_share`` of the scored correspondences (``score_ok`` (N,)) within ``threshold`` of each
    other. ``score`` (H,): hypotheses with a score <= 0 are never kept."""
    n = jnp.maximum(jnp.sum(score_ok), 1)
    alive = score > 0
    picks, exists = [], []
    for _ in range(keep):
        h = jnp.argmax(jnp.where(alive, score, -1))
        picks.append(h)
        exists.append(alive[h])
        near = score_ok[None] & (jnp.sum((pred - pred[h][None]) ** 2, -1) < threshold**2)
        alive = alive & (jnp.sum(near, 1) < same_share * n)
    return jnp.stack(picks), jnp.stack(exists)


def sim3_consensus_top(src, dst, hypotheses, score_ok, threshold, scale_range, cluster=None, keep: int = 1):
    """:func:`sim3_consensus` keeping the ``keep`` best *distinct* poses (:func:`distinct_best`), each
    refitted the same way: (transforms (keep, 4, 4), scales (keep,), inliers (keep, N) bool; a pose that
    does not exist has no inlier). A box room's wrong poses often collect as many chance inliers as
    the right one: the runners-up go on to a cheaper check (:func:`_screen_poses`)."""
    from cm3d.solvers.align import umeyama

    src, dst = jnp.asarray(src, jnp.float32), jnp.asarray(dst, jnp.float32)
    score_ok = jnp.asarray(score_ok, bool)
    count = jnp.sum if cluster is None else (lambda m: distinct_count(m, cluster))
    s, R, t, good = hypotheses
    pred = s[:, None, None] * jnp.einsum("hij,nj->hni", R, src) + t[:, None, :]
    inl = score_ok[None] & (jnp.sum((pred - dst[None]) ** 2, -1) < threshold**2)
    plausible = good & (s >= scale_range[0]) & (s <= scale_range[1]) & jnp.all(jnp.isfinite(pred), (1, 2))
    score = jnp.where(plausible, jnp.sum(inl, 1), 0)

    def refit(h, ex):
        best = inl[h]
        T = _similarity(s[h], R[h], t[h])
        for _ in range(2):
            s2, R2, t2 = umeyama(src, dst, best, with_scale=True)
            T2 = _similarity(s2, R2, t2)
            inl2 = score_ok & (jnp.sum((src @ T2[:3, :3].T + T2[:3, 3] - dst) ** 2, -1) < threshold**2)
            better = ((count(inl2) >= count(best)) & (s2 >= scale_range[0]) & (s2 <= scale_range[1])
                      & jnp.all(jnp.isfinite(T2)))
            T = jnp.where(better, T2, T)
            best = jnp.where(better, inl2, best)
        return T, jnp.cbrt(jnp.linalg.det(T[:3, :3])), best & ex

    if keep == 1:
        h = jnp.argmax(score)
        return jax.tree.map(lambda a: a[None], refit(h, score[h] > 0))
    hs, exists = distinct_best(pred, score, score_ok, threshold, keep)
    return jax.vmap(refit)(hs, exists)


def _even_subsample(points, valid, n: int):
    """``n`` of the valid points, evenly spread over them (the first n when fewer): (n, 3), (n,)."""
    order = jnp.argsort(~valid, stable=True)
    count = jnp.sum(valid)
    i = jnp.arange(n)
    pos = jnp.where(count > n, (i * count) // n, i)
    idx = order[jnp.minimum(pos, valid.shape[0] - 1)]
    return points[idx], i < count, idx


_CELL_BITS = 10  # cell coordinates in [0, 1024) per axis after the offset below
_NO_CELL = jnp.iinfo(jnp.int32).max


def cell_codes(points, valid, cell):
    """Integer code (N,) int32 of each point's grid cell ``floor(p / cell)`` (offset so that the
    grid spans +-512 cells around the origin; farther points are clipped); invalid: INT32_MAX."""
    c = jnp.clip(jnp.floor(points / cell).astype(jnp.int32) + (1 << (_CELL_BITS - 1)), 0, (1 << _CELL_BITS) - 1)
    code = c[..., 0] + (c[..., 1] << _CELL_BITS) + (c[..., 2] << (2 * _CELL_BITS))
    return jnp.where(valid, code, _NO_CELL)


def sort_by_cell(points, valid, cell, *others):
    """Reorder a map's points (and any per-point arrays) by :func:`cell_codes` (invalid last): the
    bank's layout, which lets :func:`grid_nearest` find neighbours by binary search."""
    order = jnp.argsort(cell_codes(points, valid, cell), stable=True)
    return (points[order], valid[order]) + tuple(o[order] for o in others)


def grid_nearest(q, points, valid, cell, reach: int = 1, per_cell: int = 2):
    """Nearest map point to each query q (n, 3) among the points of the cells within ``reach``
    cells (``points`` sorted by :func:`sort_by_cell`); exact for neighbours closer than
    ``reach * cell`` when no cell holds more than ``per_cell`` points (a map voxel-downsampled
    finer than ``cell`` holds about one or two). Codes run along x first, so the 2 reach + 1 cells
    of each (y, z) row are one contiguous range: one binary search per row.
    Returns (index (n,), squared distance (n,), inf if none)."""
    q, points, valid = jnp.asarray(q), jnp.asarray(points), jnp.asarray(valid, bool)
    codes = cell_codes(points, valid, cell)
    r = jnp.arange(-reach, reach + 1)
    dy, dz = (a.reshape(-1) for a in jnp.meshgrid(r, r, indexing="ij"))
    base = jnp.floor(q / cell).astype(jnp.int32) + (1 << (_CELL_BITS - 1))
    hi_c = (1 << _CELL_BITS) - 1
    x0 = jnp.clip(base[:, 0] - reach, 0, hi_c)[:, None]
    x1 = jnp.clip(base[:, 0] + reach, 0, hi_c)[:, None]
    y = base[:, 1:2] + dy[None]
    z = base[:, 2:3] + dz[None]
    inside = (y >= 0) & (y <= hi_c) & (z >= 0) & (z <= hi_c) & (base[:, 0:1] + reach >= 0) & (base[:, 0:1] - reach <= hi_c)
    row = (y << _CELL_BITS) + (z << (2 * _CELL_BITS))
    lo, hi = x0 + row, x1 + row  # (n, R) code range of each row
    start = jnp.searchsorted(codes, lo.reshape(-1), side="left").reshape(lo.shape)
    width = (2 * reach + 1) * per_cell
    idx = jnp.minimum(start[..., None] + jnp.arange(width), points.shape[0] - 1)  # (n, R, width)
    c = codes[idx]
    hit = inside[..., None] & (c >= lo[..., None]) & (c <= hi[..., None])
    d2 = jnp.where(hit, jnp.sum((points[idx] - q[:, None, None, :]) ** 2, -1), jnp.inf).reshape(q.shape[0], -1)
    k = first_argmin(d2, 1)
    n = jnp.arange(q.shape[0])
    return idx.reshape(q.shape[0], -1)[n, k], d2[n, k]


def icp_sim3(src, src_valid, dst, dst_valid, init, distance, iterations: int, cell=None, reach: int = 1,
             per_cell: int = 2):
    """Trimmed point-to-point Sim(3) ICP of ``src`` (n, 3) to ``dst`` (P, 3) with nearest neighbours
    within ``distance``: brute force when ``cell`` is None, else :func:`grid_nearest` (``dst`` sorted
    by :func:`sort_by_cell` at ``cell``). Returns (transform, inlier_count, fitness, rmse,
    nearest index (n,), inlier mask (n,)) at the final transform."""
    from cm3d.solvers.align import umeyama

    src, dst = jnp.asarray(src, jnp.float32), jnp.asarray(dst, jnp.float32)
    src_valid, dst_valid = jnp.asarray(src_valid, bool), jnp.asarray(dst_valid, bool)
    dn = jnp.sum(dst**2, -1)

    def nearest(T):
        q = src @ T[:3, :3].T + T[:3, 3]
        if cell is None:
            d2 = jnp.maximum(jnp.sum(q**2, -1)[:, None] + dn[None] - 2.0 * q @ dst.T, 0.0)
            d2 = jnp.where(dst_valid[None], d2, jnp.inf)
            j = jnp.argmin(d2, 1)
            dmin = jnp.take_along_axis(d2, j[:, None], 1)[:, 0]
        else:
            j, dmin = grid_nearest(q, dst, dst_valid, cell, reach, per_cell)
        return j, dmin, src_valid & (dmin < distance**2)

    def step(T, _):
        j, _, inl = nearest(T)
        s, R, t = umeyama(src, dst[j], inl, with_scale=True)
        T2 = _similarity(s, R, t)
        ok = (jnp.sum(inl) >= 3) & jnp.all(jnp.isfinite(T2))
        return jnp.where(ok, T2, T), None

    T, _ = jax.lax.scan(step, init, None, length=iterations)
    j, dmin, inl = nearest(T)
    count = jnp.sum(inl)
    fitness = count / jnp.maximum(jnp.sum(src_valid), 1)
    rmse = jnp.sqrt(jnp.sum(jnp.where(inl, dmin, 0.0)) / jnp.maximum(count, 1))
    return T, count, fitness, rmse, j, inl


def _keypoint_stage(bank: MemoryBank, m, query: Keypoints, floor: Keypoints | None, cluster, frame_q, sep_q,
                    cfg: MemoryConfig, key):
    """Match the query's keypoints with map ``m``'s and fit Sim(3) by RANSAC: (T (G, 4, 4), scale
    (G,), strict matches, distinct inliers (G,)), one pose per hypothesis generator (G = 1, or 2 with
    ``cfg.upright_hypotheses``: the triangle RANSAC's, then the upright pairs'). Triangle hypotheses
    come from the strict matches (mutual + ratio test); they are scored on the strict and the loose
    matches (mutual, descriptor distance below ``cfg.loose_descriptor``, no ratio test), one per
    query keypoint cluster (its best match; at most ``cfg.ransac_scored``), so a hypothesis is
    scored by distinct 3D points, not by views of one point. ``cluster``: :func:`keypoint_clusters`
    of the query. With ``cfg.upright_hypotheses`` a second consensus
    draws 2-point hypotheses (:func:`upright_pairs`) from the strict *and* loose matches, given the
    query's upright frame ``frame_q`` and the map's (both :func:`upright_frame` of :func:`up_axis`),
    scored the same way; pairs closer than ``sep_q`` (query units: one cluster) are not drawn.
    ``floor`` (None: none): the query's floor keypoints, matched with the map's floor keypoints only
    (another kind of descriptor); their matches join the image keypoints' (``cluster`` covers both,
    image keypoints first)."""
    vs = jnp.maximum(bank.voxel_size[m], 1e-12)
    thr = cfg.ransac_distance * vs
    kinds = [(query, Keypoints(bank.kp_points[m], bank.kp_desc[m], bank.kp_valid[m]))]
    if floor is not None:
        kinds.append((floor, Keypoints(bank.floor_kp_points[m], bank.floor_kp_desc[m], bank.floor_kp_valid[m])))
    parts = []
    for q, mk in kinds:  # (match_keypoints per kind)
        j, best, mutual, ratio_ok = _nearest_descriptors(_descriptor_d2(q, mk), mk.points, cfg.ratio, thr)
        parts.append((q.points, mk.points[j], q.valid & mutual & ratio_ok, q.valid & mutual, best))
    src, dst, strict, mutual, best = (jnp.concatenate(x) for x in zip(*parts))
    n = jnp.arange(src.shape[0])
    ok = strict | (mutual & (best < cfg.loose_descriptor**2))
    rank = jnp.where(ok, best, jnp.inf)
    tops = ok & (rank <= jax.ops.segment_min(rank, cluster, num_segments=n.shape[0])[cluster])
    first = jax.ops.segment_min(jnp.where(tops, n, n.shape[0]), cluster, num_segments=n.shape[0])
    rep = tops & (first[cluster] == n)  # one per cluster: its best match (ties: the first)
    # the scored matches, compacted: the ransac_scored closest in descriptor space when there are more
    sel = jnp.argsort(jnp.where(rep, best, jnp.inf), stable=True)[: min(cfg.ransac_scored, n.shape[0])]
    scored = (src[sel], dst[sel], rep[sel])
    gens = [triangle_hypotheses(src, dst, strict, key, cfg.ransac_hypotheses)]
    if cfg.upright_hypotheses:
        frame_m = upright_frame(up_axis(bank.normals[m], bank.point_valid[m], cfg.up_prior, cfg.up_max_angle))
        gens.append(upright_pairs(src, dst, ok, jax.random.fold_in(key, 1), cfg.upright_hypotheses, frame_q, frame_m,
                                  sep_q, cfg.scale_range))
    # one scored match per query cluster: inliers are distinct 3D points, and a plain count counts them
    Ts, scales, inls = zip(*(sim3_consensus_top(*scored[:2], h, scored[2], thr, cfg.scale_range,
                                                keep=cfg.pose_candidates) for h in gens))
    inls = jnp.sum(jnp.concatenate(inls), -1)
    return (jnp.concatenate(Ts), jnp.concatenate(scales), jnp.sum(strict).astype(jnp.int32),
            inls.astype(jnp.int32))


def _screen_poses(bank: MemoryBank, m, entry: MapEntry, Ts, cfg: MemoryConfig):
    """Colour-consistent overlap (G,) of the query under each pose Ts (G, 4, 4): how many of
    ``cfg.screen_points`` query voxels have a map point within one grid cell whose colour agrees
    (one nearest-neighbour step, no ICP)."""
    src, sv, idx = _even_subsample(entry.points, entry.point_valid, cfg.screen_points)
    vs = jnp.maximum(bank.voxel_size[m], 1e-12)
    cell = GRID_CELL * vs

    def one(T):
        j, d2 = grid_nearest(src @ T[:3, :3].T + T[:3, 3], bank.points[m], bank.point_valid[m], cell,
                             per_cell=cfg.grid_per_cell)
        dc = jnp.linalg.norm(entry.colors[idx].astype(jnp.float32) - bank.colors[m][j].astype(jnp.float32), axis=-1)
        return jnp.sum(sv & (d2 < cell**2) & (dc <= cfg.max_colour_difference))

    return jax.vmap(one)(Ts)


def _icp_stage(bank: MemoryBank, m, entry: MapEntry, init, cfg: MemoryConfig):
    """Sim(3) ICP of an even subsample of the query's voxels against map ``m`` from ``init``:
    (T, inlier count, fitness, rmse, colour agreement: share of inliers whose colour is within
    ``cfg.max_colour_difference`` of their map point's)."""
    src, sv, idx = _even_subsample(entry.points, entry.point_valid, cfg.icp_points)
    vs = jnp.maximum(bank.voxel_size[m], 1e-12)
    cell = GRID_CELL * vs
    T, count, fitness, rmse, j, inl = icp_sim3(src, sv, bank.points[m], bank.point_valid[m], init, cell,
                                               cfg.icp_iterations, cell=cell, per_cell=cfg.grid_per_cell)
    dc = jnp.linalg.norm(entry.colors[idx].astype(jnp.float32) - bank.colors[m][j].astype(jnp.float32), axis=-1)
    agree = jnp.sum(inl & (dc <= cfg.max_colour_difference)) / jnp.maximum(count, 1)
    return T, count, fitness, rmse, agree


def _decide(bank, m, T, scale, matches, kp_inliers, icp, cfg: MemoryConfig) -> Verification:
    """Acceptance per ``cfg.verification`` (see :func:`verify`)."""
    vs = jnp.maximum(bank.voxel_size[m], 1e-12)
    present = (m >= 0) & bank.map_valid[jnp.maximum(m, 0)]
    if cfg.verification == "none":
        eye = jnp.eye(4, dtype=jnp.float32)
        z = jnp.zeros((), jnp.float32)
        return Verification(accepted=present, transform=eye, scale=jnp.ones((), jnp.float32), matches=matches,
                            keypoint_inliers=kp_inliers, fitness=z, inlier_count=jnp.zeros((), jnp.int32), inlier_rmse=z,
                            colour_agreement=z)
    ok = present & (kp_inliers >= cfg.min_keypoint_inliers) & jnp.all(jnp.isfinite(T))
    if icp is None:
        z = jnp.zeros((), jnp.float32)
        return Verification(accepted=ok, transform=T, scale=scale, matches=matches, keypoint_inliers=kp_inliers,
                            fitness=z, inlier_count=jnp.zeros((), jnp.int32), inlier_rmse=z, colour_agreement=z)
    T2, count, fitness, rmse, agree = icp
    scale2 = jnp.cbrt(jnp.linalg.det(T2[:3, :3]))
    ok = (ok & (count >= cfg.min_inliers) & (fitness >= cfg.min_fitness) & (rmse <= cfg.max_rmse * vs)
          & (agree >= cfg.min_colour_agreement) & (jnp.abs(jnp.log(scale2 / jnp.maximum(scale, 1e-12))) < 0.2)
          & (scale2 >= cfg.scale_range[0]) & (scale2 <= cfg.scale_range[1]) & jnp.all(jnp.isfinite(T2)))
    return Verification(accepted=ok, transform=T2, scale=scale2, matches=matches, keypoint_inliers=kp_inliers,
                        fitness=fitness, inlier_count=count.astype(jnp.int32), inlier_rmse=rmse, colour_agreement=agree)


def _refine_and_decide(bank, m, entry: MapEntry, Ts, scales, matches, inliers, cfg: MemoryConfig):
    """Verify candidate ``m`` (-1: none) from its keypoint poses Ts (G, 4, 4) (:func:`_keypoint_stage`):
    with ICP (``cfg.verification == "full"``) the pose with the largest colour-consistent overlap
    (:func:`_screen_poses`; a wrong pose of a box room can fit its geometry well, but rarely its
    colours) is refined by ICP, else the one with most keypoint inliers; then :func:`_decide`.
    Returns (Verification, the chosen pose's screening overlap as a share of ``cfg.screen_points``
    (0 without ICP), its RANSAC scale): the last two feed :func:`acceptance_features`."""
    mm = jnp.maximum(m, 0)
    if cfg.verification != "full":
        g = jnp.argmax(inliers)
        return (_decide(bank, m, Ts[g], scales[g], matches, inliers[g], None, cfg), jnp.zeros((), jnp.float32),
                scales[g])
    screen = _screen_poses(bank, mm, entry, Ts, cfg)
    first = jnp.arange(Ts.shape[0]) % cfg.pose_candidates == 0  # each generator's best (kept as before)
    screen = jnp.where(first | (inliers > 0), screen, -1)  # a runner-up pose that does not exist
    g = jnp.argmax(screen * (cfg.ransac_scored + 1) + inliers)  # colour-consistent overlap first, inliers break ties
    icp = _icp_stage(bank, mm, entry, Ts[g], cfg)
    return (_decide(bank, m, Ts[g], scales[g], matches, inliers[g], icp, cfg), screen[g] / cfg.screen_points,
            scales[g])


# ----------------------------------------------------------------------------------------------
# Keypoint-free fallback: global registration of the two static clouds


def height_range(z, valid, lo: float = 0.05, hi: float = 0.95):
    """Robust floor and ceiling heights (the ``lo`` / ``hi`` quantiles of the valid heights z (N,))."""
    zz = jnp.where(valid, z, jnp.nan)
    return jnp.nanquantile(zz, lo), jnp.nanquantile(zz, hi)


def _raster(xy, w, origin, cell, size: int):
    """Occupancy grid (size, size) of the points xy (N, 2) with weights w (N,) (0 outside the grid)."""
    ij = jnp.floor((xy - origin) / cell).astype(jnp.int32)
    ok = jnp.all((ij >= 0) & (ij < size), -1)
    flat = jnp.where(ok, ij[:, 0] * size + ij[:, 1], 0)
    return jnp.zeros(size * size, jnp.float32).at[flat].add(jnp.where(ok, w, 0.0)).reshape(size, size)


def global_hypotheses(src, src_normals, src_valid, dst, dst_normals, dst_valid, frame_src, frame_dst, cell,
                      num_yaws: int, grid: int = 64, num_points: int = 1024, scale_range=(0.25, 4.0)):
    """Sim(3) hypotheses src -> dst (two static clouds of one room) without any descriptor match.

    Both clouds are put in their upright frames (``frame_*`` = :func:`upright_frame`: the rotation is a
    yaw about up); the scale is the ratio of their floor-to-ceiling spans (:func:`height_range`), the
    vertical offset aligns those spans; for each of ``num_yaws`` yaws (evenly spaced, offset so that
    the clouds' dominant wall directions (:func:`wall_direction`) agree: 4 yaws are a box room's 4
    orientations) the horizontal occupancy grids of the *wall* points (normal within 60 deg of
    horizontal; ``grid`` x ``grid`` cells of ``cell`` dst units, ``num_points`` src wall points) are
    cross-correlated by FFT and the peak gives the horizontal translation.
    Returns (transforms (Y, 4, 4), correlation peaks (Y,))."""
    src, dst = jnp.asarray(src, jnp.float32), jnp.asarray(dst, jnp.float32)
    src_valid, dst_valid = jnp.asarray(src_valid, bool), jnp.asarray(dst_valid, bool)
    up_s, up_d = frame_src[2], frame_dst[2]
    us, ud = src @ frame_src.T, dst @ frame_dst.T
    lo_s, hi_s = height_range(us[:, 2], src_valid)
    lo_d, hi_d = height_range(ud[:, 2], dst_valid)
    s = jnp.clip((hi_d - lo_d) / jnp.maximum(hi_s - lo_s, 1e-12), scale_range[0], scale_range[1])
    tz = 0.5 * (lo_d + hi_d) - s * 0.5 * (lo_s + hi_s)
    wall_d = (dst_valid & (jnp.abs(jnp.asarray(dst_normals) @ up_d) < 0.5)).astype(jnp.float32)
    od = jnp.sum(wall_d[:, None] * ud[:, :2], 0) / jnp.maximum(jnp.sum(wall_d), 1.0) - 0.5 * grid * cell
    fd = jnp.fft.rfft2(_raster(ud[:, :2], wall_d, od, cell, grid))
    wall_s = src_valid & (jnp.abs(jnp.asarray(src_normals) @ up_s) < 0.5)
    xy, wv, _ = _even_subsample(us[:, :2], wall_s, num_points)
    wv = wv.astype(jnp.float32)
    yaw0 = wall_direction(jnp.asarray(dst_normals) @ frame_dst.T, wall_d) - wall_direction(
        jnp.asarray(src_normals) @ frame_src.T, wall_s.astype(jnp.float32))

    def one(a):
        c, si = jnp.cos(a), jnp.sin(a)
        r = s * (xy @ jnp.array([[c, si], [-si, c]]))  # s Rz(a) xy, row vectors
        os_ = jnp.sum(wv[:, None] * r, 0) / jnp.maximum(jnp.sum(wv), 1.0) - 0.5 * grid * cell
        corr = jnp.fft.irfft2(fd * jnp.conj(jnp.fft.rfft2(_raster(r, wv, os_, cell, grid))), s=(grid, grid))
        k = jnp.argmax(corr)
        d = (jnp.stack([k // grid, k % grid]) + grid // 2) % grid - grid // 2
        t = jnp.concatenate([od - os_ + d * cell, tz[None]])
        A = jnp.array([[c, -si, 0.0], [si, c, 0.0], [0.0, 0.0, 1.0]]) * s
        T = _similarity(jnp.ones(()), frame_dst.T @ A @ frame_src, frame_dst.T @ t)
        return T, corr.reshape(-1)[k]

    return jax.vmap(one)(yaw0 + jnp.arange(num_yaws) * (2 * np.pi / num_yaws))


def wall_direction(upright_normals, w):
    """The dominant horizontal wall direction (radians, modulo 90 deg) of normals already in an upright
    frame (N, 3) weighted by w (N,): the circular mean of 4x their horizontal angles (box rooms: the
    four walls agree)."""
    a = 4.0 * jnp.arctan2(upright_normals[:, 1], upright_normals[:, 0])
    return 0.25 * jnp.arctan2(jnp.sum(w * jnp.sin(a)), jnp.sum(w * jnp.cos(a)))


def _colour_icp(src, scol, sv, dst, dcol, dv, T, distance, iterations: int, max_colour, cell=None, per_cell: int = 3):
    """Point-to-point Sim(3) ICP of ``src`` (n, 3) (colours ``scol`` (n, 3) float) to ``dst`` on pairs
    within ``distance`` whose colours are within ``max_colour`` RGB (brute force, or :func:`grid_nearest`
    when ``cell``: ``dst`` sorted by :func:`sort_by_cell` at ``cell``). Returns (T, nearest (n,),
    squared distance (n,), colour difference (n,)) at the final T."""
    from cm3d.solvers.align import umeyama

    def nearest(T):
        q = src @ T[:3, :3].T + T[:3, 3]
        if cell is None:
            d2 = jnp.where(dv[None], jnp.sum((q[:, None] - dst[None]) ** 2, -1), jnp.inf)
            j = jnp.argmin(d2, 1)
            dmin = jnp.take_along_axis(d2, j[:, None], 1)[:, 0]
        else:
            j, dmin = grid_nearest(q, dst, dv, cell, per_cell=per_cell)
        return j, dmin, jnp.linalg.norm(scol - dcol[j], axis=-1)

    def step(T, _):
        j, d2, dc = nearest(T)
        use = sv & (d2 < distance**2) & (dc <= max_colour)
        s2, R2, t2 = umeyama(src, dst[j], use, with_scale=True)
        T2 = _similarity(s2, R2, t2)
        return jnp.where((jnp.sum(use) >= 3) & jnp.all(jnp.isfinite(T2)), T2, T), None

    T, _ = jax.lax.scan(step, T, None, length=iterations)
    return (T, *nearest(T))


def _fallback_stage(bank: MemoryBank, m, entry: MapEntry, frame_q, cfg: MemoryConfig, extra=None) -> Verification:
    """Keypoint-free verification of map ``m``: :func:`global_hypotheses` (``cfg.fallback_yaws`` yaws)
    and the poses ``extra`` (G, 4, 4) (e.g. the keypoint path's RANSAC poses); the ``cfg.fallback_refine``
    with the most colour-consistent overlap (:func:`_screen_poses`; correlation breaks ties) are each
    refined by :func:`_colour_icp` (coarse: 128 query voxels against 512 map points within 4 map
    voxels; fine: ``cfg.icp_points`` query voxels, one grid cell); of those with ``cfg.min_inliers``
    inliers the pose with the largest (inliers within ``cfg.fallback_colour_difference`` RGB) x (their
    share) is kept, then STRICT acceptance: inliers >= ``cfg.min_inliers``, fitness >=
    ``cfg.fallback_min_fitness``, inlier RMSE <= ``cfg.fallback_max_rmse`` voxels and a share >=
    ``cfg.fallback_min_colour`` of inliers within ``cfg.fallback_colour_difference`` RGB. A box room's wrong orientations often fit its geometry
    *better* than the right one (partial views), and unseen box rooms fit as well as revisits: only a
    close colour match at the right pose separates them, so the pose is chosen by colour, not fitness.
    Fixed shapes throughout (jittable, vmappable); cost ~ ``cfg.fallback_refine`` extra ICPs per query."""
    present = (m >= 0) & bank.map_valid[jnp.maximum(m, 0)]
    m = jnp.maximum(m, 0)
    vs = jnp.maximum(bank.voxel_size[m], 1e-12)
    frame_m = upright_frame(up_axis(bank.normals[m], bank.point_valid[m], cfg.up_prior, cfg.up_max_angle))
    Ts, peak = global_hypotheses(entry.points, entry.normals, entry.point_valid, bank.points[m], bank.normals[m],
                                 bank.point_valid[m], frame_q, frame_m, 2.0 * vs, cfg.fallback_yaws,
                                 cfg.fallback_grid, cfg.fallback_points, cfg.scale_range)
    if extra is not None:  # e.g. the keypoint path's poses, rejected by its own thresholds
        Ts = jnp.concatenate([Ts, extra.astype(Ts.dtype)])
        peak = jnp.concatenate([peak, jnp.full(extra.shape[:1], jnp.max(peak), peak.dtype)])
    screen = _screen_poses(bank, m, entry, Ts, cfg).astype(jnp.float32)
    rank = screen + 0.5 * peak / jnp.maximum(jnp.max(peak), 1e-12)  # overlap first, correlation breaks ties
    _, top = jax.lax.top_k(rank, min(cfg.fallback_refine, Ts.shape[0]))
    mpts, mv, mcol = bank.points[m], bank.point_valid[m], bank.colors[m].astype(jnp.float32)
    csrc, csv, cidx = _even_subsample(entry.points, entry.point_valid, 128)
    _, _, didx = _even_subsample(mpts, mv, 512)
    src, sv, idx = _even_subsample(entry.points, entry.point_valid, cfg.icp_points)
    cell = GRID_CELL * vs

    def refine(T):
        T = _colour_icp(csrc, entry.colors[cidx].astype(jnp.float32), csv, mpts[didx], mcol[didx], mv[didx], T,
                        4.0 * vs, 4, cfg.max_colour_difference)[0]
        T, _, d2, dc = _colour_icp(src, entry.colors[idx].astype(jnp.float32), sv, mpts, mcol, mv, T, cell,
                                   cfg.icp_iterations, cfg.max_colour_difference, cell=cell, per_cell=cfg.grid_per_cell)
        inl = sv & (d2 < cell**2)
        return T, inl, d2, jnp.sum(inl & (dc <= cfg.fallback_colour_difference))

    Tr, inl, d2, good = jax.vmap(refine)(Ts[top])
    n_inl = jnp.sum(inl, 1)
    b = jnp.argmax(jnp.where(n_inl >= cfg.min_inliers, good * good / jnp.maximum(n_inl, 1), -1.0))
    T, inl, d2 = Tr[b], inl[b], d2[b]
    count = jnp.sum(inl)
    fitness = count / jnp.maximum(jnp.sum(sv), 1)
    rmse = jnp.sqrt(jnp.sum(jnp.where(inl, d2, 0.0)) / jnp.maximum(count, 1))
    agree = good[b] / jnp.maximum(count, 1)
    scale = jnp.cbrt(jnp.linalg.det(T[:3, :3]))
    ok = (present & (count >= cfg.min_inliers) & (fitness >= cfg.fallback_min_fitness)
          & (rmse <= cfg.fallback_max_rmse * vs) & (agree >= cfg.fallback_min_colour)
          & (scale >= cfg.scale_range[0]) & (scale <= cfg.scale_range[1]) & jnp.all(jnp.isfinite(T)))
    z = jnp.zeros((), jnp.int32)
    return Verification(accepted=ok, transform=T, scale=scale, matches=z, keypoint_inliers=z, fitness=fitness,
                        inlier_count=count.astype(jnp.int32), inlier_rmse=rmse, colour_agreement=agree)


def _query_keypoints(entry: MapEntry, cfg: MemoryConfig):
    """The query's keypoints (none: three invalid ones), its floor keypoints (None when it has none or
    the bank holds none: ``cfg.max_floor_keypoints == 0``), the :func:`keypoint_clusters` of both
    (image keypoints first), its upright frame (:func:`upright_frame` of :func:`up_axis`) and the
    cluster separation (query units)."""
    kp = _fit_keypoints(None, 3, cfg.keypoint_dim) if entry.keypoints is None else entry.keypoints
    floor = entry.floor_keypoints if cfg.max_floor_keypoints > 0 else None
    sep = cfg.cluster_separation * jnp.maximum(jnp.asarray(entry.voxel_size, jnp.float32), 1e-12)
    frame = upright_frame(up_axis(entry.normals, entry.point_valid, cfg.up_prior, cfg.up_max_angle))
    both = kp if floor is None else jax.tree.map(lambda a, b: jnp.concatenate([a, b]), kp, floor)
    return kp, floor, keypoint_clusters(both.points, both.valid, sep), frame, sep


def verify(bank: MemoryBank, map_id, entry: MapEntry, cfg: MemoryConfig, key) -> Verification:
    """Verify that the query ``entry`` (its own frame and scale) shows map ``map_id``.

    1. keypoint matches (:func:`match_keypoints`) and Sim(3) RANSAC (3-point hypotheses, plus
       ``cfg.upright_hypotheses`` 2-point ones about both frames' up axes, :func:`upright_pairs`;
       scored by distinct 3D points, see :func:`_keypoint_stage`): at least
       ``cfg.min_keypoint_inliers`` distinct inliers within ``cfg.ransac_distance`` map voxels;
    2. (``cfg.verification == "full"``) of the RANSAC poses the one with the most colour-consistent
       overlap (:func:`_screen_poses`) is refined by Sim(3) ICP of ``cfg.icp_points`` query voxels
       against the map's (:func:`icp_sim3`), accepted on absolute inlier count
       (``cfg.min_inliers``), fitness (``cfg.min_fitness``) and inlier RMSE (``cfg.max_rmse`` voxels).
    Geometry is what rejects look-alike scenes. ``cfg.verification == "none"`` accepts any stored map.
    These thresholds decide here; :func:`identify` decides by its acceptance model instead (it needs
    the 2D recall's scores, which a single-map check does not have).
    """
    m = jnp.maximum(map_id, 0)
    Ts, scales, matches, inliers = _keypoint_stage(bank, m, *_query_keypoints(entry, cfg), cfg, key)
    return _refine_and_decide(bank, jnp.where(map_id >= 0, m, -1), entry, Ts, scales, matches, inliers, cfg)[0]


@struct.dataclass
class Identification:
    """Recall + verification of one query: the recall, keypoint checks of each candidate
    (``candidate_inliers`` (top_k,)), the final verification (of the keypoint path's candidate, or of
    the fallback's when only the fallback accepted), ``map_id`` (the accepted map, -1 if none) and
    ``fallback``: the keypoint-free check of that candidate (:func:`_fallback_stage`; None when
    ``cfg.fallback_yaws`` is 0)."""

    recall: Recall
    candidate_inliers: jax.Array
    verification: Verification
    map_id: jax.Array
    fallback: Verification | None = None
    candidate: jax.Array | None = None  # () the verified candidate (-1: none), accepted or not
    features: jax.Array | None = None  # (len(ACCEPTANCE_FEATURES),) its scores (acceptance_features)
    acceptance: jax.Array | None = None  # () the acceptance model's score (None without cfg.accept_weights)


def identify(bank: MemoryBank, entry: MapEntry, cfg: MemoryConfig, key) -> Identification:
    """Which stored map does the query ``entry`` show, and where? (pure, jittable, vmappable)

    2D recall (:func:`recall`) proposes ``cfg.top_k`` candidates; each is checked by keypoint
    matching + Sim(3) RANSAC (triangle and upright-pair hypotheses); the candidate with most RANSAC
    inliers (ties: recall order) is refined from its pose with the most colour-consistent overlap
    and verified by ICP (:func:`verify`, per ``cfg.verification``); with ``cfg.accept_weights`` (the
    default) and ``"full"`` verification the acceptance model decides instead of the thresholds:
    :func:`acceptance_score` of :func:`acceptance_features` >= 0, plus the hard checks (a stored map, a
    finite transform, a scale in ``cfg.scale_range``). With ``cfg.fallback_yaws`` (and
    ``"full"`` verification) a query the keypoint path rejects gets a second, keypoint-free chance
    against the same candidate (:func:`_fallback_stage`, stricter thresholds); under ``vmap`` both
    paths run for every query (fixed cost: the yaw search and ``cfg.fallback_refine`` ICPs per query).
    """
    r = recall(bank, entry.kf_desc, entry.kf_valid, entry.cloud_desc, cfg)
    cand = r.candidates
    if cfg.verification == "none":
        v = _decide(bank, cand[0], jnp.eye(4), jnp.ones(()), jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32), None, cfg)
        return Identification(recall=r, candidate_inliers=jnp.zeros(cfg.top_k, jnp.int32), verification=v,
                              map_id=jnp.where(v.accepted, cand[0], -1))
    qk, qf, cluster, frame, sep = _query_keypoints(entry, cfg)
    keys = jax.random.split(key, cfg.top_k)
    Ts, scales, matches, inliers = jax.vmap(
        lambda m, k: _keypoint_stage(bank, jnp.maximum(m, 0), qk, qf, cluster, frame, sep, cfg, k))(cand, keys)
    best = jnp.where(cand >= 0, jnp.max(inliers, 1), -1)
    b = jnp.argmax(best)
    m = cand[b]
    v, screen, s_kp = _refine_and_decide(bank, m, entry, Ts[b], scales[b], matches[b], inliers[b], cfg)
    per_generator = jnp.max(inliers[b].reshape(-1, cfg.pose_candidates), 1)  # (G,) each generator's best
    feats = acceptance_features(bank, entry, r, best, b, per_generator, screen, s_kp, v)
    score = None
    if cfg.accept_weights and cfg.verification == "full":
        score = acceptance_score(feats, cfg)
        v = v.replace(accepted=_model_accepts(bank, m, v, score, cfg))
    map_id = jnp.where(v.accepted, m, -1)
    if not cfg.fallback_yaws or cfg.verification != "full":
        return Identification(recall=r, candidate_inliers=best, verification=v, map_id=map_id, candidate=m,
                              features=feats, acceptance=score)
    fb = _fallback_stage(bank, m, entry, frame, cfg, Ts[b])
    use = ~v.accepted & fb.accepted
    v = jax.tree.map(lambda a, c: jnp.where(use, a, c), fb, v)
    return Identification(recall=r, candidate_inliers=best, verification=v, map_id=jnp.where(use, m, map_id),
                          fallback=fb, candidate=m, features=feats, acceptance=score)


def _model_accepts(bank, m, v: Verification, score, cfg: MemoryConfig):
    """The acceptance model's decision: score >= 0 and the hard checks (a stored map, a finite transform,
    a scale in ``cfg.scale_range``)."""
    return ((m >= 0) & bank.map_valid[jnp.maximum(m, 0)] & (score >= 0) & jnp.all(jnp.isfinite(v.transform))
            & (v.scale >= cfg.scale_range[0]) & (v.scale <= cfg.scale_range[1]))


def acceptance_features(bank: MemoryBank, entry: MapEntry, r: Recall, candidate_inliers, b, inliers, screen,
                        ransac_scale, v: Verification):
    """The scores of the verified candidate ``r.candidates[b]`` as one vector, in the order of
    :data:`ACCEPTANCE_FEATURES`: the acceptance model's inputs (:func:`acceptance_score`).
    ``candidate_inliers`` (top_k,): each candidate's best keypoint inliers (-1: none); ``inliers`` (G,):
    the candidate's per generator (triangle, upright pairs); ``screen``: the chosen pose's screening
    overlap (share); ``ransac_scale``: its RANSAC scale; ``v``: its verification (ICP scores). Pure, fixed
    shape; 0 where not finite or without a candidate."""
    cand = r.candidates
    m = cand[b]
    mm = jnp.maximum(m, 0)
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    share = r.votes[mm] / jnp.maximum(jnp.sum(entry.kf_valid), 1)
    finite = lambda x: jnp.where(jnp.isfinite(x), x, 0.0)  # noqa: E731
    other = (jnp.arange(cand.shape[0]) != b) & (cand >= 0)
    margin = finite(r.candidate_scores[b]) - jnp.max(jnp.where(other, finite(r.candidate_scores), 0.0))
    sim = bank.cloud_desc[mm] @ jnp.asarray(entry.cloud_desc, jnp.float32)
    log1p = lambda n: jnp.log1p(jnp.maximum(f32(n), 0.0))  # noqa: E731
    runner = jnp.max(jnp.where(other, candidate_inliers, 0))
    vs = jnp.maximum(bank.voxel_size[mm], 1e-12)
    scale = jnp.maximum(v.scale, 1e-12)
    feats = jnp.stack([
        f32(share), f32(margin), f32(sim), log1p(v.matches), log1p(inliers[0]), log1p(inliers[-1]),
        log1p(v.keypoint_inliers),
        log1p(candidate_inliers[b]) - log1p(runner), f32(screen), log1p(v.inlier_count), f32(v.fitness),
        f32(v.inlier_rmse) / vs, f32(v.colour_agreement),
        jnp.minimum(jnp.abs(jnp.log(scale / jnp.maximum(ransac_scale, 1e-12))), 2.0),
        jnp.minimum(jnp.abs(jnp.log(scale)), 2.0)])
    present = (m >= 0) & bank.map_valid[mm]
    return jnp.where(present & jnp.isfinite(feats), feats, 0.0)


def acceptance_score(features, cfg: MemoryConfig):
    """The acceptance model's score of :func:`acceptance_features` (accept when >= 0): a dot product of
    the standardised features with ``cfg.accept_weights`` plus ``cfg.accept_bias``."""
    w = jnp.asarray(cfg.accept_weights, jnp.float32)
    mu = jnp.asarray(cfg.accept_mean, jnp.float32)
    sd = jnp.asarray(cfg.accept_scale, jnp.float32)
    return jnp.sum(w * (features - mu) / sd) + jnp.float32(cfg.accept_bias)


def relocalize(transform, cam_to_world):
    """Cameras (..., 4, 4) of the query frame moved into the map frame by a Sim(3) ``transform``
    (``[s R, t]``): rotation ``R R_c``, centre ``s R t_c + t``; the result is a rigid pose."""
    A, t = transform[:3, :3], transform[:3, 3]
    s = jnp.cbrt(jnp.linalg.det(A))
    R = A / s
    out = cam_to_world.at[..., :3, :3].set(R @ cam_to_world[..., :3, :3])
    return out.at[..., :3, 3].set(jnp.einsum("ij,...j->...i", A, cam_to_world[..., :3, 3]) + t)


def _merge_keyframes(old_desc, old_valid, new_desc, new_valid):
    """Up to K keyframes from the old and new ones: all when they fit, else an evenly spread subset
    of the concatenation (old first), so both visits stay represented."""
    K = old_desc.shape[0]
    desc = jnp.concatenate([old_desc, new_desc])
    valid = jnp.concatenate([old_valid, new_valid])
    order = jnp.argsort(~valid, stable=True)
    n = jnp.sum(valid)
    pos = jnp.round(jnp.linspace(0.0, 1.0, K) * jnp.maximum(n - 1, 0)).astype(jnp.int32)
    idx = jnp.where(n > K, order[pos], order[:K])
    return desc[idx], jnp.arange(K) < jnp.minimum(n, K)


def _merge_keypoints(old: Keypoints, new: Keypoints) -> Keypoints:
    """Up to N keypoints from the map's and the (already moved) query's: all when they fit, else an
    evenly spread subset of the concatenation, as for keyframes."""
    N = old.valid.shape[0]
    pts = jnp.concatenate([old.points, new.points])
    desc = jnp.concatenate([old.desc, new.desc])
    valid = jnp.concatenate([old.valid, new.valid])
    order = jnp.argsort(~valid, stable=True)
    n = jnp.sum(valid)
    pos = jnp.round(jnp.linspace(0.0, 1.0, N) * jnp.maximum(n - 1, 0)).astype(jnp.int32)
    idx = jnp.where(n > N, order[pos], order[:N])
    kv = jnp.arange(N) < jnp.minimum(n, N)
    return Keypoints(jnp.where(kv[:, None], pts[idx], 0.0), jnp.where(kv[:, None], desc[idx], 0.0), kv)


def update_map(bank: MemoryBank, map_id, entry: MapEntry, transform, cfg: MemoryConfig) -> MemoryBank:
    """Merge a verified query into map ``map_id``: its voxels moved by ``transform`` (query ->
    map), pooled with the map's (weighted by confidence), downsampled again at the map's voxel
    size (grown if over capacity); keyframes and keypoints merged; 3D descriptor and normals
    recomputed."""
    from cm3d.ops.neighbors import estimate_normals

    m = map_id
    A, t = transform[:3, :3], transform[:3, 3]
    q = entry.points @ A.T + t
    pts = jnp.concatenate([bank.points[m], q])
    valid = jnp.concatenate([bank.point_valid[m], entry.point_valid])
    feats = jnp.concatenate([jnp.concatenate([bank.colors[m], entry.colors]).astype(jnp.float32),
                             jnp.concatenate([bank.conf[m], entry.conf])[:, None]], axis=1)
    P = bank.points.shape[1]
    vox, vs = _downsample_to_capacity(pts, valid, feats, bank.voxel_size[m], P)
    normals = estimate_normals(vox.points, vox.valid, k=16, radius=cfg.normal_radius)
    normals = jnp.where(vox.valid[:, None], normals, 0.0)
    vpts, vvalid, normals, vfeat = sort_by_cell(vox.points, vox.valid, jnp.maximum(vs, 1e-12) * GRID_CELL, normals,
                                                vox.features)
    vox = vox.replace(points=vpts, valid=vvalid, features=vfeat)
    kf, kfv = _merge_keyframes(bank.kf_desc[m], bank.kf_valid[m], entry.kf_desc, entry.kf_valid)

    def merged(new, points, desc, valid):  # the query's keypoints of one kind moved into the map and merged
        new = _fit_keypoints(new, valid.shape[1], desc.shape[2])
        new = new.replace(points=jnp.where(new.valid[:, None], new.points @ A.T + t, 0.0))
        return _merge_keypoints(Keypoints(points[m], desc[m], valid[m]), new)

    kp = merged(entry.keypoints, bank.kp_points, bank.kp_desc, bank.kp_valid)
    fkp = merged(entry.floor_keypoints, bank.floor_kp_points, bank.floor_kp_desc, bank.floor_kp_valid)
    return bank.replace(
        points=bank.points.at[m].set(vox.points), normals=bank.normals.at[m].set(normals),
        conf=bank.conf.at[m].set(vox.features[:, 3]),
        colors=bank.colors.at[m].set(jnp.clip(jnp.round(vox.features[:, :3]), 0, 255).astype(jnp.uint8)),
        point_valid=bank.point_valid.at[m].set(vox.valid),
        cloud_desc=bank.cloud_desc.at[m].set(cloud_descriptor(vox.points, vox.valid, cfg)),
        kf_desc=bank.kf_desc.at[m].set(kf), kf_codes=bank.kf_codes.at[m].set(descriptors.hash_codes(kf, bank.planes)),
        kf_valid=bank.kf_valid.at[m].set(kfv), visits=bank.visits.at[m].add(1), voxel_size=bank.voxel_size.at[m].set(vs),
        kp_points=bank.kp_points.at[m].set(kp.points), kp_desc=bank.kp_desc.at[m].set(kp.desc),
        kp_valid=bank.kp_valid.at[m].set(kp.valid), floor_kp_points=bank.floor_kp_points.at[m].set(fkp.points),
        floor_kp_desc=bank.floor_kp_desc.at[m].set(fkp.desc), floor_kp_valid=bank.floor_kp_valid.at[m].set(fkp.valid))


@struct.dataclass
class Report:
    """What :func:`remember` decided: the identification (recall and verification), the accepted
    map (-1 if none), the map written to (-1 if the bank was full), the transform query -> map
    (identity for a new map) and whether a new map was created."""

    identification: Identification
    recalled: jax.Array
    map_id: jax.Array
    transform: jax.Array
    created: jax.Array


def remember(bank: MemoryBank, entry: MapEntry, cfg: MemoryConfig, key) -> tuple[MemoryBank, Report]:
    """Recall, verify, then update the recalled map or store a new one (pure, jittable).

    ``entry`` is the query sequence built by :func:`build_entry` (its own frame and scale).
    :func:`identify` picks and verifies a candidate; an accepted one is updated with the query
    moved into its frame (:func:`update_map`), else the query becomes a new map (map_id -1 when full).
    """
    ident = identify(bank, entry, cfg, key)
    hit = ident.map_id >= 0
    recalled = ident.map_id
    T = jnp.where(hit, ident.verification.transform, jnp.eye(4, dtype=ident.verification.transform.dtype))

    def on_hit(b):
        return update_map(b, jnp.maximum(recalled, 0), entry, T, cfg), recalled

    def on_miss(b):
        return insert_map(b, entry)

    bank, map_id = jax.lax.cond(hit, on_hit, on_miss, bank)
    return bank, Report(identification=ident, recalled=recalled, map_id=map_id.astype(jnp.int32), transform=T,
                        created=~hit & (map_id >= 0))


# ----------------------------------------------------------------------------------------------
# Persistence


def _fields(bank: MemoryBank) -> dict[str, np.ndarray]:
    return {f.name: np.asarray(getattr(bank, f.name)) for f in dataclasses.fields(bank)}


def save(bank: MemoryBank, path, cfg: MemoryConfig) -> None:
    """Write the bank atomically with a versioned header and a SHA-256 checksum."""
    arrays = _fields(bank)
    for name in ("points", "normals", "conf", "cloud_desc", "kf_desc", "kp_points", "kp_desc", "floor_kp_points",
                 "floor_kp_desc"):
        bad = ~np.isfinite(arrays[name])
        if bad.any():
            raise ValueError(f"memory bank field {name!r} holds {int(bad.sum())} non-finite values; "
                             "refusing to save a corrupt bank")
    payload = b"".join(np.ascontiguousarray(a).tobytes() for a in arrays.values())
    header = json.dumps({
        "version": FORMAT_VERSION, "config": dataclasses.asdict(cfg),
        "arrays": [[k, list(a.shape), a.dtype.str] for k, a in arrays.items()],
        "sha256": hashlib.sha256(payload).hexdigest(),
    }).encode()
    with atomic_write(path) as f:
        f.write(MAGIC + pystruct.pack("<Q", len(header)) + header + payload)


def load(path) -> tuple[MemoryBank, MemoryConfig]:
    """Read a bank written by :func:`save`; any damage raises :class:`MemoryFileError`."""
    path = os.fspath(path)
    try:
        data = open(path, "rb").read()
    except FileNotFoundError:
        raise MemoryFileError(f"{path}: no such memory bank file") from None
    if not data.startswith(MAGIC):
        raise MemoryFileError(f"{path}: not a cm3d memory bank (bad magic)")
    try:
        (n,) = pystruct.unpack("<Q", data[len(MAGIC): len(MAGIC) + 8])
        start = len(MAGIC) + 8
        header = json.loads(data[start: start + n])
    except (pystruct.error, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise MemoryFileError(f"{path}: damaged header ({e})") from None
    version = header.get("version")
    if version not in READ_VERSIONS:
        raise MemoryFileError(f"{path}: format version {version}, this cm3d reads {', '.join(map(str, READ_VERSIONS))}")
    payload = data[start + n:]
    if hashlib.sha256(payload).hexdigest() != header["sha256"]:
        raise MemoryFileError(f"{path}: checksum mismatch (truncated or altered file)")
    try:
        cfg = MemoryConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in header["config"].items()})
    except TypeError as e:
        raise MemoryFileError(f"{path}: unknown config fields ({e})") from None
    arrays, off = {}, 0
    for name, shape, dtype in header["arrays"]:
        size = int(np.prod(shape)) * np.dtype(dtype).itemsize
        arrays[name] = jnp.asarray(np.frombuffer(payload[off: off + size], dtype).reshape(shape))
        off += size
    spec = jax.eval_shape(lambda: empty(cfg))
    if version == 2:  # no floor keypoints yet (the config has max_floor_keypoints = 0)
        arrays.update({k: jnp.zeros(getattr(spec, k).shape, getattr(spec, k).dtype)
                       for k in ("floor_kp_points", "floor_kp_desc", "floor_kp_valid")})
    expected = {f.name: getattr(spec, f.name).shape for f in dataclasses.fields(spec)}
    if set(arrays) != set(expected) or any(arrays[k].shape != v for k, v in expected.items()):
        raise MemoryFileError(f"{path}: arrays do not match the stored config's capacities")
    return MemoryBank(**arrays), cfg
