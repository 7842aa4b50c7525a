"""Binary-mask morphology and connected components in JAX (fixed shapes, jittable, vmappable).

Components are 4-connected; each pixel is labelled with the flat index (``v * W + u``) of its
component's first pixel (the *root*), -1 outside, so a per-region quantity is a scatter by root.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp


def _pool(x, radius: int, op, init):
    if radius <= 0:
        return x
    k = 2 * radius + 1
    return jax.lax.reduce_window(x, init, op, (k, k), (1, 1), "SAME")


def dilate(mask, radius: int = 1):
    """Binary dilation (H, W) by a (2r+1) square."""
    return _pool(jnp.asarray(mask, bool), radius, jax.lax.max, False)


def erode(mask, radius: int = 1):
    """Binary erosion (H, W) by a (2r+1) square (pixels beyond the border count as set)."""
    return _pool(jnp.asarray(mask, bool), radius, jax.lax.min, True)


def opening(mask, radius: int = 1):
    """Erosion then dilation: removes specks and lines thinner than ``2r+1``."""
    return dilate(erode(mask, radius), radius)


def closing(mask, radius: int = 1):
    """Dilation then erosion: fills holes and gaps narrower than ``2r+1``."""
    return erode(dilate(mask, radius), radius)


def _shift(x, dy: int, dx: int):
    """``x`` (H, W) moved by (dy, dx): out[i, j] = x[i - dy, j - dx], False outside."""
    H, W = x.shape
    r = max(abs(dy), abs(dx))
    p = jnp.pad(x, r)
    return p[r - dy:r - dy + H, r - dx:r - dx + W]


def line_opening(mask, radius: int):
    """(H, W) bool: the pixels of ``mask`` on a straight run of at least ``2 radius + 1`` set pixels
    (horizontal, vertical or diagonal), i.e. the union of the openings by the four line segments of
    that length (pixels beyond the border count as unset). Bands and blobs keep their pixels,
    isolated specks lose them."""
    out = jnp.zeros_like(mask)
    offs = range(-radius, radius + 1)
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        full = functools.reduce(jnp.logical_and, [_shift(mask, k * dy, k * dx) for k in offs])
        out |= functools.reduce(jnp.logical_or, [_shift(full, k * dy, k * dx) for k in offs])
    return out


def _run_ids(mask):
    """Flat (row-major) id of the horizontal run each pixel belongs to; ``mask.size`` outside."""
    prev = jnp.pad(mask, ((0, 0), (1, 0)))[:, :-1]
    rid = jnp.cumsum((mask & ~prev).reshape(-1)) - 1
    return jnp.where(mask.reshape(-1), rid, mask.size)


def label_components(mask) -> jnp.ndarray:
    """4-connected component labels (H, W) int32: root flat index per pixel, -1 outside ``mask``.
    Min-label propagation along horizontal and vertical runs plus pointer jumping, in a
    ``lax.while_loop`` until no label changes."""
    mask = jnp.asarray(mask, bool)
    H, W = mask.shape
    n = H * W
    big = jnp.int32(n)
    rid_h = _run_ids(mask)
    rid_v = _run_ids(mask.T)
    start = jnp.where(mask, jnp.arange(n, dtype=jnp.int32).reshape(H, W), big)

    def run_min(flat, rid):
        return jnp.full(n + 1, big, jnp.int32).at[rid].min(flat)[rid]

    def jump(L):
        flat = L.reshape(-1)
        return jnp.concatenate([flat, jnp.array([n], jnp.int32)])[flat].reshape(H, W)

    def body(state):
        L, _ = state
        Lh = run_min(L.reshape(-1), rid_h).reshape(H, W)
        Lv = run_min(Lh.T.reshape(-1), rid_v).reshape(W, H).T
        new = jnp.where(mask, jump(jump(Lv)), big)
        return new, jnp.any(new != L)

    L, _ = jax.lax.while_loop(lambda s: s[1], body, (start, jnp.array(True)))
    return jnp.where(mask, L, -1)


def region_sum(labels, values) -> jnp.ndarray:
    """Per-root sums (H*W,) of ``values`` (H, W) over each component (index by root label)."""
    n = labels.size
    flat = labels.reshape(-1)
    idx = jnp.where(flat >= 0, flat, n)
    return jnp.zeros(n + 1, jnp.asarray(values).dtype).at[idx].add(jnp.asarray(values).reshape(-1))[:n]


def region_area(labels) -> jnp.ndarray:
    """Area (H, W) int32 of the component each pixel belongs to (0 outside every component)."""
    area = region_sum(labels, (labels >= 0).astype(jnp.int32))
    return jnp.where(labels >= 0, area[jnp.maximum(labels, 0)], 0)
