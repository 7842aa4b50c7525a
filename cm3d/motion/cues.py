"""The flow cue, the composition of all cues of a frame pair, and the mask warp used for tracking."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from cm3d.motion.appearance import confirmed_regions, static_rejected
from cm3d.motion.frames import FramePrior, MotionConfig, MotionCues, SecondPair
from cm3d.motion.geometry_cue import baseline_motion_cue, geometry_motion_cue
from cm3d.motion.keypoint_cue import (
    candidate_regions, dynamic_keypoints, keypoint_displacements, robust_motion_cue, static_reference
)
from cm3d.ops import camera, components
from cm3d.ops.gmm import fit_gmm, slowest_component_mask


def flow_motion_cue(flow, cfg: MotionConfig = MotionConfig()):
    """GMM on flow vectors (H, W, 2) -> (moving mask (H, W), :class:`GMMResult`).

    The moving pixels are those outside the component of smallest mean flow magnitude.
    """
    H, W = flow.shape[:2]
    res = fit_gmm(flow.reshape(-1, 2), cfg.gmm)
    return slowest_component_mask(res).reshape(H, W), res


def combine_pairs(mask_a, valid_a, mask_b, valid_b):
    """Evidence over two frame pairs: (dynamic, judged) (H, W). A pixel is dynamic when it moves in
    every pair that judges it (an occluded or out-of-view pixel is judged by the other pair alone)."""
    judged = valid_a | valid_b
    return (mask_a | ~valid_a) & (mask_b | ~valid_b) & judged, judged


def motion_cues(prior_t: FramePrior, prior_t2: FramePrior, flow, matches,
                cfg: MotionConfig = MotionConfig(), flow_rev=None, second: SecondPair | None = None) -> MotionCues:
    """All motion cues of frame t from the pair (t, t2): flow (H, W, 2) forward from t to t2 and
    keypoint ``matches`` (:class:`cm3d.ops.keypoints.Matches`, padded). ``flow_rev`` (t2 -> t):
    the forward-backward occlusion check; ``second``: another partner (:class:`SecondPair`) whose
    residual cue must agree (``cfg.two_pairs``). Pure; jit with ``cfg`` static, vmap over frames."""
    flow = jnp.asarray(flow, jnp.float32)
    if flow.shape != prior_t.depth.shape + (2,):
        raise ValueError(f"motion_cues: flow shape {flow.shape} does not match depth {prior_t.depth.shape}")
    flow_mask, _ = flow_motion_cue(flow, cfg)
    geo = geometry_motion_cue(prior_t, prior_t2, flow, cfg, flow_rev)
    geo_mask, valid = geo.mask, geo.valid
    if cfg.appearance:
        support = _rejects_static(prior_t, prior_t2, flow, geo, cfg)
    if second is not None and cfg.two_pairs:
        flow2 = jnp.asarray(second.flow, jnp.float32)
        g2 = geometry_motion_cue(prior_t, second.partner, flow2, cfg, jnp.asarray(second.flow_rev, jnp.float32))
        ok2 = jnp.asarray(second.valid, bool)
        geo_mask, valid = combine_pairs(geo_mask, valid, g2.mask & ok2, g2.valid & ok2)
        if cfg.appearance:
            support |= _rejects_static(prior_t, second.partner, flow2, g2, cfg) & ok2
    residual, thr, rel = geo.residual, geo.threshold, geo.rel_pose
    candidates, labels = candidate_regions(flow_mask, geo_mask, valid, cfg)
    if cfg.appearance:
        labels = confirmed_regions(labels, support, cfg.appearance_min_fraction)
    disp, ray, kp_ok = keypoint_displacements(prior_t, prior_t2, matches, rel, cfg)
    kp_dyn = dynamic_keypoints(disp, ray, kp_ok, cfg, static_reference(labels, matches, kp_ok, cfg))
    robust, kp_dyn_inside = robust_motion_cue(labels, matches, kp_dyn, kp_ok, cfg)
    baseline = baseline_motion_cue(prior_t, prior_t2, flow, rel, cfg)
    return MotionCues(flow_mask=flow_mask, geo_mask=geo_mask, candidates=candidates, robust_mask=robust,
                      baseline_mask=baseline, residual=residual, valid=valid, geo_threshold=thr,
                      rel_pose=rel, kp_dynamic=kp_dyn_inside, kp_valid=kp_ok, occluded=geo.occluded)


def _rejects_static(prior_t: FramePrior, prior_t2: FramePrior, flow, geo, cfg: MotionConfig):
    """Pixels whose images reject the static hypothesis of the pair (:mod:`cm3d.motion.appearance`)."""
    return static_rejected(prior_t.image, prior_t2.image, flow, geo.ego, geo.valid & ~geo.mask,
                           cfg.appearance_radius, cfg.appearance_k, cfg.appearance_q)


def sequence_motion_cues(priors: FramePrior, flows, matches, cfg: MotionConfig = MotionConfig(),
                         flows_rev=None) -> MotionCues:
    """Cues of frames 0..S-2 of a sequence (priors with a leading S axis, flows (S-1, H, W, 2),
    matches with a leading S-1 axis): one compiled ``vmap`` of :func:`motion_cues`.

    ``flows_rev`` (S-1, H, W, 2), flow t+1 -> t: the cues the pipeline's step computes. Every pair
    gets the forward-backward occlusion check, and every frame t >= 1 its previous frame as the
    second partner (:class:`SecondPair`: flow t -> t-1 is ``flows_rev[t-1]``, its reverse
    ``flows[t-1]``). Without it, each pair on its own, with no occlusion check."""
    first = jax.tree.map(lambda a: a[:-1], priors)
    second = jax.tree.map(lambda a: a[1:], priors)
    flows = jnp.asarray(flows, jnp.float32)
    if flows_rev is None:
        return _batched(first, second, flows, matches, None, None, cfg)
    flows_rev = jnp.asarray(flows_rev, jnp.float32)
    if flows_rev.shape != flows.shape:
        raise ValueError(f"flows_rev: shape {flows_rev.shape} differs from flows {flows.shape}")
    n = flows.shape[0]
    prev = jnp.maximum(jnp.arange(n) - 1, 0)
    pair = SecondPair(partner=jax.tree.map(lambda a: a[prev], priors), flow=flows_rev[prev], flow_rev=flows[prev],
                      valid=jnp.arange(n) >= 1)
    return _batched(first, second, flows, matches, flows_rev, pair, cfg)


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


# flow_rev / second may be None (empty pytrees: nothing to map)
_batched = jax.jit(jax.vmap(lambda a, b, f, m, fr, sp, cfg: motion_cues(a, b, f, m, cfg, fr, sp),
                            in_axes=(0, 0, 0, 0, 0, 0, None)), static_argnums=6)
motion_cues_jit = jax.jit(motion_cues, static_argnums=4)
