"""The motion cues' inputs, outputs and options: one frame's priors, each stage's mask, the config."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
from flax import struct

from cm3d.ops.gmm import GMMConfig


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
class SecondPair:
    """A second partner of frame t (its previous frame, in the pipeline): the partner's priors, flow
    (H, W, 2) t -> partner, flow partner -> t (for the forward-backward check), valid () bool."""

    partner: FramePrior
    flow: jnp.ndarray
    flow_rev: jnp.ndarray
    valid: jnp.ndarray


@struct.dataclass
class MotionCues:
    """Each stage's mask (H, W) bool and the geometric residual, for one frame pair (t, t2).

    flow_mask, geo_mask, candidates, robust_mask, baseline_mask: the stages' masks; residual (H, W)
    px (0 where invalid); valid (H, W); geo_threshold (px); rel_pose (4, 4) refined camera-t ->
    camera-t2; kp_dynamic, kp_valid (N,) per match; occluded (H, W): not judged in the pair (t, t2).
    With a second pair, geo_mask and valid combine both pairs; residual, threshold and rel_pose
    are the first pair's.
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
    occluded: jnp.ndarray


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
    pose_scale_k: float = 1.0  # robust scale = k * robust_sigma(residual)
    # geometry cue
    otsu_bins: int = 256
    otsu_log: bool = True  # Otsu on log(residual): static noise and motion are modes apart by decades
    residual_floor_px: float = 1.0
    residual_noise_k: float = 4.0  # threshold >= k * median residual (the static noise level)
    min_depth_conf: float = 0.0
    border_px: float = 2.0  # a pixel whose flow or ego flow leaves the image (minus this) is not judged
    # occlusion reasoning (cm3d.motion.occlusion): occluded pixels are not judged
    occlusion: bool = True
    fb_alpha: float = 0.01  # forward-backward check |w + w'|^2 <= alpha (|w|^2 + |w'|^2) + beta (Sundaram 2010)
    fb_beta_px2: float = 0.5
    fb_occludes: bool = False  # an inconsistent pixel is not judged (else it is only left out of the pose fit)
    zbuffer_rel_tol: float = 0.05  # hidden: lands behind the partner's depth by more than this fraction
    edge_radius_px: int = 2  # the residual is to the ego flows of every depth within this radius (0: own depth)
    hole_edges: bool = True  # pixels within edge_radius_px of a hole (confidence 0) spanning 2r+1 px are not judged
    two_pairs: bool = True  # with a second partner (t-1), dynamic = moving in every pair that judges it
    # appearance check (cm3d.motion.appearance): a candidate region is kept only where the images
    # reject the static hypothesis (ego-warp patch dissimilarity above the flow warp's by k robust
    # sigmas of that excess on the presumed-static pixels, and worse than the q-quantile of the
    # flow warp's there) on at least min_fraction of its pixels, in either pair
    appearance: bool = True
    appearance_radius: int = 2
    appearance_k: float = 3.0
    appearance_q: float = 0.9
    appearance_min_fraction: float = 0.3
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
        if self.pose_stride < 1 or self.pose_iters < 0:
            raise ValueError("MotionConfig.pose_stride >= 1 and pose_iters >= 0 required")
        if self.track_iters < 0 or self.track_min_obs < 6:
            raise ValueError(f"MotionConfig.track_iters >= 0 and track_min_obs >= 6 (a rigid fit) required, "
                             f"got {self.track_iters}, {self.track_min_obs}")
        for name in ("track_min_scale_px", "track_n_mad", "track_min_px"):
            if not getattr(self, name) > 0:
                raise ValueError(f"MotionConfig.{name}: must be > 0, got {getattr(self, name)}")
