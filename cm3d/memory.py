"""The cognitive memory bank: an immutable pytree of static maps, recalled by descriptors.

Layout (capacities from :class:`MemoryConfig`, all static): per map ``m < max_maps`` a static point
cloud (``points``, ``normals``, ``conf``, ``colors``, ``point_valid``; voxel downsampled, in the
map's own frame and scale), its 3D descriptor ``cloud_desc`` and up to ``max_keyframes`` keyframe
descriptors ``kf_desc`` with hash codes ``kf_codes``. The *global feature table* is the flat view
``kf_desc.reshape(max_maps * max_keyframes, dim)`` with ``map_id = row // max_keyframes``
(:func:`global_table`), so it never goes out of sync with the maps.

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
FORMAT_VERSION = 1


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
    cloud_dim: int = descriptors.CLOUD_DIM
    hash_bits: int = 64
    hash_seed: int = 0
    hash_radius: int = 22  # a table row is a candidate when its code is this close (Hamming)
    match_radius: float = 0.45  # ... and its exact L2 distance to the query is below this
    top_k: int = 3  # candidate maps passed on to verification
    w_cloud: float = 0.5  # weight of the 3D-descriptor similarity when re-ranking
    voxel_resolution: float = 60.0  # map voxel = largest extent / this (grown while over capacity)
    min_conf_quantile: float = 0.3  # static points: confidence above this quantile of the sequence
    pixel_stride: int = 4  # static points: every stride-th pixel
    scales: tuple[float, ...] = (0.7, 1.0, 1.4)  # query -> map scale hypotheses for registration
    min_fitness: float = 0.35  # verification: share of query voxels with a map voxel nearby
    max_rmse: float = 0.6  # verification: inlier RMSE, in map voxels
    normal_radius: float = 0.2  # neighbourhood cell for map normals (map units: VGGT-normalised)
    min_inliers: int = 150  # verification: absolute number of inlier voxels


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

    @property
    def num_maps(self) -> jax.Array:
        return jnp.sum(self.map_valid)


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
    )


@struct.dataclass
class MapEntry:
    """One map's contents, already at the bank's capacities (P points, K keyframes)."""

    points: jax.Array  # (P, 3)
    normals: jax.Array  # (P, 3)
    conf: jax.Array  # (P,)
    colors: jax.Array  # (P, 3) uint8
    point_valid: jax.Array  # (P,)
    kf_desc: jax.Array  # (K, D2)
    kf_valid: jax.Array  # (K,)
    cloud_desc: jax.Array  # (D3,)
    voxel_size: jax.Array  # ()


def insert_map(bank: MemoryBank, entry: MapEntry) -> tuple[MemoryBank, jax.Array]:
    """Put ``entry`` in the first free slot: ``(bank, map_id)``; a full bank is returned
    unchanged with ``map_id = -1`` (pure and jittable; see :func:`add_map` for the host check)."""
    free = ~bank.map_valid
    slot = jnp.argmax(free)
    ok = free[slot]
    codes = descriptors.hash_codes(entry.kf_desc, bank.planes)

    def put(field, value):
        return field.at[slot].set(jnp.where(ok, value.astype(field.dtype), field[slot]))

    new = bank.replace(
        points=put(bank.points, entry.points), normals=put(bank.normals, entry.normals),
        conf=put(bank.conf, entry.conf), colors=put(bank.colors, entry.colors),
        point_valid=put(bank.point_valid, entry.point_valid), cloud_desc=put(bank.cloud_desc, entry.cloud_desc),
        kf_desc=put(bank.kf_desc, entry.kf_desc), kf_codes=put(bank.kf_codes, codes),
        kf_valid=put(bank.kf_valid, entry.kf_valid), map_valid=put(bank.map_valid, jnp.bool_(True)),
        visits=put(bank.visits, jnp.int32(1)), voxel_size=put(bank.voxel_size, entry.voxel_size),
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
    best = jnp.argmin(jnp.where(ok, d2, jnp.inf), axis=1)
    has = jnp.any(ok, axis=1)
    M = bank.map_valid.shape[0]
    votes = jnp.zeros(M).at[map_id[best]].add(has.astype(jnp.float32))
    frac = votes / jnp.maximum(jnp.sum(query_valid), 1)
    sim3d = bank.cloud_desc @ query_cloud_desc
    scores = jnp.where((votes > 0) & bank.map_valid, frac + cfg.w_cloud * sim3d, -jnp.inf)
    top_scores, top = jax.lax.top_k(scores, cfg.top_k)
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


def _entry_from_points(points, colors, conf, valid, kf_desc, kf_valid, voxel_size, cfg: MemoryConfig) -> MapEntry:
    """Downsample to the bank's capacity and describe (see :func:`build_entry`)."""
    from cm3d.ops.neighbors import estimate_normals

    feats = jnp.concatenate([colors.astype(jnp.float32), conf[:, None]], axis=1)
    vox, vs = _downsample_to_capacity(points, valid, feats, voxel_size, cfg.max_points)
    normals = estimate_normals(vox.points, vox.valid, k=16, radius=cfg.normal_radius)
    return MapEntry(points=vox.points, normals=jnp.where(vox.valid[:, None], normals, 0.0),
                    conf=vox.features[:, 3], colors=jnp.clip(jnp.round(vox.features[:, :3]), 0, 255).astype(jnp.uint8),
                    point_valid=vox.valid, kf_desc=kf_desc, kf_valid=kf_valid,
                    cloud_desc=descriptors.cloud_descriptor(vox.points, vox.valid), voxel_size=vs)


