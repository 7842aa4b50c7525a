"""Where a frame pair cannot tell motion from ego-motion: occlusions, depth edges, unreliable flow.

At a depth discontinuity parallax occludes and disoccludes pixels, and optical flow (which is
smooth over a patch) mixes the motions of both sides; so the residual to the ego flow is large
there although nothing moves. Three pure tests, all (H, W), fixed shapes:

* :func:`forward_backward_consistent`: the backward flow, sampled where the forward flow lands,
  sends the pixel back (Sundaram et al. 2010: ``|w + ŵ|² <= α (|w|² + |ŵ|²) + β``);
* :func:`visible_in_partner`: the static-scene point lands in front of (not behind) the partner
  frame's depth (a z-buffer test with both depth maps);
* :func:`depth_range_residual`: the distance of the flow to the segment of ego flows that any depth
  within the pixel's neighbourhood (the flow's support) explains; a straight segment, the
  projection of the viewing-ray interval. Inside a surface the interval is a point and this is
  the ordinary residual; across a depth edge it spans both sides.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from cm3d.ops import camera, se3
from cm3d.trajectory import bilinear


def forward_backward_consistent(flow, flow_back, alpha: float = 0.01, beta_px2: float = 0.5):
    """(H, W) bool: forward flow (H, W, 2) t -> t2 and backward flow t2 -> t agree at the pixel.

    ``|w + ŵ(p + w)|² <= alpha (|w|² + |ŵ(p + w)|²) + beta_px2``, ``ŵ`` sampled bilinearly; a pixel
    whose flow leaves the image is inconsistent (nothing there to check against).
    """
    H, W = flow.shape[:2]
    tgt = camera.pixel_grid(H, W, flow.dtype) + flow
    back = bilinear(flow_back[None], jnp.zeros(H * W, jnp.int32), tgt.reshape(-1, 2)).reshape(H, W, 2)
    err = jnp.sum((flow + back) ** 2, -1)
    tol = alpha * (jnp.sum(flow ** 2, -1) + jnp.sum(back ** 2, -1)) + beta_px2
    inside = (tgt[..., 0] >= 0) & (tgt[..., 0] <= W - 1) & (tgt[..., 1] >= 0) & (tgt[..., 1] <= H - 1)
    return inside & (err <= tol)


def visible_in_partner(depth, K0, K1, rel, depth1, rel_tol: float):
    """(H, W) bool: frame-0 pixels whose static-scene point is not hidden in frame 1.

    The point (``depth`` lifted with ``K0``, moved by ``rel`` camera 0 -> camera 1) is hidden when
    its depth in camera 1 exceeds ``(1 + rel_tol)`` times the *largest* partner depth ``depth1``
    (H, W) of the four pixels around where it lands (a conservative z-buffer: behind every
    neighbour). Pixels landing outside, or on no valid partner depth, count as visible (judged by
    the other tests).
    """
    H, W = depth.shape
    grid = camera.pixel_grid(H, W, depth.dtype)
    X = camera.backproject(grid.reshape(-1, 2), depth.reshape(-1), K0)
    Xc = se3.transform_points(rel.astype(depth.dtype), X)
    z = Xc[:, 2]
    uvw = Xc @ K1.astype(depth.dtype).T
    uv = uvw[:, :2] / jnp.where(jnp.abs(z) < camera.MIN_DEPTH, camera.MIN_DEPTH, z)[:, None]
    x0 = jnp.clip(jnp.floor(uv[:, 0]).astype(jnp.int32), 0, W - 2)
    y0 = jnp.clip(jnp.floor(uv[:, 1]).astype(jnp.int32), 0, H - 2)
    d4 = jnp.stack([depth1[y0, x0], depth1[y0, x0 + 1], depth1[y0 + 1, x0], depth1[y0 + 1, x0 + 1]], -1)
    dmax = jnp.max(d4, -1)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1)
    hidden = inside & (dmax > camera.MIN_DEPTH) & (z > (1.0 + rel_tol) * dmax)
    return ~hidden.reshape(H, W)


def local_depth_range(depth, valid, radius: int):
    """(min, max) (H, W) of the valid depths within ``radius`` px (a (2r+1) square); the pixel's own
    depth where none is valid."""
    k = 2 * radius + 1
    big = jnp.asarray(jnp.finfo(depth.dtype).max, depth.dtype)
    lo = jax.lax.reduce_window(jnp.where(valid, depth, big), big, jax.lax.min, (k, k), (1, 1), "SAME")
    hi = jax.lax.reduce_window(jnp.where(valid, depth, 0.0), jnp.asarray(0.0, depth.dtype), jax.lax.max, (k, k),
                               (1, 1), "SAME")
    return jnp.where(lo < big, lo, depth), jnp.where(hi > 0, hi, depth)


def depth_range_residual(flow, depth, valid, K0, K1, rel, radius: int):
    """(residual (H, W) px, ego flow (H, W, 2), ego validity): the distance of ``flow`` to the segment
    between the ego flows of the nearest and the farthest valid depth within ``radius`` px.

    The ego flow of a pixel is linear along its viewing ray in the image (a 3D segment projects to a
    2D segment), so the segment holds every static flow a depth in ``[min, max]`` explains. ``rel``:
    camera 0 -> camera 1 (4, 4). The ego flow returned is that of the pixel's own depth.
    """
    eye = jnp.eye(4, dtype=depth.dtype)
    inv = se3.inverse(rel)
    lo, hi = local_depth_range(depth, valid, radius)
    ego, ok = camera.ego_flow(depth, K0, eye, K1, inv)
    a, ok_a = camera.ego_flow(lo, K0, eye, K1, inv)
    b, ok_b = camera.ego_flow(hi, K0, eye, K1, inv)
    ab = b - a
    t = jnp.clip(jnp.sum((flow - a) * ab, -1) / jnp.maximum(jnp.sum(ab * ab, -1), 1e-12), 0.0, 1.0)
    r = jnp.linalg.norm(flow - a - t[..., None] * ab, axis=-1)
    return r, ego, ok & ok_a & ok_b
