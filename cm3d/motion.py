"""Motion cues: which pixels of frame t belong to moving objects (CogniMap3D, first stage).

``motion_cues(prior_t, prior_t2, flow, matches, cfg)`` is one pure, jittable and vmappable
function composed of named stages, each returning its own mask so experiments can score them:

1. ``flow_motion_cue``: a K-component GMM on the flow vectors; every pixel outside the component
   of smallest mean flow magnitude is moving (:mod:`cm3d.ops.gmm`).
2. ``geometry_motion_cue``: the residual ``|flow - ego_flow|`` between the observed flow and the
   flow the static scene would show, from the prior depth and the relative pose. The prior poses
   are noisy (moderate: 3 deg / 3 cm RMS, i.e. tens of pixels of ego-flow error), so the relative
   pose is first re-estimated from the flow itself (``refine_relative_pose``: robust Gauss-Newton
   on SE(3), Geman-McClure weights with a MAD scale, started at the prior). The residual is
   thresholded by Otsu (:mod:`cm3d.ops.otsu`, on log residual) over valid-depth pixels, never
   below a noise floor ``max(floor_px, k * median residual)``.
3. ``robust_motion_cue``: keypoint matches are lifted to 3D with both frames' 3x3-median depth
   (the t2 depth rescaled to t's per-frame depth scale) and the relative pose; displacements are
   divided by depth (the prior's scale is unknown and its depth noise is relative). A keypoint
   inside a candidate region is dynamic when its deviation from the median displacement, scaled
   by robust sigmas (MAD) along and across its viewing ray, is large in magnitude, or its direction
   is more than ``kp_direction_deg`` off. The mask is the candidate regions (4-connected components
   of the cleaned flow/geometry candidates) holding enough dynamic keypoints.
4. ``baseline_motion_cue``: MonST3R-style fixed threshold on the residual flow, for comparison.

Refinement by seeded segmentation and tracking run on the host: :mod:`cm3d.refine`.
Conventions: :mod:`cm3d.ops.camera` (cam_to_world poses, forward flow ``F[v, u] = (du, dv)``).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from cm3d.ops import camera, components, se3
from cm3d.ops.gmm import GMMConfig, fit_gmm, slowest_component_mask
from cm3d.ops.otsu import threshold_otsu


@struct.dataclass
class FramePrior:
    """One frame's foundation-model priors (leading axes allowed: a sequence is a FramePrior of (S, ...)).

    image (H, W, 3) uint8; depth (H, W) camera z, prior units; depth_conf (H, W), larger is better;
    intrinsic (3, 3); cam_to_world (4, 4).
    """

    image: jnp.ndarray
    depth: jnp.ndarray
    depth_conf: jnp.ndarray
    intrinsic: jnp.ndarray
    cam_to_world: jnp.ndarray

    @classmethod
    def from_sequence(cls, seq, frames=None) -> "FramePrior":
        """Priors of a :class:`cm3d.data.Sequence` (all frames, or an index / slice), as float32."""
        sl = slice(None) if frames is None else frames
        return cls(
            image=jnp.asarray(seq.images[sl]),
            depth=jnp.asarray(seq.depth[sl], jnp.float32),
            depth_conf=jnp.asarray(seq.depth_conf[sl], jnp.float32),
            intrinsic=jnp.asarray(seq.intrinsic[sl], jnp.float32),
            cam_to_world=jnp.asarray(seq.cam_to_world[sl], jnp.float32),
        )


@struct.dataclass
class MotionCues:
    """Each stage's mask (H, W) bool and the geometric residual, for one frame pair (t, t2).

    flow_mask: GMM flow cue; geo_mask: residual > geo_threshold; candidates: cleaned candidate
    regions; robust_mask: candidate regions confirmed by dynamic keypoints; baseline_mask:
    MonST3R-style fixed threshold; residual (H, W) px, 0 where invalid; valid (H, W) bool;
    geo_threshold (scalar px); rel_pose (4, 4) refined camera-t to camera-t2 transform;
    kp_dynamic, kp_valid (N,) bool per match.
    """

    flow_mask: jnp.ndarray
    geo_mask: jnp.ndarray
    candidates: jnp.ndarray
    robust_mask: jnp.ndarray
    baseline_mask: jnp.ndarray
    residual: jnp.ndarray
    valid: jnp.ndarray
    geo_threshold: jnp.ndarray
    rel_pose: jnp.ndarray
    kp_dynamic: jnp.ndarray
    kp_valid: jnp.ndarray


@dataclasses.dataclass(frozen=True)
class MotionConfig:
    """Options of the motion cues (hashable: pass as a static argument). Pixel values refer to the
    image size at hand; area fractions are of H * W."""

    gmm: GMMConfig = GMMConfig(num_components=3, max_iters=50, tol=1e-3)
    # relative pose from flow
    refine_pose: bool = True
    pose_iters: int = 12
    pose_stride: int = 4  # sample every pose_stride-th pixel (static)
    pose_min_scale_px: float = 0.5  # floor of the robust scale
    pose_scale_k: float = 1.0  # robust scale = k * 1.4826 * median residual
    pose_loss: str = "geman_mcclure"  # or "cauchy" (redescends slower: large movers bias it)
    # geometry cue
    otsu_bins: int = 256
    otsu_log: bool = True  # Otsu on log(residual): static noise and motion are modes apart by decades
    residual_floor_px: float = 1.0
    residual_noise_k: float = 4.0  # threshold >= k * median residual (the static noise level)
    min_depth_conf: float = 0.0
    border_px: float = 2.0  # a pixel whose flow or ego flow leaves the image (minus this) is not judged
    # candidate regions
    candidate_source: str = "geo"  # "geo", "union" or "intersection" of the flow and geo masks
    open_radius: int = 1
    min_region_frac: float = 3e-4
    # robust keypoint cue
    kp_sigma_k: float = 4.0  # robust score (along / across the ray) above which a keypoint is dynamic
    kp_min_rel_disp: float = 0.005  # ... and above this displacement / depth
    kp_direction_deg: float = 60.0  # or its direction is off the mean displacement by more
    kp_max_depth_ratio: float = 1.15  # a keypoint on a depth edge (3x3 max/min depth above) is not judged
    kp_min_reference: int = 8  # keypoints outside the candidates needed to take the statistics there
    kp_sigma_along: float = 0.01  # else: noise of the relative displacement along the ray (depth noise)
    kp_sigma_across: float = 0.002  # ... and across it (pixel error / focal length)
    kp_min_dynamic: int = 1  # a region needs this many dynamic keypoints ...
    kp_min_fraction: float = 0.3  # ... and this fraction of its keypoints dynamic
    keep_unverified: bool = True  # regions without any keypoint keep their geometric verdict
    # MonST3R-style baseline
    baseline_threshold_px: float = 1.0
    baseline_refined_pose: bool = True  # ego flow from the flow-aligned pose (as MonST3R's optimised poses)
    # track cue (landmark tracks over several frames, :func:`moving_tracks`)
    track_cue: bool = True
    track_iters: int = 10  # Gauss-Newton steps of each group's rigid correction
    track_min_obs: int = 30  # a (seed block, frame) group with fewer observations is not judged (5x the 6 DoF)
    track_min_scale_px: float = 0.25  # floor of the robust scale
    track_n_mad: float = 3.0  # a track moves when its RMS residual exceeds median + n_mad 1.4826 MAD ...
    track_min_px: float = 0.3  # ... and this

    def __post_init__(self):
        if self.candidate_source not in ("geo", "union", "intersection"):
            raise ValueError(f"MotionConfig.candidate_source: unknown {self.candidate_source!r}")
        if self.pose_loss not in ("geman_mcclure", "cauchy"):
            raise ValueError(f"MotionConfig.pose_loss: unknown {self.pose_loss!r} (geman_mcclure, cauchy)")
        if self.pose_stride < 1 or self.pose_iters < 0:
            raise ValueError("MotionConfig.pose_stride >= 1 and pose_iters >= 0 required")
        if self.track_iters < 0 or self.track_min_obs < 6:
            raise ValueError(f"MotionConfig.track_iters >= 0 and track_min_obs >= 6 (a rigid fit) required, "
                             f"got {self.track_iters}, {self.track_min_obs}")
        for name in ("track_min_scale_px", "track_n_mad", "track_min_px"):
            if not getattr(self, name) > 0:
                raise ValueError(f"MotionConfig.{name}: must be > 0, got {getattr(self, name)}")


# ----------------------------------------------------------------------------------------------
# helpers


def masked_median(x, valid):
    """Median (lower of the two middle values) of ``x[valid]`` for 1D x; 0 when nothing is valid."""
    x = jnp.asarray(x).reshape(-1)
    valid = jnp.asarray(valid, bool).reshape(-1)
    n = jnp.sum(valid)
    s = jnp.sort(jnp.where(valid, x, jnp.inf))
    return jnp.where(n > 0, s[jnp.clip((n - 1) // 2, 0, x.shape[0] - 1)], 0.0)


def median_filter3(depth):
    """3x3 median of a depth map (H, W), ignoring non-positive depth (0 when none is positive)."""
    H, W = depth.shape
    p = jnp.pad(depth, 1, mode="edge")
    stack = jnp.stack([p[i:i + H, j:j + W] for i in range(3) for j in range(3)])
    ok = stack > camera.MIN_DEPTH
    n = jnp.sum(ok, 0)
    s = jnp.sort(jnp.where(ok, stack, jnp.inf), axis=0)
    med = jnp.take_along_axis(s, jnp.clip((n - 1) // 2, 0, 8)[None], 0)[0]
    return jnp.where(n > 0, med, 0.0)


def _sample_median3(depth, uv):
    """3x3 median of the positive depths around the nearest pixels of (N, 2) ``(u, v)`` (0 when
    none is positive), and in-bounds flags: :func:`median_filter3` evaluated at the keypoints only."""
    H, W = depth.shape
    u = jnp.round(uv[:, 0]).astype(jnp.int32)
    v = jnp.round(uv[:, 1]).astype(jnp.int32)
    inb = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    off = jnp.arange(-1, 2)
    vv = jnp.clip(v[:, None, None] + off[None, :, None], 0, H - 1)
    uu = jnp.clip(u[:, None, None] + off[None, None, :], 0, W - 1)
    patch = depth[vv, uu].reshape(-1, 9)
    ok = patch > camera.MIN_DEPTH
    cnt = jnp.sum(ok, -1)
    srt = jnp.sort(jnp.where(ok, patch, jnp.inf), axis=-1)
    med = jnp.take_along_axis(srt, jnp.clip((cnt - 1) // 2, 0, 8)[:, None], -1)[:, 0]
    return jnp.where(cnt > 0, med, 0.0), inb


def relative_pose(prior_t: FramePrior, prior_t2: FramePrior):
    """Camera-t to camera-t2 transform ``inv(T_t2) @ T_t`` (4, 4) of the priors."""
    return se3.inverse(prior_t2.cam_to_world) @ prior_t.cam_to_world


def ego_flow_rel(depth, K0, K1, rel):
    """Static-scene flow (H, W, 2) and validity for camera-0 depth and relative pose ``rel``."""
    eye = jnp.eye(4, dtype=depth.dtype)
    return camera.ego_flow(depth, K0, eye, K1, se3.inverse(rel))


def _sample(img, uv):
    """Nearest-pixel values of img (H, W[, C]) at (N, 2) ``(u, v)``; and in-bounds flags."""
    H, W = img.shape[:2]
    u = jnp.round(uv[:, 0]).astype(jnp.int32)
    v = jnp.round(uv[:, 1]).astype(jnp.int32)
    inb = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    return img[jnp.clip(v, 0, H - 1), jnp.clip(u, 0, W - 1)], inb


def _lands_inside(flow, margin):
    """(H, W) bool: the flow sends the pixel at least ``margin`` px inside the image."""
    H, W = flow.shape[:2]
    tgt = camera.pixel_grid(H, W, flow.dtype) + flow
    u, v = tgt[..., 0], tgt[..., 1]
    return (u >= margin) & (u <= W - 1 - margin) & (v >= margin) & (v <= H - 1 - margin)


# ----------------------------------------------------------------------------------------------
# stage 1: flow


def flow_motion_cue(flow, cfg: MotionConfig = MotionConfig()):
    """GMM on flow vectors (H, W, 2) -> (moving mask (H, W), :class:`GMMResult`).

    The moving pixels are those outside the component of smallest mean flow magnitude.
    """
    H, W = flow.shape[:2]
    res = fit_gmm(flow.reshape(-1, 2), cfg.gmm)
    return slowest_component_mask(res).reshape(H, W), res


# ----------------------------------------------------------------------------------------------
# stage 2: geometry


def _pinhole_left_jacobian(Y, z, fx, sk, fy):
    """(N, 2, 6) derivative of the pinhole pixels of camera points Y (N, 3) (safe depths z (N,))
    under a left perturbation ``T <- exp(delta) T`` (jaxlie order: translation first)."""
    x, y = Y[:, 0], Y[:, 1]
    # d(u, v)/dY for the pinhole, then dY/d(v, w) = [I, -[Y]x] for T <- exp(delta) T
    zero = jnp.zeros_like(x)
    du = jnp.stack([fx / z, sk / z, -(fx * x + sk * y) / z**2], -1)
    dv = jnp.stack([zero, fy / z, -fy * y / z**2], -1)

    def rows(dp):
        rot = jnp.cross(Y, dp)  # dp . (-[Y]x w) = (Y x dp) . w
        return jnp.concatenate([dp, rot], -1)

    return jnp.stack([rows(du), rows(dv)], 1)


def refine_relative_pose(depth, K0, K1, flow, rel_init, weight, cfg: MotionConfig = MotionConfig()):
    """Camera-0 to camera-1 pose (4, 4) that best explains ``flow`` on static pixels.

    Minimises ``sum_i w_i rho(|pi(K1 T X_i) - (p_i + F(p_i))|)`` over pixels on a ``pose_stride``
    grid, ``X_i`` lifted with ``depth``/``K0``; ``rho`` is Geman-McClure (or Cauchy) with scale
    ``max(pose_min_scale_px, pose_scale_k * 1.4826 * median residual)``, moving objects being the
    outliers; ``pose_iters`` damped Gauss-Newton steps ``T <- exp(delta) T`` from ``rel_init``.
    ``weight`` (H, W) >= 0 (0 drops a pixel). Fixed shapes; without valid pixels returns ``rel_init``.
    """
    s = cfg.pose_stride
    H, W = depth.shape
    grid = camera.pixel_grid(H, W, depth.dtype)[::s, ::s].reshape(-1, 2)
    d = depth[::s, ::s].reshape(-1)
    target = grid + flow[::s, ::s].reshape(-1, 2)
    w0 = weight[::s, ::s].reshape(-1) * (d > camera.MIN_DEPTH)
    rays = jnp.concatenate([grid, jnp.ones_like(grid[:, :1])], -1) @ jnp.linalg.inv(K0).T
    X = rays * d[:, None]
    fx, sk, cx, fy, cy = K1[0, 0], K1[0, 1], K1[0, 2], K1[1, 1], K1[1, 2]

    def residuals(T):
        Y = X @ T[:3, :3].T + T[:3, 3]
        z = Y[:, 2]
        zs = jnp.where(z > camera.MIN_DEPTH, z, 1.0)
        u = (fx * Y[:, 0] + sk * Y[:, 1]) / zs + cx
        v = fy * Y[:, 1] / zs + cy
        r = jnp.stack([u, v], -1) - target
        ok = (z > camera.MIN_DEPTH) & (w0 > 0)
        return r, Y, zs, ok

    def step(T, _):
        r, Y, z, ok = residuals(T)
        rn = jnp.linalg.norm(r, axis=-1)
        scale = jnp.maximum(cfg.pose_min_scale_px, cfg.pose_scale_k * 1.4826 * masked_median(rn, ok))
        q = 1.0 / (1.0 + (rn / scale) ** 2)
        w = jnp.where(ok, w0 * (q * q if cfg.pose_loss == "geman_mcclure" else q), 0.0)
        J = _pinhole_left_jacobian(Y, z, fx, sk, fy)
        Hm = jnp.einsum("n,nij,nik->jk", w, J, J)
        g = jnp.einsum("n,nij,ni->j", w, J, r)
        damp = 1e-6 * jnp.trace(Hm) / 6.0 + 1e-9
        delta = -jnp.linalg.solve(Hm + damp * jnp.eye(6, dtype=Hm.dtype), g)
        delta = jnp.where(jnp.all(jnp.isfinite(delta)), delta, 0.0)
        return se3.exp(delta) @ T, None

    T, _ = jax.lax.scan(step, rel_init.astype(depth.dtype), None, length=cfg.pose_iters)
    return T


def geometry_motion_cue(prior_t: FramePrior, prior_t2: FramePrior, flow, cfg: MotionConfig = MotionConfig()):
    """Residual flow cue -> (mask, residual (H, W) px, valid (H, W), threshold, refined relative pose).

    ``residual = |flow - ego_flow|`` with the ego flow of the prior depth of frame t under the
    (flow-refined) relative pose; valid where depth is positive, confident enough, and in front of
    both cameras. Threshold: Otsu (on log residual when ``otsu_log``) of the valid residuals, at
    least ``max(residual_floor_px, residual_noise_k * median residual)``.
    """
    depth, K0, K1 = prior_t.depth, prior_t.intrinsic, prior_t2.intrinsic
    rel = relative_pose(prior_t, prior_t2)
    conf_ok = (prior_t.depth_conf >= cfg.min_depth_conf) & (depth > camera.MIN_DEPTH)
    if cfg.refine_pose:
        rel = refine_relative_pose(depth, K0, K1, flow, rel, conf_ok.astype(depth.dtype), cfg)
    ego, ego_ok = ego_flow_rel(depth, K0, K1, rel)
    valid = ego_ok & conf_ok & _lands_inside(ego, cfg.border_px) & _lands_inside(flow, cfg.border_px)
    residual = jnp.where(valid, jnp.linalg.norm(flow - ego, axis=-1), 0.0)
    sub = max(1, cfg.pose_stride)  # the median noise level from a grid subsample is plenty
    floor = jnp.maximum(cfg.residual_floor_px,
                        cfg.residual_noise_k * masked_median(residual[::sub, ::sub], valid[::sub, ::sub]))
    if cfg.otsu_log:
        t = jnp.exp(threshold_otsu(jnp.log(residual + 1e-3), cfg.otsu_bins, valid)) - 1e-3
    else:
        t = threshold_otsu(residual, cfg.otsu_bins, valid)
    thr = jnp.maximum(t, floor)
    return (residual > thr) & valid, residual, valid, thr, rel


# ----------------------------------------------------------------------------------------------
# stage 3: candidates and keypoints


def candidate_regions(flow_mask, geo_mask, valid, cfg: MotionConfig = MotionConfig()):
    """Cleaned candidate mask and its component labels: the chosen combination of the flow and
    geometry masks, opened by ``open_radius`` and without components under ``min_region_frac``."""
    if cfg.candidate_source == "geo":
        cand = geo_mask
    elif cfg.candidate_source == "union":
        cand = geo_mask | (flow_mask & valid)
    else:
        cand = geo_mask & flow_mask
    cand = components.opening(cand, cfg.open_radius)
    H, W = cand.shape
    labels = components.label_components(cand)
    keep = components.region_area(labels) >= max(1, int(round(cfg.min_region_frac * H * W)))
    labels = jnp.where(keep, labels, -1)
    return labels >= 0, labels


def _depth_smooth(depth, max_ratio: float):
    """(H, W) bool: the 3x3 neighbourhood's depth spans less than the ratio ``max_ratio`` (no depth edge)."""
    lo = jax.lax.reduce_window(depth, jnp.inf, jax.lax.min, (3, 3), (1, 1), "SAME")
    hi = jax.lax.reduce_window(depth, -jnp.inf, jax.lax.max, (3, 3), (1, 1), "SAME")
    return (lo > camera.MIN_DEPTH) & (hi < max_ratio * lo)