def build_entry(cloud: SequenceCloud, kf_desc, kf_valid, cfg: MemoryConfig) -> MapEntry:
    """A new map from a sequence: adaptive voxel size from the scene extent, mean point, colour and
    confidence per voxel, PCA normals, the 3D descriptor and the keyframe descriptors."""
    from cm3d.ops.voxel import adaptive_voxel_size

    vs = adaptive_voxel_size(cloud.points, cloud.valid, cfg.voxel_resolution)
    return _entry_from_points(cloud.points, cloud.colors, cloud.conf, cloud.valid, kf_desc, kf_valid, vs, cfg)


@struct.dataclass
class Verification:
    """ICP verification of one candidate: accepted, transform (4, 4) query -> map (Sim(3)),
    scale, fitness, inlier_count, inlier_rmse (map units)."""

    accepted: jax.Array
    transform: jax.Array
    scale: jax.Array
    fitness: jax.Array
    inlier_count: jax.Array
    inlier_rmse: jax.Array


def registration_options(cfg: MemoryConfig):
    from cm3d.solvers.align import GlobalOptions

    return dataclasses.replace(GlobalOptions.sim3(), scales=tuple(cfg.scales))


def verify(bank: MemoryBank, map_id, entry: MapEntry, cfg: MemoryConfig, key) -> Verification:
    """Register the query's map-entry cloud (its voxels) to map ``map_id`` from any pose and scale
    (FPFH + RANSAC + Sim(3) ICP) and accept on absolute inlier count, fitness and inlier RMSE."""
    from cm3d.solvers.align import global_registration

    m = jnp.maximum(map_id, 0)
    g = global_registration(entry.points, bank.points[m], entry.point_valid, bank.point_valid[m], key,
                            registration_options(cfg))
    n_src = jnp.sum(entry.point_valid)
    inliers = jnp.round(g.fitness * n_src).astype(jnp.int32)
    vs = jnp.maximum(bank.voxel_size[m], 1e-12)
    ok = ((map_id >= 0) & bank.map_valid[m] & (inliers >= cfg.min_inliers) & (g.fitness >= cfg.min_fitness)
          & (g.inlier_rmse <= cfg.max_rmse * vs) & jnp.all(jnp.isfinite(g.transform)))
    return Verification(accepted=ok, transform=g.transform, scale=g.scale, fitness=g.fitness,
                        inlier_count=inliers, inlier_rmse=g.inlier_rmse)


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


