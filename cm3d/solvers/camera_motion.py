"""Robust fit of rigid camera motions to pixel observations: IRLS Gauss–Newton on SE(3).

Minimises ``Σ_k w_k ρ(|π(K T_g X_k) − z_k| / σ)`` over group transforms ``T_g`` (G, 4, 4) of camera
points ``X_k`` (K, 3), steps ``T ← exp(δ) T`` (left perturbation, translation first), Geman–McClure
weights at a caller-given robust scale. Fixed shapes and step count; a non-finite step is not
taken. Used by the motion cues (flow-aligned relative pose, track cue).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from cm3d.ops import se3
from cm3d.ops.camera import MIN_DEPTH

def pinhole_left_jacobian(Y, z, fx, sk, fy):
    """(N, 2, 6) derivative of the pinhole pixels of camera points Y (N, 3) (safe depths z (N,))
    under a left perturbation ``T <- exp(delta) T`` (jaxlie order: translation first)."""
    x, y = Y[:, 0], Y[:, 1]
    zero = jnp.zeros_like(x)
    du = jnp.stack([fx / z, sk / z, -(fx * x + sk * y) / z**2], -1)
    dv = jnp.stack([zero, fy / z, -fy * y / z**2], -1)

    def rows(dp):
        rot = jnp.cross(Y, dp)  # dp . (-[Y]x w) = (Y x dp) . w
        return jnp.concatenate([dp, rot], -1)

    return jnp.stack([rows(du), rows(dv)], 1)


def reprojection(T, X, target, K, weight, group):
    """Residuals (K, 2) px of points X (K, 3) moved by ``T[group]`` and projected by K ((3, 3) or
    (K, 3, 3)) against target pixels (K, 2); camera points (K, 3), safe depths (K,), and which
    observations count (K,): positive weight, in front of the camera, finite."""
    C = T[group]
    Y = jnp.einsum("kij,kj->ki", C[:, :3, :3], X) + C[:, :3, 3]
    fx, sk, cx, fy, cy = K[..., 0, 0], K[..., 0, 1], K[..., 0, 2], K[..., 1, 1], K[..., 1, 2]
    z = Y[:, 2]
    zs = jnp.where(z > MIN_DEPTH, z, 1.0)
    r = jnp.stack([(fx * Y[:, 0] + sk * Y[:, 1]) / zs + cx, fy * Y[:, 1] / zs + cy], -1) - target
    ok = (weight > 0) & (z > MIN_DEPTH) & jnp.all(jnp.isfinite(r), -1)
    return r, Y, zs, ok


def fit_camera_motion(X, target, K, weight, init, scale_fn: Callable, iterations: int,
                      group=None, fit=None):
    """``iterations`` IRLS Gauss–Newton steps from ``init`` (G, 4, 4) -> transforms (G, 4, 4).

    X (K, 3) camera points, target (K, 2) px, K intrinsics ((3, 3) or (K, 3, 3)), weight (K,) >= 0,
    group (K,) int in [0, G) (default: all in group 0); ``scale_fn(|r| (K,), ok (K,))`` -> the robust
    scale (scalar or (K,)) in px; fit (G,) bool: groups that may move (default all).
    """
    G = init.shape[0]
    group = jnp.zeros(X.shape[0], jnp.int32) if group is None else group
    fx, sk, fy = K[..., 0, 0], K[..., 0, 1], K[..., 1, 1]
    eye6 = jnp.eye(6, dtype=X.dtype)

    def step(T, _):
        r, Y, z, ok = reprojection(T, X, target, K, weight, group)
        rn = jnp.linalg.norm(r, axis=-1)
        q = 1.0 / (1.0 + (rn / scale_fn(rn, ok)) ** 2)
        w = jnp.where(ok, weight * q * q, 0.0)
        J = pinhole_left_jacobian(Y, z, fx, sk, fy)
        Hm = jax.ops.segment_sum(w[:, None, None] * jnp.einsum("kri,krj->kij", J, J), group, G)
        g = jax.ops.segment_sum(w[:, None] * jnp.einsum("kri,kr->ki", J, r), group, G)
        damp = 1e-6 * jnp.trace(Hm, axis1=-2, axis2=-1) / 6.0 + 1e-9
        delta = -jnp.linalg.solve(Hm + damp[:, None, None] * eye6, g[..., None])[..., 0]
        keep = jnp.all(jnp.isfinite(delta), -1, keepdims=True)
        if fit is not None:
            keep &= fit[:, None]
        return se3.exp(jnp.where(keep, delta, 0.0)) @ T, None

    T, _ = jax.lax.scan(step, init, None, length=iterations)
    return T