def keypoint_displacements(prior_t: FramePrior, prior_t2: FramePrior, matches, rel,
                           cfg: MotionConfig = MotionConfig()):
    """Relative 3D displacement (N, 3) of matched keypoints in camera-t axes, their unit viewing
    rays (N, 3) and validity (N,).

    Both ends are lifted with their frame's 3x3-median depth, the t2 end brought into camera t by
    ``inv(rel)``; keypoints on a depth edge (3x3 depth span above ``kp_max_depth_ratio``) at either
    end are invalid, as their depth may belong to the other surface. The depth of frame t2 is first
    rescaled by the median ratio between the depth the t-end predicts there and the observed one
    (the prior's per-frame depth scale jitter), and the displacement is divided by the keypoint's
    depth in frame t, so it is free of the prior's unknown scale.
    """
    uv0, uv1 = matches.uv0.astype(prior_t.depth.dtype), matches.uv1.astype(prior_t.depth.dtype)
    z0, in0 = _sample_median3(prior_t.depth, uv0)
    z1, in1 = _sample_median3(prior_t2.depth, uv1)
    s0, _ = _sample(_depth_smooth(prior_t.depth, cfg.kp_max_depth_ratio), uv0)
    s1, _ = _sample(_depth_smooth(prior_t2.depth, cfg.kp_max_depth_ratio), uv1)
    ok = jnp.asarray(matches.valid, bool) & in0 & in1 & s0 & s1 & (z0 > camera.MIN_DEPTH) & (z1 > camera.MIN_DEPTH)

    def lift(uv, z, K):
        ray = jnp.concatenate([uv, jnp.ones_like(uv[:, :1])], -1) @ jnp.linalg.inv(K).T
        return ray * z[:, None]

    X0 = lift(uv0, z0, prior_t.intrinsic)
    z_pred = se3.transform_points(rel, X0)[:, 2]
    ratio = z_pred / jnp.where(ok, z1, 1.0)
    scale = masked_median(ratio, ok & (ratio > 0))
    scale = jnp.where(scale > 0, scale, 1.0)
    X1 = se3.transform_points(se3.inverse(rel), lift(uv1, z1 * scale, prior_t2.intrinsic))
    disp = (X1 - X0) / jnp.where(ok, z0, 1.0)[:, None]
    ray = X0 / jnp.maximum(jnp.linalg.norm(X0, axis=-1, keepdims=True), 1e-12)
    return jnp.where(ok[:, None], disp, 0.0), ray, ok


