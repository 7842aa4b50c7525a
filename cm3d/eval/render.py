"""Depth images of a point cloud seen by posed pinhole cameras: a jittable z-buffer splatter.

Used to re-render depth from a fused static map (the paper's Table 1: depth from the refined map
against the prior's per-frame depth). Each point is projected into the camera and written, with
its camera depth ``z``, to the pixel it falls in and to the ``(2 r + 1)^2`` pixels around it
(``radius = r``, a square splat that fills the gaps between the points of a sparse map); every
pixel keeps the smallest ``z`` written to it (the z-buffer), so the nearest surface wins. With a
``tolerance`` the z-buffer is soft: the pixel takes the mean ``z`` of the writes within
``(1 + tolerance)`` of the nearest one, so several noisy samples of the front surface are averaged
while the surfaces behind it stay hidden.

Poses are ``cam_to_world`` 4x4 and pixels follow :mod:`cm3d.ops.camera` (pixel ``(u, v)`` is
column ``u``, row ``v``; integer coordinates at pixel centres). Everything is pure JAX with fixed
shapes: clouds are padded to a capacity with a validity mask; image size and splat radius are
static.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp


def _check(points, valid, cam_to_world, K):
    if points.ndim != 2 or points.shape[-1] != 3:
        raise ValueError(f"render_depth: points must be (N, 3), got {points.shape}")
    if valid.shape != points.shape[:1]:
        raise ValueError(f"render_depth: valid must be ({points.shape[0]},), got {valid.shape}")
    if cam_to_world.shape[-2:] != (4, 4):
        raise ValueError(f"render_depth: cam_to_world must be (..., 4, 4), got {cam_to_world.shape}")
    if K.shape[-2:] != (3, 3):
        raise ValueError(f"render_depth: intrinsic must be (..., 3, 3), got {K.shape}")


def _splat_one(points, valid, cam_to_world, K, height: int, width: int, radius: int, near: float,
               tolerance=0.0):
    R, t = cam_to_world[:3, :3], cam_to_world[:3, 3]
    pc = (points - t) @ R  # world -> camera: R^T (p - t)
    z = pc[:, 2]
    front = valid & (z > near)
    zs = jnp.where(front, z, 1.0)
    u = (K[0, 0] * pc[:, 0] + K[0, 1] * pc[:, 1]) / zs + K[0, 2]
    v = K[1, 1] * pc[:, 1] / zs + K[1, 2]
    finite = jnp.isfinite(u) & jnp.isfinite(v)
    # rounding to the nearest pixel centre; clip first so the int cast cannot overflow
    cu = jnp.round(jnp.clip(jnp.where(finite, u, -1e6), -1e6, 1e6)).astype(jnp.int32)
    cv = jnp.round(jnp.clip(jnp.where(finite, v, -1e6), -1e6, 1e6)).astype(jnp.int32)
    offs = jnp.arange(-radius, radius + 1, dtype=jnp.int32)
    du, dv = jnp.meshgrid(offs, offs, indexing="xy")
    cols = cu[None, :] + du.reshape(-1, 1)  # (O, N)
    rows = cv[None, :] + dv.reshape(-1, 1)
    ok = front[None, :] & finite[None, :] & (cols >= 0) & (cols < width) & (rows >= 0) & (rows < height)
    npx = height * width
    flat = jnp.where(ok, rows * width + cols, npx)  # out-of-image writes go to a spare slot
    zz = jnp.broadcast_to(z, flat.shape)
    flat, zz = flat.reshape(-1), zz.reshape(-1)
    zmin = jnp.full(npx + 1, jnp.inf, dtype=points.dtype).at[flat].min(zz)
    # soft z-buffer: the mean depth of the writes within (1 + tolerance) of the nearest one
    near_enough = zz <= zmin[flat] * (1.0 + tolerance)
    total = jnp.zeros(npx + 1, points.dtype).at[flat].add(jnp.where(near_enough, zz, 0.0))
    count = jnp.zeros(npx + 1, points.dtype).at[flat].add(near_enough.astype(points.dtype))
    covered = jnp.isfinite(zmin[:npx]).reshape(height, width)
    depth = (total[:npx] / jnp.maximum(count[:npx], 1.0)).reshape(height, width)
    return jnp.where(covered, depth, 0.0), covered


@functools.partial(jax.jit, static_argnames=("height", "width", "radius"))
def render_depth(points, valid, cam_to_world, K, *, height: int, width: int, radius: int = 0,
                 near: float = 1e-6, tolerance=0.0):
    """Z-buffered depth image of a point cloud in one camera.

    points (N, 3) world; valid (N,) bool (padding False); cam_to_world (4, 4); K (3, 3) pinhole
    intrinsics; height, width: image size (static); radius: splat half-size in pixels (static,
    0 = one pixel per point); near: points with camera ``z <= near`` are not drawn; tolerance: a
    soft z-buffer, the pixel's depth is the mean ``z`` of the writes with ``z <= (1 + tolerance)
    z_min`` (0: the nearest point's depth, a hard z-buffer).
    Returns (depth (H, W), 0 where nothing was drawn; covered (H, W) bool).
    """
    points, valid = jnp.asarray(points), jnp.asarray(valid, bool)
    cam_to_world, K = jnp.asarray(cam_to_world, points.dtype), jnp.asarray(K, points.dtype)
    _check(points, valid, cam_to_world, K)
    if radius < 0:
        raise ValueError(f"render_depth: radius must be >= 0, got {radius}")
    return _splat_one(points, valid, cam_to_world, K, height, width, radius, near, tolerance)


@functools.partial(jax.jit, static_argnames=("height", "width", "radius"))
def render_depths(points, valid, cam_to_world, K, *, height: int, width: int, radius: int = 0,
                  near: float = 1e-6, tolerance=0.0):
    """:func:`render_depth` for a sequence of cameras, one frame after another (``lax.map``, so
    memory stays that of one frame): cam_to_world (S, 4, 4), K (S, 3, 3) or (3, 3).
    Returns (depth (S, H, W), covered (S, H, W))."""
    points, valid = jnp.asarray(points), jnp.asarray(valid, bool)
    cam_to_world = jnp.asarray(cam_to_world, points.dtype)
    K = jnp.asarray(K, points.dtype)
    _check(points, valid, cam_to_world, K)
    if cam_to_world.ndim != 3:
        raise ValueError(f"render_depths: cam_to_world must be (S, 4, 4), got {cam_to_world.shape}")
    if radius < 0:
        raise ValueError(f"render_depths: radius must be >= 0, got {radius}")
    K = jnp.broadcast_to(K, (cam_to_world.shape[0], 3, 3))
    return jax.lax.map(lambda a: _splat_one(points, valid, a[0], a[1], height, width, radius, near, tolerance),
                        (cam_to_world, K))


def pad_points(points, capacity: int | None = None):
    """Host helper: pad (N, 3) points to ``capacity`` rows (default: the next power of two, so
    clouds of similar sizes share one compiled renderer) -> (points (C, 3), valid (C,))."""
    import numpy as np

    pts = np.asarray(points).reshape(-1, 3)
    n = len(pts)
    cap = capacity if capacity is not None else max(1, 1 << max(0, (n - 1).bit_length()))
    if cap < n:
        raise ValueError(f"pad_points: capacity {cap} < {n} points")
    out = np.zeros((cap, 3), pts.dtype if pts.dtype.kind == "f" else np.float32)
    out[:n] = pts
    valid = np.zeros(cap, bool)
    valid[:n] = True
    return out, valid
