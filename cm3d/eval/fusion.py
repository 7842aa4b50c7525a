"""Multi-view depth fusion: every frame's depth re-estimated from its neighbours' depths and poses.

For the video-depth evaluation (Table 1). For a reference frame ``t`` and each neighbour ``k``:
1. lift every reference pixel ``p`` with the current estimate ``d_t`` and project it into ``k``;
2. sample ``k``'s depth there (bilinear in inverse depth; refused across a depth edge, ``edge_tol``);
3. lift that sample in ``k`` and bring it back into ``t``: depth ``z'`` at pixel ``p'``;
4. accept it when ``|z' - d_t| <= rel_tol d_t`` (occlusion test) and ``|p' - p| <= px_tol``.
The fused depth is the confidence-weighted mean of the own depth and the accepted ``z'``; pixels no
neighbour agrees with keep their own depth. ``iterations`` > 1 repeats with the fused ``d_t``.
Poses cam_to_world, pixels as :mod:`cm3d.ops.camera`. Neighbours are a fixed-size row of frame
indices padded with ``-1`` (:func:`neighbour_frames`); frames run in ``lax.map`` batches.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
from flax import struct


@dataclasses.dataclass(frozen=True)
class FusionConfig:
    """Options of :func:`fuse_depths` (static: hashable, part of the compiled program).

    rel_tol: relative depth agreement of a neighbour's sample with the reference's estimate;
    px_tol: round-trip reprojection distance (pixels); edge_tol: largest relative spread of the four
    bilinear corners (a depth edge between them refuses the sample); iterations: fusion passes (the
    later ones project and gate with the previous pass's fused depth); near: smallest camera ``z``.
    """

    rel_tol: float = 0.05
    px_tol: float = 1.0
    edge_tol: float = 0.1
    iterations: int = 2
    near: float = 1e-6

    def __post_init__(self):
        if not self.iterations >= 1:
            raise ValueError(f"FusionConfig.iterations: must be >= 1, got {self.iterations}")
        for name in ("rel_tol", "px_tol", "edge_tol"):
            if not getattr(self, name) > 0:
                raise ValueError(f"FusionConfig.{name}: must be > 0, got {getattr(self, name)}")


@struct.dataclass
class FusedDepth:
    """depth (S, H, W): fused depth (the input depth where nothing was fused); support (S, H, W)
    int32: how many neighbours agreed with the pixel (0: the pixel kept its own depth)."""

    depth: jax.Array
    support: jax.Array


def _apply(M, x, y, z):
    """``M (3, 3) @ (x, y, z)`` for component images (elementwise, so XLA fuses it into one loop;
    a matmul with a length-3 inner axis is slow on CPU)."""
    return tuple(M[i, 0] * x + M[i, 1] * y + M[i, 2] * z for i in range(3))


def _rays(K, u, v):
    """Ray components ``K^-1 (u, v, 1)`` of pixels (u, v)."""
    return _apply(jnp.linalg.inv(K), u, v, jnp.ones_like(u))


def _project(K, x, y, z, near):
    """Pixel (u, v) of camera points (x, y, z) and ``front`` where z > near."""
    front = z > near
    zs = jnp.where(front, z, 1.0)
    qx, qy, _ = _apply(K, x, y, z)
    return qx / zs, qy / zs, front


def _sample(src_depth, src_weight, us, vs, edge_tol):
    """Bilinear sample of a source depth (H, W; 0 = unusable) at (us, vs) (H, W) in inverse depth,
    its weight (None: no weights) and ok: all four corners inside, usable and within ``edge_tol``
    of each other. Gathers from the flattened image (one index per corner)."""
    H, W = src_depth.shape
    x0 = jnp.floor(us)
    y0 = jnp.floor(vs)
    fx, fy = us - x0, vs - y0
    inside = (x0 >= 0) & (x0 <= W - 2) & (y0 >= 0) & (y0 <= H - 2) & jnp.isfinite(us) & jnp.isfinite(vs)
    base = (jnp.where(inside, y0, 0) * W + jnp.where(inside, x0, 0)).astype(jnp.int32)
    idx = [base, base + 1, base + W, base + W + 1]
    wts = [(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy]
    flat = src_depth.reshape(-1)
    d = [flat[i] for i in idx]
    dmin = functools.reduce(jnp.minimum, d)
    dmax = functools.reduce(jnp.maximum, d)
    ok = inside & (dmin > 0) & (dmax <= (1.0 + edge_tol) * dmin)
    inv = sum(w / jnp.where(ok, dk, 1.0) for w, dk in zip(wts, d))
    if src_weight is None:
        wt = ok.astype(src_depth.dtype)
    else:
        wflat = src_weight.reshape(-1)
        wt = sum(w * wflat[i] for w, i in zip(wts, idx))
    return jnp.where(ok, 1.0 / inv, 0.0), wt, ok


def reproject_neighbour(ref_est, ref_pose, ref_K, src_depth, src_valid, src_weight, src_pose, src_K,
                        cfg: FusionConfig):
    """One neighbour's depth seen from the reference camera (steps 1-4 of the module doc).

    ref_est (H, W): the reference's depth estimate (0 = none); poses cam_to_world (4, 4); K (3, 3);
    src_depth (H, W), src_valid (H, W) bool, src_weight (H, W) or None (weight 1). Returns (z' (H, W)
    depth in the reference camera, weight (H, W), accepted (H, W) bool)."""
    H, W = ref_est.shape
    v, u = jnp.meshgrid(jnp.arange(H, dtype=ref_K.dtype), jnp.arange(W, dtype=ref_K.dtype), indexing="ij")
    rel = jnp.linalg.inv(src_pose) @ ref_pose  # reference camera -> source camera
    R, t = rel[:3, :3], rel[:3, 3]
    rx, ry, rz = _rays(ref_K, u, v)
    xs, ys, zs = _apply(R, rx * ref_est, ry * ref_est, rz * ref_est)
    us, vs, front = _project(src_K, xs + t[0], ys + t[1], zs + t[2], cfg.near)
    usable = jnp.where(src_valid & (src_depth > 0), src_depth, 0.0)
    ds, wt, ok = _sample(usable, src_weight, us, vs, cfg.edge_tol)
    sx, sy, sz = _rays(src_K, us, vs)
    # source camera -> reference camera: R^T (y - t)
    yx, yy, z2 = _apply(R.T, sx * ds - t[0], sy * ds - t[1], sz * ds - t[2])
    u2, v2, front2 = _project(ref_K, yx, yy, z2, cfg.near)
    ok &= front & front2 & (ref_est > 0)
    ok &= jnp.abs(z2 - ref_est) <= cfg.rel_tol * ref_est
    ok &= (u2 - u) ** 2 + (v2 - v) ** 2 <= cfg.px_tol**2
    return jnp.where(ok, z2, 0.0), jnp.where(ok, wt, 0.0), ok


def fuse_frame(depth, valid, weight, pose, K, nb_depth, nb_valid, nb_weight, nb_pose, nb_K, nb_ok,
               cfg: FusionConfig = FusionConfig()):
    """Fused depth of one frame from M neighbours (vmappable); returns (fused (H, W), support (H, W) int32).

    depth, valid, weight (H, W): measured depth, usable pixels, confidence (None: 1); pose (4, 4)
    cam_to_world; K (3, 3); nb_*: the same for the neighbours (M, ...); nb_ok (M,) bool: padding False.
    """
    own = valid & (depth > 0)
    d0 = jnp.where(own, depth, 0.0)
    weight = jnp.ones_like(depth) if weight is None else weight
    nb_valid = nb_valid & nb_ok[:, None, None]

    def one_pass(_, carry):
        est, _ = carry

        def add(m, sums):  # one neighbour at a time: the sums stay (H, W), cache-sized
            num, den, cnt = sums
            w_m = None if nb_weight is None else nb_weight[m]
            z, w, ok = reproject_neighbour(est, pose, K, nb_depth[m], nb_valid[m], w_m, nb_pose[m], nb_K[m], cfg)
            return num + w * z, den + w, cnt + ok.astype(jnp.int32)

        num, den, support = jax.lax.fori_loop(0, nb_depth.shape[0], add,
                                              (weight * d0, weight, jnp.zeros(depth.shape, jnp.int32)))
        fused = num / jnp.where(den > 0, den, 1.0)
        keep = own & (support > 0)
        return jnp.where(keep, fused, d0), jnp.where(own, support, 0)

    est, support = jax.lax.fori_loop(0, cfg.iterations, one_pass, (d0, jnp.zeros(depth.shape, jnp.int32)))
    return jnp.where(own, est, depth), support


def _check(depth, valid, cam_to_world, K, neighbours, weights):
    if depth.ndim != 3:
        raise ValueError(f"fuse_depths: depth must be (S, H, W), got {depth.shape}")
    S = depth.shape[0]
    if valid.shape != depth.shape:
        raise ValueError(f"fuse_depths: valid must be {depth.shape}, got {valid.shape}")
    if weights is not None and weights.shape != depth.shape:
        raise ValueError(f"fuse_depths: weights must be {depth.shape}, got {weights.shape}")
    if cam_to_world.shape != (S, 4, 4):
        raise ValueError(f"fuse_depths: cam_to_world must be ({S}, 4, 4), got {cam_to_world.shape}")
    if K.shape not in ((3, 3), (S, 3, 3)):
        raise ValueError(f"fuse_depths: intrinsic must be (3, 3) or ({S}, 3, 3), got {K.shape}")
    if neighbours.ndim != 2 or neighbours.shape[0] != S:
        raise ValueError(f"fuse_depths: neighbours must be ({S}, M) frame indices, got {neighbours.shape}")


@functools.partial(jax.jit, static_argnames=("cfg", "batch_size"))
def fuse_depths(depth, valid, cam_to_world, K, neighbours, weights=None, *, cfg: FusionConfig = FusionConfig(),
                batch_size: int = 1) -> FusedDepth:
    """Multi-view fused depth of every frame of a video (see the module doc).

    depth (S, H, W) camera z (<= 0: none); valid (S, H, W) bool: pixels that may be fused and lent
    to neighbours (e.g. static and confident); cam_to_world (S, 4, 4); K (3, 3) or (S, 3, 3);
    neighbours (S, M) int: each frame's neighbour frame indices, -1 = padding; weights (S, H, W)
    optional confidences (default 1); cfg: :class:`FusionConfig` (static); batch_size: frames per
    ``vmap`` batch inside the ``lax.map`` over frames (static; memory grows with it).
    Pixels that are not valid keep their input depth with support 0."""
    depth = jnp.asarray(depth)
    valid = jnp.asarray(valid, bool)
    cam_to_world = jnp.asarray(cam_to_world, depth.dtype)
    K = jnp.asarray(K, depth.dtype)
    neighbours = jnp.asarray(neighbours, jnp.int32)
    _check(depth, valid, cam_to_world, K, neighbours, weights)
    weights = None if weights is None else jnp.asarray(weights, depth.dtype)
    S = depth.shape[0]
    K = jnp.broadcast_to(K, (S, 3, 3))
    nb_ok = (neighbours >= 0) & (neighbours < S)
    nb = jnp.where(nb_ok, neighbours, 0)

    def frame(t):
        i = nb[t]
        w_t, w_i = (None, None) if weights is None else (weights[t], weights[i])
        return fuse_frame(depth[t], valid[t], w_t, cam_to_world[t], K[t], depth[i], valid[i], w_i,
                          cam_to_world[i], K[i], nb_ok[t], cfg)

    fused, support = jax.lax.map(frame, jnp.arange(S), batch_size=batch_size)
    return FusedDepth(depth=fused, support=support)


def neighbour_frames(num_frames: int, offsets=(-4, -3, -2, -1, 1, 2, 3, 4)):
    """Host helper: (S, M) int32 neighbour frame indices ``t + o`` for the ``offsets`` (M of them);
    an offset that leaves the video is reflected (``t - o``), and a frame that would repeat or
    still lie outside is padding (-1)."""
    import numpy as np

    offsets = [int(o) for o in offsets]
    if not offsets or 0 in offsets:
        raise ValueError(f"neighbour_frames: offsets must be non-empty and non-zero, got {offsets}")
    if num_frames < 1:
        raise ValueError(f"neighbour_frames: num_frames must be >= 1, got {num_frames}")
    out = np.full((num_frames, len(offsets)), -1, np.int32)
    for t in range(num_frames):
        seen = {t}
        for j, o in enumerate(offsets):
            for c in (t + o, t - o):
                if 0 <= c < num_frames and c not in seen:
                    out[t, j] = c
                    seen.add(c)
                    break
    return out