def static_reference(labels, matches, kp_ok, cfg: MotionConfig = MotionConfig()):
    """Valid keypoints (N,) outside every candidate region: the presumed-static reference."""
    lab, inb = _sample(labels, matches.uv0.astype(jnp.float32))
    return kp_ok & inb & (lab < 0)


def dynamic_keypoints(disp, ray, ok, cfg: MotionConfig = MotionConfig(), reference=None):
    """Keypoints (N,) whose relative displacement deviates from the robust mean one.

    The robust statistics come from the ``reference`` keypoints (N,) bool (default: all valid
    ones; :func:`motion_cues` passes those outside the candidate regions, so that a mover holding
    many keypoints cannot drag the reference motion). With fewer than ``kp_min_reference``
    reference keypoints (the matches sit on the movers) the reference is the static-scene model
    itself: zero displacement (the relative pose was aligned to the flow) with the noise sigmas
    ``kp_sigma_along`` / ``kp_sigma_across``.

    The deviation from the coordinate-wise median displacement is split along the viewing ray
    (where the depth noise lies) and across it (where only the keypoint's pixel error does); each
    part is scaled by its own robust sigma (MAD; Rayleigh median across), and a keypoint is dynamic
    when the combined score exceeds ``kp_sigma_k`` and the deviation exceeds ``kp_min_rel_disp``
    (magnitude test), or when both ``|d_i|`` and the median ``|m|`` exceed ``kp_min_rel_disp`` and
    their angle exceeds ``kp_direction_deg`` (direction test).
    """
    ref = ok if reference is None else jnp.asarray(reference, bool) & ok
    enough = jnp.sum(ref) >= cfg.kp_min_reference
    m = jnp.stack([masked_median(disp[:, k], ref) for k in range(3)]) * enough
    dev = disp - m
    along = jnp.sum(dev * ray, -1)
    across = jnp.linalg.norm(dev - along[:, None] * ray, axis=-1)
    floor = cfg.kp_min_rel_disp / max(cfg.kp_sigma_k, 1e-6) / 4.0
    med_along = masked_median(along, ref) * enough
    s_along = jnp.where(enough, 1.4826 * masked_median(jnp.abs(along - med_along), ref), cfg.kp_sigma_along)
    s_across = jnp.where(enough, masked_median(across, ref) / 1.1774, cfg.kp_sigma_across)
    s_along, s_across = jnp.maximum(s_along, floor), jnp.maximum(s_across, floor)
    score = jnp.sqrt(((along - med_along) / s_along) ** 2 + (across / s_across) ** 2)
    mag = (score > cfg.kp_sigma_k) & (jnp.linalg.norm(dev, axis=-1) > cfg.kp_min_rel_disp)
    nd, nm = jnp.linalg.norm(disp, axis=-1), jnp.linalg.norm(m)
    cosang = jnp.sum(disp * m, -1) / jnp.maximum(nd * nm, 1e-12)
    big = (nd > cfg.kp_min_rel_disp) & (nm > cfg.kp_min_rel_disp)
    direction = big & (cosang < jnp.cos(jnp.deg2rad(cfg.kp_direction_deg)))
    return (mag | direction) & ok


