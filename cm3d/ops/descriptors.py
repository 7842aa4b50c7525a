"""Handcrafted global descriptors and their hash codes (pure JAX, masks instead of variable sizes).

- :func:`image_descriptor`: colour, gradient-orientation and 2x2-grid lightness/chroma histograms
  of the static pixels, Hellinger- and L2-normalised.
- :func:`cloud_descriptor`: invariant to rotation, translation and scale: histograms of normalised
  centroid and pair distances, the PCA spectrum, angles to the principal axis.
- :func:`hash_codes` / :func:`hamming`: random-hyperplane LSH bits packed in uint32 words.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

IMAGE_DIM = 128
CLOUD_DIM = 40


def _soft_hist(x, w, bins: int, lo: float, hi: float):
    """Linear-interpolation (soft) histogram of values x (N,) with weights w (N,)."""
    t = jnp.clip((x - lo) / (hi - lo) * bins - 0.5, 0.0, bins - 1.0)
    i0 = jnp.floor(t).astype(jnp.int32)
    f = t - i0
    i1 = jnp.minimum(i0 + 1, bins - 1)
    return jnp.zeros(bins).at[i0].add(w * (1 - f)).at[i1].add(w * f)


def _normalise(h, eps=1e-12):
    h = jnp.sqrt(jnp.maximum(h, 0.0))  # Hellinger / power normalisation
    return h / jnp.maximum(jnp.linalg.norm(h), eps)


def _downsample(img, factor: int):
    H, W = img.shape[:2]
    h, w = H // factor, W // factor
    return img[: h * factor, : w * factor].reshape(h, factor, w, factor, *img.shape[2:]).mean((1, 3))


def image_descriptor(image: jnp.ndarray, mask: jnp.ndarray | None = None, factor: int = 4) -> jnp.ndarray:
    """L2-normalised descriptor (IMAGE_DIM,) of an RGB image (H, W, 3) (uint8 or [0, 1] float),
    over the pixels where ``mask`` (H, W) is true (e.g. static, high-confidence). An empty mask
    gives the zero vector (matches nothing)."""
    img = jnp.asarray(image, jnp.float32)
    img = jnp.where(img.max() > 1.5, img / 255.0, img)
    m = jnp.ones(img.shape[:2], jnp.float32) if mask is None else jnp.asarray(mask, jnp.float32)
    img, m = _downsample(img, factor), _downsample(m, factor)
    wpix = (m > 0.5).astype(jnp.float32)
    h, w = wpix.shape
    flat = img.reshape(-1, 3)
    wf = wpix.reshape(-1)

    # joint colour histogram, 4 x 4 x 4 soft bins (separable interpolation weights)
    def axis_weights(x):
        t = jnp.clip(x * 4 - 0.5, 0.0, 3.0)
        return jnp.maximum(0.0, 1.0 - jnp.abs(t[:, None] - jnp.arange(4.0)[None]))  # (N, 4)

    wr, wg, wb = (axis_weights(flat[:, c]) for c in range(3))
    colour = jnp.einsum("n,na,nb,nc->abc", wf, wr, wg, wb).reshape(-1)

    # gradient orientation (mod pi: robust to contrast flips), magnitude-weighted, two scales
    gray = img @ jnp.array([0.299, 0.587, 0.114])

    def orient_hist(g, wmask):
        gy, gx = jnp.gradient(g)
        # only where the central differences see valid pixels on both sides
        pad = jnp.pad(wmask, 1)
        inner = pad[1:-1, 1:-1] * pad[:-2, 1:-1] * pad[2:, 1:-1] * pad[1:-1, :-2] * pad[1:-1, 2:]
        mag = jnp.hypot(gx, gy) * inner
        ang = jnp.mod(jnp.arctan2(gy, gx), jnp.pi)
        t = ang / jnp.pi * 8
        i0 = jnp.floor(t).astype(jnp.int32) % 8
        f = t - jnp.floor(t)
        return jnp.zeros(8).at[i0.ravel()].add((mag * (1 - f)).ravel()).at[((i0 + 1) % 8).ravel()].add((mag * f).ravel())

    grad = jnp.concatenate([orient_hist(gray, wpix),
                            orient_hist(_downsample(gray, 2), (_downsample(wpix, 2) > 0.5).astype(jnp.float32))])

    # 2x2 grid of lightness (6 bins) and chroma (6 bins) histograms
    light = gray.reshape(-1)
    chroma = (flat.max(-1) - flat.min(-1))
    rows = (jnp.arange(h)[:, None] * 2 // h) * 2 + (jnp.arange(w)[None, :] * 2 // w)
    cell = rows.reshape(-1)
    grid = []
    for c in range(4):
        wc = wf * (cell == c)
        grid += [_normalise(_soft_hist(light, wc, 6, 0.0, 1.0)), _normalise(_soft_hist(chroma, wc, 6, 0.0, 0.8))]
    d = jnp.concatenate([_normalise(colour), _normalise(grad), 0.5 * jnp.concatenate(grid)])
    return d / jnp.maximum(jnp.linalg.norm(d), 1e-12)


def cloud_descriptor(points: jnp.ndarray, valid: jnp.ndarray | None = None) -> jnp.ndarray:
    """Similarity-invariant descriptor (CLOUD_DIM,) of a point cloud (N, 3) with mask (N,)."""
    p = jnp.asarray(points, jnp.float32)
    w = jnp.ones(p.shape[0]) if valid is None else jnp.asarray(valid, jnp.float32)
    n = jnp.maximum(w.sum(), 1.0)
    c = (w[:, None] * p).sum(0) / n
    q = p - c
    r = jnp.sqrt(jnp.maximum((w * jnp.sum(q * q, -1)).sum() / n, 1e-12))
    qn = q / r
    dist = jnp.linalg.norm(qn, axis=-1)
    h_center = _soft_hist(dist, w, 16, 0.0, 3.0)
    # pairs: each valid point with the valid point half a cycle later in a fixed shuffle
    perm = jax.random.permutation(jax.random.PRNGKey(0), p.shape[0])
    order = perm[jnp.argsort(-w[perm], stable=True)]  # valid points first, shuffled
    nv = jnp.maximum(w.sum().astype(jnp.int32), 1)
    idx = jnp.arange(p.shape[0])
    partner = order[(idx + nv // 2) % nv]
    pw = w[order] * (idx < nv)
    pair_d = jnp.linalg.norm(qn[order] - qn[partner], axis=-1)
    h_pair = _soft_hist(pair_d, pw, 16, 0.0, 4.0)
    cov = (w[:, None, None] * qn[:, :, None] * qn[:, None, :]).sum(0) / n
    evals, evecs = jnp.linalg.eigh(cov)
    spectrum = evals[::-1] / jnp.maximum(evals.sum(), 1e-12)
    cosang = jnp.abs(qn @ evecs[:, -1]) / jnp.maximum(dist, 1e-6)
    h_angle = _soft_hist(cosang, w, 5, 0.0, 1.0)
    d = jnp.concatenate([_normalise(h_center), _normalise(h_pair), spectrum, _normalise(h_angle)])
    ok = w.sum() >= 3
    return jnp.where(ok, d / jnp.maximum(jnp.linalg.norm(d), 1e-12), 0.0)


def hash_planes(dim: int, bits: int = 32, seed: int = 0) -> jnp.ndarray:
    """Random hyperplanes (bits, dim) for :func:`hash_codes`; fixed by ``seed``."""
    return jax.random.normal(jax.random.PRNGKey(seed), (bits, dim))


def hash_codes(x: jnp.ndarray, planes: jnp.ndarray) -> jnp.ndarray:
    """LSH codes (..., bits // 32) uint32 of descriptors (..., dim): sign bits of ``planes @ x``."""
    bits = (jnp.einsum("kd,...d->...k", planes, x) > 0).astype(jnp.uint32)
    words = bits.reshape(bits.shape[:-1] + (-1, 32))
    return jnp.sum(words << jnp.arange(32, dtype=jnp.uint32), axis=-1, dtype=jnp.uint32)


def hamming(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """Hamming distance between packed codes (..., W) and (..., W) (broadcasting)."""
    return jnp.sum(jax.lax.population_count(a ^ b), axis=-1).astype(jnp.int32)
