"""SE(3)/SO(3) on 4x4 matrices, backed by jaxlie.

A pose is ``cam_to_world`` ``T``: ``x_w = R @ x_c + t``; camera axes OpenCV's (x right, y down, z
forward). VGGT's ``extrinsic`` (world-to-camera, 3x4) is converted at the file boundary only
(:func:`extrinsic_to_cam_to_world`). Tangents follow jaxlie, translation first, ``T @ exp(xi)``.
All functions broadcast over leading axes.
"""

from __future__ import annotations

import jax.numpy as jnp
import jaxlie


def make_pose(R: jnp.ndarray, t: jnp.ndarray) -> jnp.ndarray:
    """Stack rotation (..., 3, 3) and translation (..., 3) into a 4x4 pose (..., 4, 4)."""
    R = jnp.asarray(R)
    t = jnp.asarray(t, dtype=R.dtype)
    top = jnp.concatenate([R, t[..., :, None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0], R.dtype), top.shape[:-2] + (1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


def inverse(T: jnp.ndarray) -> jnp.ndarray:
    """Inverse of a rigid transform (..., 4, 4), in closed form ``[R^T, -R^T t]``."""
    R, t = T[..., :3, :3], T[..., :3, 3]
    Rt = jnp.swapaxes(R, -1, -2)
    return make_pose(Rt, -jnp.einsum("...ij,...j->...i", Rt, t))


def compose(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """``a @ b`` for poses (..., 4, 4): apply ``b`` first, then ``a``."""
    return a @ b


def transform_points(T: jnp.ndarray, p: jnp.ndarray) -> jnp.ndarray:
    """Apply pose (..., 4, 4) to points (..., N, 3)."""
    return jnp.einsum("...ij,...nj->...ni", T[..., :3, :3], p) + T[..., None, :3, 3]


def exp(xi: jnp.ndarray) -> jnp.ndarray:
    """Exponential map, tangent (..., 6) (translation first) -> pose (..., 4, 4).
    Rotation by jaxlie's ``SO3.exp``; ``V(ω) v`` here with a Taylor series below θ = 0.1, where the
    closed form (and jaxlie's ``SE3.exp``) cancels catastrophically in float32."""
    v, w = xi[..., :3], xi[..., 3:]
    th2 = jnp.sum(w * w, -1, keepdims=True)
    small = th2 < 1e-2
    th = jnp.sqrt(jnp.where(small, 1.0, th2))
    b = jnp.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - jnp.cos(th)) / (th * th))
    c = jnp.where(small, 1.0 / 6.0 - th2 / 120.0 + th2 * th2 / 5040.0, (th - jnp.sin(th)) / (th * th * th))
    wv = jnp.cross(w, v)
    t = v + b * wv + c * jnp.cross(w, wv)
    return make_pose(jaxlie.SO3.exp(w).as_matrix(), t)


def log(T: jnp.ndarray) -> jnp.ndarray:
    """Logarithm, pose (..., 4, 4) -> tangent (..., 6) (translation first).
    Rotation by jaxlie's ``SO3.log``; ``V(ω)^{-1} t`` here with a Taylor series below θ = 0.1, where the
    closed form (and jaxlie's ``SE3.log``) cancels catastrophically in float32."""
    w = jaxlie.SO3.from_matrix(T[..., :3, :3]).log()
    t = T[..., :3, 3]
    th2 = jnp.sum(w * w, -1, keepdims=True)
    small = th2 < 1e-2
    th = jnp.sqrt(jnp.where(small, 1.0, th2))
    closed = (1.0 - th * jnp.sin(th) / (2.0 * (1.0 - jnp.cos(th)))) / (th * th)
    c = jnp.where(small, 1.0 / 12.0 + th2 / 720.0 + th2 * th2 / 30240.0, closed)
    wt = jnp.cross(w, t)
    return jnp.concatenate([t - 0.5 * wt + c * jnp.cross(w, wt), w], -1)


def ominus(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """``a ⊖ b = log(b^{-1} a)`` (..., 6): the tangent at ``b`` that reaches ``a``."""
    return log(inverse(b) @ a)


def orthonormalize(R: jnp.ndarray) -> jnp.ndarray:
    """Nearest rotation (Frobenius) to a 3x3 matrix by SVD: ``U diag(1, 1, det(U V^T)) V^T``."""
    U, _, Vt = jnp.linalg.svd(R)
    d = jnp.sign(jnp.linalg.det(U @ Vt))
    d = jnp.where(d == 0, 1.0, d)
    U = U.at[..., :, 2].multiply(d[..., None])
    return U @ Vt


def orthonormalize_pose(T: jnp.ndarray) -> jnp.ndarray:
    """Pose (..., 4, 4) whose rotation block is re-orthonormalised by SVD."""
    return make_pose(orthonormalize(T[..., :3, :3]), T[..., :3, 3])


def rotation_angle(R: jnp.ndarray) -> jnp.ndarray:
    """Rotation angle in radians of (..., 3, 3), via atan2 (accurate near 0 and pi)."""
    tr = jnp.trace(R, axis1=-2, axis2=-1)
    skew = jnp.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1
    )
    return jnp.arctan2(0.5 * jnp.linalg.norm(skew, axis=-1), 0.5 * (tr - 1.0))


def extrinsic_to_cam_to_world(E: jnp.ndarray) -> jnp.ndarray:
    """VGGT/OpenCV world-to-camera extrinsic (..., 3, 4) or (..., 4, 4) -> cam_to_world (..., 4, 4)."""
    return inverse(make_pose(E[..., :3, :3], E[..., :3, 3]))


def cam_to_world_to_extrinsic(T: jnp.ndarray) -> jnp.ndarray:
    """cam_to_world (..., 4, 4) -> world-to-camera extrinsic (..., 3, 4), VGGT's layout."""
    return inverse(T)[..., :3, :]
