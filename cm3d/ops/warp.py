"""Photometric agreement of trajectories (pure JAX, fixed shapes): the in-graph twin of
:func:`cm3d.pipeline.photometric.warp_errors`.

For frame pairs ``(t, t + g)``, ``g`` in ``gaps``, every ``step``-th pixel of frame t that is static
with positive depth and confidence is lifted with its depth, moved by each trajectory's relative pose
and projected into frame ``t + g``; it counts when it lands inside the image on a static pixel under
*every* trajectory (a paired comparison). A trajectory's error is the mean over pairs (with at least
one such pixel) of the mean absolute grey difference (bilinear), truncated at ``truncate`` levels.
Evidence the factor graph never saw: the graph fits flow tracks, this compares grey values."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def sample_step(height: int, width: int, max_pixels: int) -> int:
    """The grid step that samples about ``max_pixels`` pixels of a ``height x width`` frame."""
    return max(1, int((height * width / max_pixels) ** 0.5))


def _bilinear(img, u, v):
    H, W = img.shape
    u0 = jnp.clip(jnp.floor(u), 0, W - 2).astype(jnp.int32)
    v0 = jnp.clip(jnp.floor(v), 0, H - 2).astype(jnp.int32)
    fu, fv = u - u0, v - v0
    top = img[v0, u0] * (1 - fu) + img[v0, u0 + 1] * fu
    bottom = img[v0 + 1, u0] * (1 - fu) + img[v0 + 1, u0 + 1] * fu
    return top * (1 - fv) + bottom * fv


def pair_warp_errors(images, depth, conf, static, K, trajectories, valid, gaps=(1, 2, 4), step: int = 1,
                     truncate: float = 40.0):
    """Errors of trajectories on the same frames, per frame pair.

    images (S, H, W[, C]) grey levels 0-255 (channels averaged); depth, conf (S, H, W); static (S, H, W)
    bool; K (S, 3, 3); trajectories (T, S, 4, 4) cam_to_world; valid (S,) frames that count; ``gaps``,
    ``step`` static. Returns (errors (P, T), paired pixels (P,)) for the pairs ``(t, t + g)``, ``g`` in
    ``gaps`` (P = S x len(gaps), gap-major): each pair's mean absolute grey difference over the pixels
    paired under every trajectory (0 where none)."""
    grey = images.astype(jnp.float32)
    if grey.ndim == 4:
        grey = grey.mean(-1)
    S, H, W = grey.shape
    dt = trajectories.dtype
    v, u = jnp.meshgrid(jnp.arange(0, H, step), jnp.arange(0, W, step), indexing="ij")
    iu, iv = u.ravel(), v.ravel()
    uv1 = jnp.stack([iu, iv, jnp.ones_like(iu)]).astype(dt)  # (3, N)

    def pair(t, g):
        j = jnp.minimum(t + g, S - 1)
        dz = depth[t, iv, iu].astype(dt)
        src = (static[t, iv, iu] & (dz > 0) & (conf[t, iv, iu] > 0) & jnp.isfinite(dz)
               & valid[t] & valid[j] & (t + g < S))
        X = jnp.linalg.solve(K[t].astype(dt), uv1) * jnp.where(src, dz, 0.0)
        Kj = K[j].astype(dt)

        def project(P):
            rel = jnp.linalg.solve(P[j], P[t])
            Y = rel[:3, :3] @ X + rel[:3, 3:]
            z = Y[2]
            zs = jnp.where(z > 1e-9, z, 1.0)
            uj = (Kj[0, 0] * Y[0] + Kj[0, 1] * Y[1]) / zs + Kj[0, 2]
            vj = Kj[1, 1] * Y[1] / zs + Kj[1, 2]
            inside = (z > 1e-9) & (uj >= 0) & (uj <= W - 1) & (vj >= 0) & (vj <= H - 1)
            uc = jnp.clip(jnp.round(uj), 0, W - 1).astype(jnp.int32)
            vc = jnp.clip(jnp.round(vj), 0, H - 1).astype(jnp.int32)
            return uj, vj, inside & static[j, vc, uc]

        uj, vj, ok = jax.vmap(project)(trajectories)  # (T, N)
        ok = src & jnp.all(ok, axis=0)
        ref = grey[t, iv, iu]
        diff = jnp.minimum(jnp.abs(jax.vmap(lambda a, b: _bilinear(grey[j], a, b))(uj, vj) - ref), truncate)
        n = jnp.sum(ok)
        return jnp.sum(jnp.where(ok, diff, 0.0), axis=1) / jnp.maximum(n, 1), n

    ts = jnp.arange(S)
    per_gap = [jax.vmap(lambda t, g=g: pair(t, g))(ts) for g in gaps]
    return jnp.concatenate([e for e, _ in per_gap]), jnp.concatenate([c for _, c in per_gap])


def paired_warp_errors(images, depth, conf, static, K, trajectories, valid, gaps=(1, 2, 4), step: int = 1,
                       truncate: float = 40.0):
    """Errors of trajectories on the same frames: :func:`pair_warp_errors` averaged over the frame pairs
    with paired pixels. Returns (errors (T,), paired pixels in all ()); errors are 0 without any pair."""
    err, n = pair_warp_errors(images, depth, conf, static, K, trajectories, valid, gaps, step, truncate)
    return mean_over_pairs(err, n), jnp.sum(n)


def mean_over_pairs(err, n):
    """Errors (P, T) of :func:`pair_warp_errors` averaged over the pairs with paired pixels (``n`` (P,) > 0):
    (T,), 0 without any."""
    has = n > 0
    return jnp.sum(jnp.where(has[:, None], err, 0.0), axis=0) / jnp.maximum(jnp.sum(has), 1)
