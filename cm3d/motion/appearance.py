"""Appearance check: does the image itself reject the static-scene hypothesis of a pixel?

The residual-flow cue trusts the optical flow. Where the flow is ill-posed (textureless or glossy
surfaces, sensor-noise blobs, repeated texture) it can be far from the ego flow although nothing
moves, and the residual reads that as motion. The images decide between the two hypotheses: warp
the partner frame by the ego flow (the pixel is static) and by the optical flow (it moves as the
flow says), and compare the patch dissimilarities. On a textured mover the ego warp lands on other
texture while the flow warp matches; on a textureless surface both warps match equally well, so
the image gives no evidence of motion.

Dissimilarity is the zero-mean patch difference (the standard deviation of ``I_t - I_t2(warp)``
over a ``(2r+1)²`` box), insensitive to a local brightness offset (exposure, a light's gain). The
margin is ``k`` robust sigmas of the excess dissimilarity on the presumed-static pixels of the same
frame pair, so ``appearance_k`` means the same at any contrast, noise level or resolution.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from cm3d.ops import camera, robust
from cm3d.ops.robust import masked_median_low
from cm3d.trajectory import bilinear

_LUMA = (0.299, 0.587, 0.114)
STATS_STRIDE = 4


def gray(image):
    """Luma in [0, 1] (H, W) float32 of an (H, W, 3) uint8 (or [0, 1] float) image."""
    img = jnp.asarray(image, jnp.float32)
    if jnp.issubdtype(jnp.asarray(image).dtype, jnp.integer):
        img = img / 255.0
    return img @ jnp.asarray(_LUMA, jnp.float32)


def box_mean(x, radius: int):
    """Mean over the (2r+1)² box around each pixel (H, W), counting only pixels inside the image."""
    k = 2 * radius + 1
    s = jax.lax.reduce_window(x, 0.0, jax.lax.add, (k, k), (1, 1), "SAME")
    H, W = x.shape
    rows, cols = (np.minimum(np.arange(n) + radius, n - 1) - np.maximum(np.arange(n) - radius, 0) + 1 for n in (H, W))
    return s / jnp.asarray(np.outer(rows, cols), x.dtype)  # pixels inside the box (a constant, not folded)


def warp_dissimilarity(gray_t, gray_t2, flow, radius: int):
    """Zero-mean patch dissimilarity (H, W) of frame t and frame t2 sampled at ``p + flow(p)``:
    ``sqrt(box(d²) − box(d)²)`` with ``d = I_t − I_t2(p + flow)`` (bilinear, clamped at the border)."""
    H, W = gray_t.shape
    tgt = (camera.pixel_grid(H, W, flow.dtype) + flow).reshape(-1, 2)
    warped = bilinear(gray_t2[None, :, :, None], jnp.zeros(H * W, jnp.int32), tgt).reshape(H, W)
    d = gray_t - warped
    return jnp.sqrt(jnp.maximum(box_mean(d * d, radius) - box_mean(d, radius) ** 2, 0.0))


def static_rejected(image_t, image_t2, flow, ego, reference, radius: int = 2, k: float = 3.0, q: float = 0.0):
    """(H, W) bool: pixels where the image rejects the static hypothesis.

    ``excess = e_ego - e_flow``, the ego-flow warp's dissimilarity above the optical-flow warp's
    (:func:`warp_dissimilarity`), exceeds its median over the ``reference`` pixels (presumed
    static: there both warps agree up to matching noise) by ``k`` robust sigmas (1.4826 MAD) of it
    there; and, with ``q > 0``, ``e_ego`` itself exceeds the ``q``-quantile of ``e_flow`` over the
    reference: the static hypothesis matches worse than most correct matches of the pair do (the
    flow minimises the dissimilarity, so on an ambiguous surface it always beats the ego warp by a
    little). Images (H, W, 3), flows (H, W, 2) frame t -> t2, reference (H, W) bool.
    """
    g0, g1 = gray(image_t), gray(image_t2)
    e_ego, e_flow = warp_dissimilarity(g0, g1, ego, radius), warp_dissimilarity(g0, g1, flow, radius)
    excess = e_ego - e_flow
    # the reference statistics from every STATS_STRIDE-th pixel (sorts of the full frame cost more
    # than the rest of the check; a few thousand samples fix a median and a quantile well)
    ex, ref = excess[::STATS_STRIDE, ::STATS_STRIDE], reference[::STATS_STRIDE, ::STATS_STRIDE]
    med = masked_median_low(ex, ref)
    sigma = robust.MAD_TO_SIGMA * masked_median_low(jnp.abs(ex - med), ref)
    out = excess > med + k * jnp.maximum(sigma, 1e-4)
    if q > 0:
        n = jnp.sum(ref)
        rank = jnp.floor((n - 1) * q).astype(jnp.int32)
        out &= e_ego > robust.kth_smallest(e_flow[::STATS_STRIDE, ::STATS_STRIDE].reshape(-1), ref.reshape(-1), rank)
    return out


def confirmed_regions(labels, support, min_fraction: float):
    """Regions (labels from :func:`~cm3d.motion.keypoint_cue.candidate_regions`, -1 outside) whose
    share of ``support`` pixels is at least ``min_fraction``; returns the relabelled (H, W) int
    (-1 where a region was dropped)."""
    H, W = labels.shape
    n = H * W
    idx = jnp.where(labels >= 0, labels, n).reshape(-1)
    area = jnp.zeros(n + 1, jnp.int32).at[idx].add(1)[:n]
    hits = jnp.zeros(n + 1, jnp.int32).at[idx].add(support.reshape(-1).astype(jnp.int32))[:n]
    ok = hits >= min_fraction * jnp.maximum(area, 1)
    return jnp.where((labels >= 0) & ok[jnp.maximum(labels, 0)], labels, -1)