def robust_motion_cue(labels, matches, kp_dynamic, kp_ok, cfg: MotionConfig = MotionConfig()):
    """Candidate regions (labels from :func:`candidate_regions`) confirmed by dynamic keypoints.

    A region is kept when it holds at least ``kp_min_dynamic`` dynamic keypoints that are also at
    least ``kp_min_fraction`` of its valid keypoints; a region without any valid keypoint is kept
    iff ``keep_unverified``. Returns the mask (H, W) and the per-keypoint "dynamic and inside a
    candidate" flags (N,).
    """
    H, W = labels.shape
    n = H * W
    lab, inb = _sample(labels, matches.uv0.astype(jnp.float32))
    inside = kp_ok & inb & (lab >= 0)
    idx = jnp.where(inside, lab, n)
    dyn = kp_dynamic & inside
    n_dyn = jnp.zeros(n + 1, jnp.int32).at[idx].add(dyn.astype(jnp.int32))[:n]
    n_all = jnp.zeros(n + 1, jnp.int32).at[idx].add(inside.astype(jnp.int32))[:n]
    confirmed = (n_dyn >= cfg.kp_min_dynamic) & (n_dyn >= cfg.kp_min_fraction * n_all)
    if cfg.keep_unverified:
        confirmed = confirmed | (n_all == 0)
    region = jnp.where(labels >= 0, confirmed[jnp.maximum(labels, 0)], False)
    return region, dyn