def update_map(bank: MemoryBank, map_id, entry: MapEntry, transform, cfg: MemoryConfig) -> MemoryBank:
    """Merge a verified query into map ``map_id``: its voxels moved by ``transform`` (query ->
    map), pooled with the map's (weighted by confidence), downsampled again at the map's voxel
    size (grown if over capacity); keyframes merged; 3D descriptor and normals recomputed."""
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
    kf, kfv = _merge_keyframes(bank.kf_desc[m], bank.kf_valid[m], entry.kf_desc, entry.kf_valid)
    return bank.replace(
        points=bank.points.at[m].set(vox.points), normals=bank.normals.at[m].set(jnp.where(vox.valid[:, None], normals, 0.0)),
        conf=bank.conf.at[m].set(vox.features[:, 3]),
        colors=bank.colors.at[m].set(jnp.clip(jnp.round(vox.features[:, :3]), 0, 255).astype(jnp.uint8)),
        point_valid=bank.point_valid.at[m].set(vox.valid),
        cloud_desc=bank.cloud_desc.at[m].set(descriptors.cloud_descriptor(vox.points, vox.valid)),
        kf_desc=bank.kf_desc.at[m].set(kf), kf_codes=bank.kf_codes.at[m].set(descriptors.hash_codes(kf, bank.planes)),
        kf_valid=bank.kf_valid.at[m].set(kfv), visits=bank.visits.at[m].add(1), voxel_size=bank.voxel_size.at[m].set(vs))


@struct.dataclass
class Report:
    """What :func:`remember` decided: the recall, each candidate's verification (top_k,), the
    accepted map (-1 if none), the map written to (-1 if the bank was full), the transform
    query -> map (identity for a new map) and whether a new map was created."""

    recall: Recall
    checks: Verification
    recalled: jax.Array
    map_id: jax.Array
    transform: jax.Array
    created: jax.Array


def remember(bank: MemoryBank, entry: MapEntry, cfg: MemoryConfig, key) -> tuple[MemoryBank, Report]:
    """Recall, verify, then update the recalled map or store a new one (pure, jittable).

    ``entry`` is the query sequence built by :func:`build_entry` (its own frame and scale). The
    top-k recalled candidates are verified; the best accepted one (highest fitness) is updated
    with the query moved into its frame, else the query becomes a new map (map_id -1 when full).
    """
    r = recall(bank, entry.kf_desc, entry.kf_valid, entry.cloud_desc, cfg)
    keys = jax.random.split(key, cfg.top_k)
    checks = jax.vmap(lambda m, k: verify(bank, m, entry, cfg, k))(r.candidates, keys)
    score = jnp.where(checks.accepted, checks.fitness, -jnp.inf)
    best = jnp.argmax(score)
    hit = checks.accepted[best]
    recalled = jnp.where(hit, r.candidates[best], -1)
    T = jnp.where(hit, checks.transform[best], jnp.eye(4, dtype=checks.transform.dtype))

    def on_hit(b):
        return update_map(b, recalled, entry, T, cfg), recalled

    def on_miss(b):
        return insert_map(b, entry)

    bank, map_id = jax.lax.cond(hit, on_hit, on_miss, bank)
    return bank, Report(recall=r, checks=checks, recalled=recalled, map_id=map_id, transform=T,
                        created=~hit & (map_id >= 0))


# ----------------------------------------------------------------------------------------------
# Persistence


def _fields(bank: MemoryBank) -> dict[str, np.ndarray]:
    return {f.name: np.asarray(getattr(bank, f.name)) for f in dataclasses.fields(bank)}


def save(bank: MemoryBank, path, cfg: MemoryConfig) -> None:
    """Write the bank atomically with a versioned header and a SHA-256 checksum."""
    arrays = _fields(bank)
    for name in ("points", "normals", "conf", "cloud_desc", "kf_desc"):
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
    if header.get("version") != FORMAT_VERSION:
        raise MemoryFileError(f"{path}: format version {header.get('version')}, this cm3d reads {FORMAT_VERSION}")
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
    expected = {f.name: getattr(spec, f.name).shape for f in dataclasses.fields(spec)}
    if set(arrays) != set(expected) or any(arrays[k].shape != v for k, v in expected.items()):
        raise MemoryFileError(f"{path}: arrays do not match the stored config's capacities")
    return MemoryBank(**arrays), cfg
