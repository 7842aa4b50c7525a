"""Overlap alignment: the Sim(3) between consecutive chunks from their shared frames.

On the frames two chunks share, the same pixel grid is lifted with each chunk's depth and pose (no
matching needed); with the camera centres they feed a robust Sim(3) ``A_k`` (chunk k -> k-1,
:func:`cm3d.solvers.sim3_irls.irls_sim3`). Chaining ``G_k = G_{k-1} A_k`` gives chunk 0's frame.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from cm3d.data.sequence import Sequence
from cm3d.ops import camera, robust, se3, sim3
from cm3d.solvers.sim3_irls import irls_sim3


@dataclasses.dataclass(frozen=True)
class StitchConfig:
    """Options of the overlap alignment (all static).

    grid: (rows, cols) pixels sampled on every shared frame; centre_weight: the camera centres'
    total weight relative to the sampled points'; robust_iterations, robust_k: IRLS rounds and the
    Cauchy scale in robust sigmas (MAD of the point residuals); inlier_sigmas: residuals within this
    many robust sigmas count as inliers in the diagnostics.
    """

    grid: tuple[int, int] = (12, 16)
    centre_weight: float = 1.0
    robust_iterations: int = 8
    robust_k: float = 2.0
    inlier_sigmas: float = 3.0

    def __post_init__(self):
        if len(self.grid) != 2 or min(self.grid) < 1:
            raise ValueError(f"StitchConfig.grid: expected (rows, cols) >= 1, got {self.grid}")
        for name in ("centre_weight", "robust_k", "inlier_sigmas"):
            if not getattr(self, name) >= 0 or (name != "centre_weight" and getattr(self, name) == 0):
                raise ValueError(f"StitchConfig.{name}: must be > 0, got {getattr(self, name)}")
        if self.robust_iterations < 0:
            raise ValueError(f"StitchConfig.robust_iterations: must be >= 0, got {self.robust_iterations}")


@dataclasses.dataclass(frozen=True)
class Boundary:
    """Diagnostics of the boundary between chunks ``chunk - 1`` and ``chunk``.

    frames: global [start, stop) shared; scale: of ``A_k`` (1 for naive); cumulative_scale: common
    units per unit of ``chunk``; rotation_deg: of ``A_k``; rmse_points / rmse_centres: inlier pixel /
    camera-centre residuals (common units); rel_rmse_points: over the median depth; inlier_fraction:
    within ``inlier_sigmas``; num_points: valid lifted pixels.
    """

    chunk: int
    frames: tuple[int, int]
    scale: float
    cumulative_scale: float
    rotation_deg: float
    rmse_points: float
    rmse_centres: float
    rel_rmse_points: float
    inlier_fraction: float
    num_points: int


@struct.dataclass
class OverlapFit:
    """:func:`align_overlap`'s result: transform (4, 4) chunk k -> chunk k-1 and its diagnostics
    (lengths in chunk k-1's units; median_depth: the shared pixels' median distance to their camera)."""

    transform: jnp.ndarray
    scale: jnp.ndarray
    rotation_deg: jnp.ndarray
    rmse_points: jnp.ndarray
    rmse_centres: jnp.ndarray
    inlier_fraction: jnp.ndarray
    num_points: jnp.ndarray
    median_depth: jnp.ndarray


def sample_grid(H: int, W: int, grid):
    """Rows (R,) and columns (C,) of a ``grid = (R, C)`` of pixel centres of an H x W image."""
    rows = ((np.arange(grid[0]) + 0.5) * H / grid[0]).astype(np.int32)
    cols = ((np.arange(grid[1]) + 0.5) * W / grid[1]).astype(np.int32)
    return rows, cols


def lift_pixels(depth, intrinsic, cam_to_world, rows, cols):
    """Pixels ``rows x cols`` of frames (O, H, W) lifted to world points -> ((O * P, 3), valid (O * P,)).

    depth (O, H, W) camera z; intrinsic (O, 3, 3); cam_to_world (O, 4, 4); rows (R,), cols (C,) int.
    """
    d = depth[:, rows[:, None], cols[None, :]].reshape(depth.shape[0], -1)  # (O, P)
    v, u = jnp.meshgrid(rows, cols, indexing="ij")
    uv = jnp.stack([u.ravel(), v.ravel()], -1).astype(cam_to_world.dtype)
    ok = jnp.isfinite(d) & (d > 0)
    pw = camera.backproject(uv, jnp.where(ok, d, 0.0), intrinsic, cam_to_world)
    return pw.reshape(-1, 3), ok.reshape(-1)


def _correspondences(prev, nxt, rows, cols, centre_weight):
    """src (chunk k) and dst (chunk k-1) points: lifted pixels then camera centres; base weights."""
    pa, oka = lift_pixels(prev[0], prev[1], prev[2], rows, cols)
    pb, okb = lift_pixels(nxt[0], nxt[1], nxt[2], rows, cols)
    ok = oka & okb
    O = prev[2].shape[0]
    npts = jnp.sum(ok)
    wc = jnp.where(npts > 0, centre_weight * npts / O, 1.0)
    src = jnp.concatenate([pb, nxt[2][:, :3, 3]])
    dst = jnp.concatenate([pa, prev[2][:, :3, 3]])
    w0 = jnp.concatenate([ok.astype(src.dtype), jnp.full((O,), wc, src.dtype)])
    is_pt = jnp.concatenate([ok, jnp.zeros(O, bool)])
    centres = jnp.repeat(prev[2][:, :3, 3], rows.size * cols.size, 0)
    depth_a = jnp.where(oka, jnp.linalg.norm(pa - centres, axis=-1), 0.0)  # distance to the camera
    return src, dst, w0, is_pt, robust.masked_median(depth_a, oka)


def _residual_stats(A, src, dst, is_pt):
    """Residual norms (N,) of ``A src - dst`` and the robust sigma of the point residuals (> 0)."""
    r = jnp.linalg.norm(sim3.apply(A, src) - dst, axis=-1)
    spread = jnp.sqrt(jnp.mean(jnp.sum((dst - jnp.mean(dst, 0)) ** 2, -1)))
    sigma = jnp.maximum(robust.robust_sigma(r, is_pt), 1e-9 * spread + jnp.finfo(src.dtype).tiny)
    return r, sigma


@functools.partial(jax.jit, static_argnames=("cfg", "fit"))
def align_overlap(prev, nxt, A0=None, cfg: StitchConfig = StitchConfig(), fit: bool = True) -> OverlapFit:
    """Sim(3) ``A`` (4x4, ``[s R, t]``) mapping chunk k's frame to chunk k-1's, from their shared frames.

    prev, nxt: (depth (O, H, W), intrinsic (O, 3, 3), cam_to_world (O, 4, 4)) of the shared frames.
    Correspondences: the ``cfg.grid`` pixels lifted by each chunk plus the camera centres; robust
    IRLS. ``fit=False``: only the diagnostics of ``A0``. Returns :class:`OverlapFit`.
    """
    H, W = prev[0].shape[1:]
    rows, cols = (jnp.asarray(a) for a in sample_grid(H, W, cfg.grid))
    src, dst, w0, is_pt, med_depth = _correspondences(prev, nxt, rows, cols, cfg.centre_weight)
    n_pt = jnp.sum(is_pt)
    if fit:
        A = irls_sim3(src, dst, w0, lambda A: _residual_stats(A, src, dst, is_pt), cfg.robust_iterations,
                      cfg.robust_k)
    else:
        A = jnp.asarray(A0, src.dtype)
    r, sigma = _residual_stats(A, src, dst, is_pt)
    inl = is_pt & (r <= cfg.inlier_sigmas * sigma)
    n_in = jnp.sum(inl)
    cen = jnp.arange(src.shape[0]) >= src.shape[0] - prev[2].shape[0]
    s = sim3.scale(A)
    return OverlapFit(
        transform=A, scale=s, rotation_deg=jnp.rad2deg(se3.rotation_angle(A[:3, :3] / s)),
        rmse_points=jnp.sqrt(jnp.sum(jnp.where(inl, r * r, 0.0)) / jnp.maximum(n_in, 1)),
        rmse_centres=jnp.sqrt(jnp.sum(jnp.where(cen, r * r, 0.0)) / jnp.maximum(jnp.sum(cen), 1)),
        inlier_fraction=n_in / jnp.maximum(n_pt, 1), num_points=n_pt, median_depth=med_depth)


def shared_frames(chunk: Sequence, sl: slice):
    """(depth, intrinsic, cam_to_world) of a chunk's frames ``sl``: :func:`align_overlap`'s inputs."""
    return tuple(jnp.asarray(np.asarray(a)) for a in (chunk.depth[sl], chunk.intrinsic[sl], chunk.cam_to_world[sl]))


def align_boundaries(chunks, ranges, overlaps, cfg: StitchConfig = StitchConfig(), A=None):
    """Fit every boundary's ``A_k`` (or, given ``A`` (K, 4, 4), only evaluate it) and chain
    ``G_k = G_{k-1} A_k`` in float64 on the host. Returns (A (K, 4, 4), G (K, 4, 4), Boundary tuple)."""
    fit = A is None
    A = [np.eye(4)] + [None] * (len(chunks) - 1) if fit else [np.asarray(a, np.float64) for a in A]
    G, out = [np.eye(4)], []
    for k in range(1, len(chunks)):
        o = overlaps[k - 1]
        prev, nxt = shared_frames(chunks[k - 1], slice(-o, None)), shared_frames(chunks[k], slice(0, o))
        f = align_overlap(prev, nxt, None if fit else jnp.asarray(A[k]), cfg=cfg, fit=fit)
        A[k] = np.asarray(f.transform, np.float64)
        G.append(G[-1] @ A[k])
        unit = float(sim3.scale(G[k - 1]))  # common units per unit of chunk k-1
        rmse = float(f.rmse_points)
        out.append(Boundary(chunk=k, frames=(ranges[k][0], ranges[k][0] + o), scale=float(f.scale),
                            cumulative_scale=float(sim3.scale(G[k])), rotation_deg=float(f.rotation_deg),
                            rmse_points=rmse * unit, rmse_centres=float(f.rmse_centres) * unit,
                            rel_rmse_points=rmse / max(float(f.median_depth), 1e-300),
                            inlier_fraction=float(f.inlier_fraction), num_points=int(f.num_points)))
    return np.stack(A), np.stack(G), tuple(out)
