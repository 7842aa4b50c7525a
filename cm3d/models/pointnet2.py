"""A learned 3D global descriptor: a small PointNet++ encoder (Flax linen) with shipped weights.

:func:`cloud_descriptor` maps a voxelised static cloud (N, 3) with a validity mask (N,), in a map's
own frame and scale, to a unit descriptor (512,). Pure: jit, vmap and grad. Steps: :func:`resample`
to 512 points, :func:`normalise` (centroid, RMS radius), three :class:`SetAbstraction` levels
(FPS + ball query on yaw-invariant :func:`cylindrical` coordinates), global max pool, linear, L2.
Invariant to yaw about the camera y axis, translation and scale; not to arbitrary 3D rotations
(docs/pointnet2.md). Weights: :func:`load_params` / :func:`save_params`, one float16 ``.npz`` with
a SHA-256 header (``cm3d/models/pointnet2.npz``); a bad file raises :class:`WeightsError`.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import zipfile
from pathlib import Path

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util

from cm3d.data.atomic import atomic_write

DEFAULT_WEIGHTS = Path(__file__).with_name("pointnet2.npz")
FORMAT_VERSION = 1
OUT_DIM = 512


class WeightsError(ValueError):
    """A PointNet++ weight file is missing, truncated, altered or made for another architecture."""


@dataclasses.dataclass(frozen=True)
class PointNet2Config:
    """Architecture (static, shape-affecting). Radii are in normalised units (RMS radius = 1)."""

    num_points: int = 512
    centroids: tuple[int, ...] = (128, 32, 8)
    neighbours: tuple[int, ...] = (16, 16, 8)
    radii: tuple[float, ...] = (0.4, 0.8, 1.6)
    mlps: tuple[tuple[int, ...], ...] = ((32, 64, 128), (128, 128, 256), (256, 512))
    out_dim: int = OUT_DIM

    def __post_init__(self):
        n = len(self.centroids)
        if not (len(self.neighbours) == len(self.radii) == len(self.mlps) == n):
            raise ValueError("PointNet2Config: centroids, neighbours, radii and mlps need one entry per level")
        sizes = (self.num_points,) + tuple(self.centroids)
        if any(b > a for a, b in zip(sizes, sizes[1:])) or any(k > a for k, a in zip(self.neighbours, sizes)):
            raise ValueError(f"PointNet2Config: each level needs centroids and neighbours <= the points it "
                             f"samples from, got num_points={self.num_points}, centroids={self.centroids}, "
                             f"neighbours={self.neighbours}")


CONFIG = PointNet2Config()


# Sampling and grouping (fixed shapes, masks)


def resample(points, valid, n: int):
    """The valid points (in their order) evenly resampled to ``n`` rows: ``(points (n, 3), ok)``.
    Index ``i`` takes the ``floor(i * nv / n)``-th valid point; ``ok`` is False for an empty cloud."""
    points = jnp.where(valid[:, None], jnp.asarray(points, jnp.float32), 0.0)
    order = jnp.argsort(~valid, stable=True)  # valid rows first, in their order
    nv = jnp.sum(valid).astype(jnp.int32)
    pos = (jnp.arange(n, dtype=jnp.int32) * jnp.maximum(nv, 1)) // n
    return points[order[pos]], nv > 0


def normalise(points):
    """Points (n, 3) centred on their centroid and divided by their RMS radius (similarity invariance)."""
    q = points - points.mean(0)
    r = jnp.sqrt(jnp.maximum(jnp.mean(jnp.sum(q * q, -1)), 1e-12))
    return q / r


def farthest_point_sampling(points, valid, n: int):
    """Indices (n,) int32 of ``n`` valid points chosen greedily, each the farthest (Euclidean) from
    those already chosen; the first is the valid point farthest from the valid centroid. When fewer
    than ``n`` points are valid the remaining picks repeat chosen ones (distance 0)."""
    w = valid.astype(points.dtype)
    c = (w[:, None] * points).sum(0) / jnp.maximum(w.sum(), 1.0)
    d0 = jnp.where(valid, jnp.sum((points - c) ** 2, -1), -1.0)
    first = jnp.argmax(d0)

    def body(i, state):
        idx, dist = state
        last = points[idx[i - 1]]
        dist = jnp.minimum(dist, jnp.sum((points - last) ** 2, -1))
        return idx.at[i].set(jnp.argmax(dist).astype(jnp.int32)), dist

    idx = jnp.zeros(n, jnp.int32).at[0].set(first.astype(jnp.int32))
    dist = jnp.where(valid, jnp.inf, -1.0)
    idx, _ = jax.lax.fori_loop(1, n, body, (idx, dist))
    return idx


def ball_group(centres, points, valid, radius: float, k: int):
    """PointNet++ ball query: for each centre (M, 3) the indices (M, k) of the first ``k`` valid
    points (in index order) within ``radius``; missing slots repeat the first one, and a centre
    with no point in its ball gets its nearest valid point. Also returns the count in the ball (M,).
    A cumulative count and a binary search per slot (no sort: top-k is slow on CPU)."""
    d2 = (jnp.sum(centres**2, -1)[:, None] + jnp.sum(points**2, -1)[None, :] - 2.0 * centres @ points.T)
    d2 = jnp.where(valid[None, :], d2, jnp.inf)
    inside = d2 <= radius**2
    count = jnp.cumsum(inside, axis=1, dtype=jnp.int32)
    idx = jax.vmap(lambda row: jnp.searchsorted(row, jnp.arange(1, k + 1, dtype=jnp.int32)))(count)
    n = count[:, -1]
    first = jnp.where(n > 0, idx[:, 0], jnp.argmin(d2, axis=1))
    idx = jnp.where(jnp.arange(k)[None, :] < n[:, None], idx, first[:, None])
    return idx.astype(jnp.int32), n


# The network


def cylindrical(v):
    """Yaw-invariant coordinates (..., 2) of vectors (..., 3): distance from the y axis (the first
    camera's "down" axis, close to gravity) and the y component."""
    return jnp.stack([jnp.sqrt(v[..., 0] ** 2 + v[..., 2] ** 2 + 1e-8), v[..., 1]], -1)


class SetAbstraction(nn.Module):
    """One PointNet++ level: a shared MLP (Dense, LayerNorm, ReLU) on each grouped point's
    cylindrical offset from its centre / radius, its cylindrical position in the cloud and its
    features, max-pooled over the group."""

    features: tuple[int, ...]
    radius: float

    @nn.compact
    def __call__(self, xyz, feats, centre_idx, group_idx):
        centres = xyz[centre_idx]
        pts = xyz[group_idx]  # (M, k, 3)
        h = jnp.concatenate([cylindrical(pts - centres[:, None, :]) / self.radius, cylindrical(pts)], -1)
        if feats is not None:
            h = jnp.concatenate([h, feats[group_idx]], -1)
        for f in self.features:
            h = nn.relu(nn.LayerNorm(epsilon=1e-4)(nn.Dense(f)(h)))
        return centres, h.max(axis=1)


class PointNet2(nn.Module):
    """The encoder of one cloud: ``(points (N, 3), valid (N,)) -> unit descriptor (out_dim,)``
    (zero for an empty cloud). Batch it with ``jax.vmap``."""

    cfg: PointNet2Config = CONFIG

    @nn.compact
    def __call__(self, points, valid):
        cfg = self.cfg
        xyz, ok = resample(points, valid, cfg.num_points)
        xyz = normalise(xyz)
        feats = None
        for level, (m, k, r, mlp) in enumerate(zip(cfg.centroids, cfg.neighbours, cfg.radii, cfg.mlps)):
            everyone = jnp.ones(xyz.shape[0], bool)
            centre_idx = farthest_point_sampling(xyz, everyone, m)
            group_idx, _ = ball_group(xyz[centre_idx], xyz, everyone, r, k)
            xyz, feats = SetAbstraction(mlp, r, name=f"sa{level + 1}")(xyz, feats, centre_idx, group_idx)
        d = nn.Dense(cfg.out_dim, name="head")(feats.max(axis=0))
        d = d / jnp.maximum(jnp.linalg.norm(d), 1e-12)
        return jnp.where(ok, d, 0.0)


def init_params(key, cfg: PointNet2Config = CONFIG):
    """Fresh parameters (a nested dict of float32 arrays)."""
    pts = jax.random.normal(key, (cfg.num_points, 3))
    return PointNet2(cfg).init(key, pts, jnp.ones(cfg.num_points, bool))["params"]


def apply(params, points, valid=None, cfg: PointNet2Config = CONFIG):
    """The descriptor (out_dim,) of one cloud with the given parameters (see :class:`PointNet2`)."""
    points = jnp.asarray(points, jnp.float32)
    valid = jnp.ones(points.shape[0], bool) if valid is None else jnp.asarray(valid, bool)
    if points.ndim != 2 or points.shape[-1] != 3 or valid.shape != points.shape[:1]:
        raise ValueError(f"points: expected (N, 3) with valid (N,), got {points.shape} and {valid.shape}")
    return PointNet2(cfg).apply({"params": params}, points, valid)


# Weights: save / load with a checksum


def _checksum(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(json.dumps([name, a.dtype.str, list(a.shape)]).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def save_params(params, path, cfg: PointNet2Config = CONFIG, info: dict | None = None) -> None:
    """Write ``params`` as float16 arrays + a JSON header with their SHA-256, atomically."""
    flat = {"/".join(k): np.asarray(v, np.float16) for k, v in traverse_util.flatten_dict(params).items()}
    meta = {"format": FORMAT_VERSION, "config": dataclasses.asdict(cfg), "sha256": _checksum(flat),
            "info": info or {}}
    with atomic_write(path) as f:
        np.savez(f, __meta__=np.array(json.dumps(meta)), **flat)


def read_meta(path=None) -> dict:
    """The JSON header of a weight file (format, config, sha256, training info)."""
    path = Path(DEFAULT_WEIGHTS if path is None else path)
    return _read(path)[1]


def _read(path: Path):
    if not path.exists():
        raise WeightsError(f"PointNet++ weights {path}: file not found "
                           "(train them with experiments/train_pointnet2.py)")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, KeyError) as e:
        raise WeightsError(f"PointNet++ weights {path}: unreadable, truncated or corrupted ({e})") from e
    if "__meta__" not in arrays:
        raise WeightsError(f"PointNet++ weights {path}: no __meta__ header (not a cm3d weight file)")
    try:
        meta = json.loads(str(arrays.pop("__meta__")))
    except json.JSONDecodeError as e:
        raise WeightsError(f"PointNet++ weights {path}: corrupted header ({e})") from e
    return arrays, meta


def load_params(path=None, cfg: PointNet2Config = CONFIG):
    """Parameters (nested dict of float32 numpy arrays) from a weight file (default: the shipped one).
    Raises :class:`WeightsError` when the file is missing, corrupt, or of another format or architecture."""
    path = Path(DEFAULT_WEIGHTS if path is None else path)
    arrays, meta = _read(path)
    if meta.get("format") != FORMAT_VERSION:
        raise WeightsError(f"PointNet++ weights {path}: format version {meta.get('format')}, expected {FORMAT_VERSION}")
    if meta.get("sha256") != _checksum(arrays):
        raise WeightsError(f"PointNet++ weights {path}: SHA-256 checksum mismatch (the file was altered or corrupted)")
    if meta.get("config") != json.loads(json.dumps(dataclasses.asdict(cfg))):
        raise WeightsError(f"PointNet++ weights {path}: trained for architecture {meta.get('config')}, "
                           f"not {dataclasses.asdict(cfg)}")
    expected = traverse_util.flatten_dict(jax.eval_shape(lambda: init_params(jax.random.PRNGKey(0), cfg)))
    expected = {"/".join(k): v.shape for k, v in expected.items()}
    got = {k: v.shape for k, v in arrays.items()}
    if got != expected:
        raise WeightsError(f"PointNet++ weights {path}: parameter names/shapes {got} differ from "
                           f"the model's {expected}")
    flat = {tuple(k.split("/")): np.asarray(v, np.float32) for k, v in arrays.items()}
    return traverse_util.unflatten_dict(flat)


@functools.lru_cache(maxsize=4)
def _cached(path: str):
    return load_params(path)


def shipped_params():
    """The shipped parameters (loaded and checked once per process, host-side numpy arrays)."""
    return _cached(str(DEFAULT_WEIGHTS))


def cloud_descriptor(points, valid=None):
    """Learned descriptor (512,) float32, unit norm (zero for an empty cloud), of a voxelised cloud
    (N, 3) in its own frame and scale with mask (N,), using the shipped weights (closed over as
    constants). Jittable, vmappable; used by :func:`cm3d.memory.cloud_descriptor` when
    ``MemoryConfig.descriptor_3d == "pointnet2"``."""
    return apply(shipped_params(), points, valid)