def baseline_motion_cue(prior_t: FramePrior, prior_t2: FramePrior, flow, rel, cfg: MotionConfig = MotionConfig()):
    """MonST3R-style mask: ``|flow - ego_flow| > baseline_threshold_px`` with the ego flow under ``rel``."""
    ego, ok = ego_flow_rel(prior_t.depth, prior_t.intrinsic, prior_t2.intrinsic, rel)
    return ok & (jnp.linalg.norm(flow - ego, axis=-1) > cfg.baseline_threshold_px)


# ----------------------------------------------------------------------------------------------
# composition


def motion_cues(prior_t: FramePrior, prior_t2: FramePrior, flow, matches,
                cfg: MotionConfig = MotionConfig()) -> MotionCues:
    """All motion cues of frame t from the pair (t, t2): flow (H, W, 2) forward from t to t2 and
    keypoint ``matches`` (:class:`cm3d.ops.keypoints.Matches`, padded). Pure; jit with ``cfg``
    static, vmap over frames for a sequence."""
    flow = jnp.asarray(flow, jnp.float32)
    if flow.shape != prior_t.depth.shape + (2,):
        raise ValueError(f"motion_cues: flow shape {flow.shape} does not match depth {prior_t.depth.shape}")
    flow_mask, _ = flow_motion_cue(flow, cfg)
    geo_mask, residual, valid, thr, rel = geometry_motion_cue(prior_t, prior_t2, flow, cfg)
    candidates, labels = candidate_regions(flow_mask, geo_mask, valid, cfg)
    disp, ray, kp_ok = keypoint_displacements(prior_t, prior_t2, matches, rel, cfg)
    kp_dyn = dynamic_keypoints(disp, ray, kp_ok, cfg, static_reference(labels, matches, kp_ok, cfg))
    robust, kp_dyn_inside = robust_motion_cue(labels, matches, kp_dyn, kp_ok, cfg)
    base_rel = rel if cfg.baseline_refined_pose else relative_pose(prior_t, prior_t2)
    baseline = baseline_motion_cue(prior_t, prior_t2, flow, base_rel, cfg)
    return MotionCues(flow_mask=flow_mask, geo_mask=geo_mask, candidates=candidates, robust_mask=robust,
                      baseline_mask=baseline, residual=residual, valid=valid, geo_threshold=thr,
                      rel_pose=rel, kp_dynamic=kp_dyn_inside, kp_valid=kp_ok)


