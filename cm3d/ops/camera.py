"""Pinhole camera geometry: unproject depth, project points, ego-motion flow.

Pixel convention (OpenCV): pixel ``(u, v)`` is column ``u``, row ``v``, and its centre sits at the
integer coordinate, so a pixel centre's ray is ``K^{-1} (u, v, 1)``. Depth is the camera-frame
``z`` (not the ray length), in the sequence's units. Flow ``F[v, u] = (du, dv)`` sends pixel
``(u, v)`` of frame ``t`` to ``(u + du, v + dv)`` in frame ``t + 1``: the forward flow that
``cv2.calcOpticalFlow*(prev, next)`` returns. Poses are ``cam_to_world`` (see :mod:`cm3d.ops.se3`).
All functions broadcast over leading (frame) axes.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from cm3d.ops import se3

MIN_DEPTH = 1e-6


def pixel_grid(height: int, width: int, dtype=jnp.float32) -> jnp.ndarray:
    """Pixel-centre coordinates (H, W, 2) as ``(u, v)``."""
    v, u = jnp.meshgrid(jnp.arange(height, dtype=dtype), jnp.arange(width, dtype=dtype), indexing="ij")
    return jnp.stack([u, v], axis=-1)


def rays(uv, K):
    """Camera rays ``K^{-1} (u, v, 1)`` (..., N, 3) of pixels uv (..., N, 2) (z = 1).

    NumPy inputs are computed in NumPy (host code keeps float64), JAX inputs in JAX.
    """
    xp = np if isinstance(uv, np.ndarray) and isinstance(K, np.ndarray) else jnp
    uv1 = xp.concatenate([uv, xp.ones_like(uv[..., :1])], -1)
    return xp.einsum("...ij,...nj->...ni", xp.linalg.inv(K), uv1)


def backproject(uv, depth, K, cam_to_world=None):
    """Points (..., N, 3) of pixels uv (..., N, 2) at camera depth z (..., N): ``z K^{-1} (u, v, 1)``,
    in the camera frame, or in the world when ``cam_to_world`` (..., 4, 4) is given."""
    pc = rays(uv, K) * depth[..., None]
    if cam_to_world is None:
        return pc
    xp = np if isinstance(pc, np.ndarray) and isinstance(cam_to_world, np.ndarray) else jnp
    return xp.einsum("...ij,...nj->...ni", cam_to_world[..., :3, :3], pc) + cam_to_world[..., None, :3, 3]


def unproject_camera(depth: jnp.ndarray, K: jnp.ndarray) -> jnp.ndarray:
    """Camera-frame points (..., H, W, 3) from depth (..., H, W) and intrinsics (..., 3, 3)."""
    H, W = depth.shape[-2:]
    uv1 = jnp.concatenate([pixel_grid(H, W, depth.dtype), jnp.ones((H, W, 1), depth.dtype)], -1)
    rays = jnp.einsum("...ij,hwj->...hwi", jnp.linalg.inv(K), uv1)
    return rays * depth[..., None]


def unproject(depth: jnp.ndarray, K: jnp.ndarray, cam_to_world: jnp.ndarray) -> jnp.ndarray:
    """World points (..., H, W, 3) of every pixel: ``T (z K^{-1} [u, v, 1])``."""
    pc = unproject_camera(depth, K)
    R, t = cam_to_world[..., :3, :3], cam_to_world[..., :3, 3]
    return jnp.einsum("...ij,...hwj->...hwi", R, pc) + t[..., None, None, :]


def project(points: jnp.ndarray, K: jnp.ndarray, cam_to_world: jnp.ndarray):
    """Project world points (..., N, 3) into a camera.

    Returns ``(uv, z)``: pixel coordinates (..., N, 2) and camera-frame depth (..., N). Points with
    ``z <= 0`` get finite but meaningless ``uv``; mask them with ``z > 0``.
    """
    pc = se3.transform_points(se3.inverse(cam_to_world), points)
    z = pc[..., 2]
    zs = jnp.where(jnp.abs(z) < MIN_DEPTH, MIN_DEPTH, z)
    uvw = jnp.einsum("...ij,...nj->...ni", K, pc)
    return uvw[..., :2] / zs[..., None], z


def ego_flow(depth0, K0, cam_to_world0, K1, cam_to_world1):
    """Flow (..., H, W, 2) a static scene shows from frame 0 to frame 1, and its validity (..., H, W).

    Each pixel of frame 0 is lifted with its depth, moved by the relative pose and projected into
    frame 1. Valid where the input depth is positive and the point lies in front of camera 1.
    """
    H, W = depth0.shape[-2:]
    pts = unproject(depth0, K0, cam_to_world0).reshape(depth0.shape[:-2] + (H * W, 3))
    uv1, z1 = project(pts, K1, cam_to_world1)
    flow = uv1.reshape(depth0.shape + (2,)) - pixel_grid(H, W, depth0.dtype)
    valid = (depth0 > MIN_DEPTH) & (z1.reshape(depth0.shape) > MIN_DEPTH)
    return jnp.where(valid[..., None], flow, 0.0), valid


def depth_smooth(depth, max_ratio: float):
    """(..., H, W) bool: the pixel's 3x3 neighbourhood has positive depth spanning less than the
    ratio ``max_ratio`` (max / min): no depth edge, no hole, so the pixel's depth measures the
    surface a slightly wrong pixel would also see."""
    win = (1,) * (depth.ndim - 2) + (3, 3)
    lo = jax.lax.reduce_window(depth, jnp.inf, jax.lax.min, win, (1,) * depth.ndim, "SAME")
    hi = jax.lax.reduce_window(depth, -jnp.inf, jax.lax.max, win, (1,) * depth.ndim, "SAME")
    return (lo > MIN_DEPTH) & (hi < max_ratio * lo)
