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
        map_valid=jnp.zeros((M,), bool), visits=jnp.zeros((M,), jnp.int32),
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
        visits=put(bank.visits, jnp.int32(1)),
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
        cfg = MemoryConfig(**header["config"])
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