def sequence_motion_cues(priors: FramePrior, flows, matches, cfg: MotionConfig = MotionConfig()) -> MotionCues:
    """Cues of frames 0..S-2 of a sequence (priors with a leading S axis, flows (S-1, H, W, 2),
    matches with a leading S-1 axis): one compiled ``vmap`` of :func:`motion_cues`."""
    first = jax.tree.map(lambda a: a[:-1], priors)
    second = jax.tree.map(lambda a: a[1:], priors)
    return _batched(first, second, jnp.asarray(flows, jnp.float32), matches, cfg)


# ----------------------------------------------------------------------------------------------
# stage 6: landmark tracks over several frames


def segment_median(x, group, valid, num_groups: int):
    """Per-group median (lower middle value) of ``x[valid]`` (K,) by ``group`` (K,) int in
    [0, num_groups): (num_groups,), 0 for an empty group. One sort, fixed shapes."""
    g = jnp.where(valid, group, num_groups)
    order = jnp.lexsort((jnp.where(valid, x, jnp.inf), g))
    xs = x[order]
    count = jax.ops.segment_sum(valid.astype(jnp.int32), group, num_groups)
    start = jnp.cumsum(count) - count
    med = xs[jnp.clip(start + (count - 1) // 2, 0, x.shape[0] - 1)]
    return jnp.where(count > 0, med, 0.0)


def track_residuals(points, poses, intrinsics, pose_idx, uv, valid, block, num_blocks: int,
                    cfg: MotionConfig = MotionConfig()):
    """Reprojection residuals of landmark tracks after each group's best rigid correction.

    points (L, 3) world landmarks lifted from their seed pixel (prior depth, prior pose of the seed
    frame); poses (W, 4, 4) cam_to_world priors and intrinsics (W, 3, 3) of the window's frames;
    pose_idx, uv, valid (L * T,) the tracks' observations, landmark-major (observation t of
    landmark l at ``l * T + t``, t = 0 the seed); block (L,) int in [0, num_blocks): the seeding
    block (landmarks seeded from one frame share its pose error).

    A prior pose error moves every static landmark seen in frame i and seeded in block b by one
    rigid transform of camera i (the error of the pair's relative pose): per group (b, i), a
    correction ``exp(delta) T`` of the landmarks' camera points is fitted by ``track_iters`` damped
    Gauss-Newton steps with Geman-McClure weights at the group's robust scale (``1.4826`` x its
    median residual, at least ``track_min_scale_px``), so tracks on moving objects stay outliers.
    An affine image-motion model leaves the depth-dependent parallax of the translation error
    (measured at 96x128, moderate priors: static residual p90 1.0-1.5 px against 0.1-0.4 px with the
    rigid one, movers 1.4-2.6 px after 3 frames). Returns (residual (L * T, 2) px, judged (L * T,)
    bool: t > 0, in front of the camera, in a group of at least ``track_min_obs`` observations)."""
    L = points.shape[0]
    Kn = pose_idx.shape[0]
    T = Kn // L
    W = poses.shape[0]
    G = num_blocks * W
    dt = poses.dtype
    pose_idx = jnp.asarray(pose_idx, jnp.int32)
    group = jnp.repeat(jnp.asarray(block, jnp.int32), T) * W + pose_idx
    point = jnp.repeat(jnp.arange(L), T)
    j = jnp.tile(jnp.arange(T), L)
    inv = se3.inverse(poses)[pose_idx]
    X = jnp.einsum("kij,kj->ki", inv[:, :3, :3], points[point].astype(dt)) + inv[:, :3, 3]
    Kk = intrinsics[pose_idx].astype(dt)
    fx, sk, cx, fy, cy = Kk[:, 0, 0], Kk[:, 0, 1], Kk[:, 0, 2], Kk[:, 1, 1], Kk[:, 1, 2]
    uv = jnp.asarray(uv, dt)

    def residuals(corr):
        C = corr[group]
        Y = jnp.einsum("kij,kj->ki", C[:, :3, :3], X) + C[:, :3, 3]
        z = Y[:, 2]
        zs = jnp.where(z > camera.MIN_DEPTH, z, 1.0)
        r = jnp.stack([(fx * Y[:, 0] + sk * Y[:, 1]) / zs + cx, fy * Y[:, 1] / zs + cy], -1) - uv
        ok = valid & (j > 0) & (z > camera.MIN_DEPTH) & jnp.all(jnp.isfinite(r), -1)
        return r, Y, zs, ok

    _, _, _, ok0 = residuals(jnp.broadcast_to(jnp.eye(4, dtype=dt), (G, 4, 4)))
    count = jax.ops.segment_sum(ok0.astype(jnp.int32), group, G)
    fit = count >= cfg.track_min_obs
    eye6 = jnp.eye(6, dtype=dt)

    def step(corr, _):
        r, Y, z, ok = residuals(corr)
        rn = jnp.linalg.norm(r, axis=-1)
        scale = jnp.maximum(cfg.track_min_scale_px, 1.4826 * segment_median(rn, group, ok, G))[group]
        q = 1.0 / (1.0 + (rn / scale) ** 2)
        w = jnp.where(ok, q * q, 0.0)
        J = _pinhole_left_jacobian(Y, z, fx, sk, fy)
        Hm = jax.ops.segment_sum(w[:, None, None] * jnp.einsum("kri,krj->kij", J, J), group, G)
        g = jax.ops.segment_sum(w[:, None] * jnp.einsum("kri,kr->ki", J, r), group, G)
        damp = 1e-6 * jnp.trace(Hm, axis1=-2, axis2=-1) / 6.0 + 1e-9
        delta = -jnp.linalg.solve(Hm + damp[:, None, None] * eye6, g[..., None])[..., 0]
        delta = jnp.where(fit[:, None] & jnp.all(jnp.isfinite(delta), -1, keepdims=True), delta, 0.0)
        return se3.exp(delta) @ corr, None

    corr, _ = jax.lax.scan(step, jnp.broadcast_to(jnp.eye(4, dtype=dt), (G, 4, 4)), None, length=cfg.track_iters)
    r, _, _, ok = residuals(corr)
    return jnp.where(ok[:, None], r, 0.0), ok & fit[group]


def moving_tracks(points, poses, intrinsics, pose_idx, uv, valid, block, num_blocks: int,
                  cfg: MotionConfig = MotionConfig()):
    """The track cue: (L,) bool, landmark tracks that move against the static scene.

    A mover as slow as the prior's pose noise (about 1 px per frame at 96x128) is lost in the
    two-frame residual flow, but its track drifts off the rigidly explained scene by that much
    every frame. Each track's RMS residual over its judged observations (:func:`track_residuals`)
    is compared with ``max(track_min_px, median + track_n_mad 1.4826 MAD)`` over the judged tracks.
    Arguments as :func:`track_residuals`; tracks without a judged observation are not moving.
    Returns all False when ``cfg.track_cue`` is off."""
    L = points.shape[0]
    if not cfg.track_cue:
        return jnp.zeros(L, bool)
    r, judged = track_residuals(points, poses, intrinsics, pose_idx, uv, valid, block, num_blocks, cfg)
    return moving_from_residuals(r, judged, L, cfg)


def moving_from_residuals(r, judged, num_tracks: int, cfg: MotionConfig = MotionConfig()):
    """The decision of :func:`moving_tracks` from :func:`track_residuals`' output: (L,) bool."""
    L = num_tracks
    T = judged.shape[0] // L
    jl = judged.reshape(L, T)
    n = jnp.sum(jl, -1)
    rms = jnp.sqrt(jnp.sum(jnp.where(jl, jnp.sum(r * r, -1).reshape(L, T), 0.0), -1) / jnp.maximum(n, 1))
    has = n > 0
    med = masked_median(rms, has)
    mad = masked_median(jnp.abs(rms - med), has)
    tau = jnp.maximum(cfg.track_min_px, med + cfg.track_n_mad * 1.4826 * mad)
    return has & (rms > tau)


@jax.jit
def _warp(mask, flow):
    H, W = mask.shape
    grid = camera.pixel_grid(H, W, flow.dtype)
    tgt = jnp.round(grid + flow).astype(jnp.int32)
    u, v = tgt[..., 0], tgt[..., 1]
    ok = mask & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    idx = jnp.where(ok, v * W + u, H * W).reshape(-1)
    out = jnp.zeros(H * W + 1, bool).at[idx].max(ok.reshape(-1))[: H * W].reshape(H, W)
    return components.closing(out, 1)


def warp_mask(mask, flow):
    """Forward-warp a mask (H, W) of frame t to frame t+1 with the flow (H, W, 2): every set pixel
    is splatted to its rounded target, and the splat holes are closed (3x3 closing)."""
    return _warp(jnp.asarray(mask, bool), jnp.asarray(flow, jnp.float32))


_batched = jax.jit(jax.vmap(motion_cues, in_axes=(0, 0, 0, 0, None)), static_argnums=4)
motion_cues_jit = jax.jit(motion_cues, static_argnums=4)
