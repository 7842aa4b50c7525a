"""Motion cues: which pixels of frame t belong to moving objects (CogniMap3D, first stage).

``motion_cues(prior_t, prior_t2, flow, matches, cfg)`` is pure, jittable and vmappable and returns
each stage's mask: ``flow_motion_cue`` (GMM on the flow, :mod:`.cues`), ``geometry_motion_cue``
(residual to the ego flow of the flow-refined relative pose, Otsu, :mod:`.geometry_cue`),
``robust_motion_cue`` (candidate regions the images confirm, :mod:`.appearance`, and keypoints
confirm, :mod:`.keypoint_cue`) and the
MonST3R-style ``baseline_motion_cue``. The track cue (:mod:`.track_cue`) judges landmark tracks over
several frames; host-side refinement is :mod:`cm3d.refine`. Conventions: :mod:`cm3d.ops.camera`.
"""

# the public API of the motion cues (re-exported)
from cm3d.motion.cues import combine_pairs, flow_motion_cue, motion_cues, motion_cues_jit, sequence_motion_cues, warp_mask  # noqa: F401
from cm3d.motion.appearance import confirmed_regions, static_rejected, warp_dissimilarity  # noqa: F401
from cm3d.motion.frames import FramePrior, MotionConfig, MotionCues, SecondPair  # noqa: F401
from cm3d.motion.geometry_cue import (  # noqa: F401
    GeometryCue, baseline_motion_cue, ego_flow_rel, geometry_motion_cue, refine_relative_pose, relative_pose
)
from cm3d.motion.keypoint_cue import (  # noqa: F401
    candidate_regions, dynamic_keypoints, keypoint_displacements, robust_motion_cue, static_reference
)
from cm3d.motion.occlusion import (  # noqa: F401
    depth_range_residual, forward_backward_consistent, visible_in_partner
)
from cm3d.motion.track_cue import moving_from_residuals, moving_tracks, segment_median, track_residuals  # noqa: F401
