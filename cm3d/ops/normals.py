"""Local-PCA normals: the eigenvector of a neighbourhood covariance's smallest eigenvalue (Open3D's
``estimate_normals``), from neighbour coordinates as rows or per coordinate."""

from __future__ import annotations

import jax.numpy as jnp


def _smallest_eigvec(cov: jnp.ndarray) -> jnp.ndarray:
    """Unit eigenvector of the smallest eigenvalue of symmetric PSD (..., 3, 3), closed form.

    Eigenvalues by the trigonometric formula (Smith 1961) on the scaled matrix, the vector as the
    longest cross product of two rows of ``A - lambda I`` (what Open3D's ``FastEigen3x3`` does).
    Zero where ``cov`` is zero.
    """
    scale = jnp.max(jnp.abs(cov), axis=(-2, -1))
    ok = scale > 0
    a = cov / jnp.where(ok, scale, 1.0)[..., None, None]
    a00, a11, a22 = a[..., 0, 0], a[..., 1, 1], a[..., 2, 2]
    a01, a02, a12 = a[..., 0, 1], a[..., 0, 2], a[..., 1, 2]
    q = (a00 + a11 + a22) / 3.0
    p1 = a01**2 + a02**2 + a12**2
    p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
    p = jnp.sqrt(jnp.maximum(p2, 0.0) / 6.0)
    ps = jnp.where(p > 0, p, 1.0)
    b = (a - q[..., None, None] * jnp.eye(3, dtype=a.dtype)) / ps[..., None, None]
    r = jnp.clip(jnp.linalg.det(b) / 2.0, -1.0, 1.0)
    phi = jnp.arccos(r) / 3.0
    lam = q + 2.0 * p * jnp.cos(phi + 2.0 * jnp.pi / 3.0)  # smallest eigenvalue
    m = a - lam[..., None, None] * jnp.eye(3, dtype=a.dtype)
    r0, r1, r2 = m[..., 0, :], m[..., 1, :], m[..., 2, :]
    c = jnp.stack([jnp.cross(r0, r1), jnp.cross(r0, r2), jnp.cross(r1, r2)], axis=-2)
    nc = jnp.sum(c * c, axis=-1)
    best = jnp.argmax(nc, axis=-1)
    v = jnp.take_along_axis(c, best[..., None, None], axis=-2)[..., 0, :]
    nv = jnp.sqrt(jnp.take_along_axis(nc, best[..., None], axis=-1)[..., 0])
    good = ok & (nv > 1e-12) & (p > 0)
    return jnp.where(good[..., None], v / jnp.where(good, nv, 1.0)[..., None], 0.0)


def pca_normals(nbp: jnp.ndarray, mask: jnp.ndarray) -> jnp.ndarray:
    """Local-PCA normals (n, 3) of neighbourhoods nbp (n, k, 3) with mask (n, k): the eigenvector
    of the smallest eigenvalue of the (biased) covariance, as Open3D's ``estimate_normals``; unit
    length up to sign, zero where fewer than 3 points are masked in."""
    w = mask.astype(nbp.dtype)
    cnt = jnp.sum(w, axis=1)
    wsum = jnp.maximum(cnt, 1.0)
    mu = jnp.sum(nbp * w[..., None], axis=1) / wsum[:, None]
    xc = (nbp - mu[:, None]) * w[..., None]
    cov = jnp.einsum("nki,nkj->nij", xc, nbp - mu[:, None]) / wsum[:, None, None]
    return jnp.where((cnt >= 3)[:, None], _smallest_eigvec(cov), 0.0)


def _pca_normals_soa(x, y, z, mask):
    """:func:`pca_normals` of neighbourhoods given per coordinate, x, y, z (n, k), mask (n, k): six
    row sums instead of a batched (3, k) x (k, 3) product (much faster on XLA CPU)."""
    w = mask.astype(x.dtype)
    cnt = jnp.sum(w, axis=1)
    ws = jnp.maximum(cnt, 1.0)
    mx, my, mz = (jnp.sum(v * w, axis=1) / ws for v in (x, y, z))
    cx, cy, cz = (x - mx[:, None]) * w, (y - my[:, None]) * w, (z - mz[:, None]) * w
    sxx, syy, szz = jnp.sum(cx * cx, 1), jnp.sum(cy * cy, 1), jnp.sum(cz * cz, 1)
    sxy, sxz, syz = jnp.sum(cx * cy, 1), jnp.sum(cx * cz, 1), jnp.sum(cy * cz, 1)
    cov = jnp.stack([jnp.stack([sxx, sxy, sxz], -1), jnp.stack([sxy, syy, syz], -1),
                     jnp.stack([sxz, syz, szz], -1)], -2) / ws[:, None, None]
    return jnp.where((cnt >= 3)[:, None], _smallest_eigvec(cov), 0.0)
