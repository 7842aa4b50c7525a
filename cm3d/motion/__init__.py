"""Motion cues: which pixels of frame t belong to moving objects (CogniMap3D, first stage).

``motion_cues(prior_t, prior_t2, flow, matches, cfg)`` is one pure, jittable and vmappable
function composed of named stages, each returning its own mask so experiments can score them:

1. ``flow_motion_cue`` (:mod:`.cues`): a K-component GMM on the flow vectors; every pixel outside
   the component of smallest mean flow magnitude is moving (:mod:`cm3d.ops.gmm`).
2. ``geometry_motion_cue`` (:mod:`.geometry_cue`): the residual ``|flow − ego_flow|`` under the
   relative pose re-aligned to the flow (``refine_relative_pose``: robust Gauss–Newton on SE(3)),
   thresholded by Otsu on log residual above a noise floor.
3. ``robust_motion_cue`` (:mod:`.keypoint_cue`): candidate regions (4-connected components of the
   cleaned candidates) holding enough keypoints whose depth-normalised 3D displacement deviates
   from the static reference's (robust sigmas along and across the viewing ray).
4. ``baseline_motion_cue``: MonST3R-style fixed threshold on the residual flow, for comparison.

The track cue (:mod:`.track_cue`, ``moving_tracks``) judges the pipeline's landmark tracks over
several frames. Refinement by seeded segmentation and tracking run on the host: :mod:`cm3d.refine`.
Conventions: :mod:`cm3d.ops.camera` (cam_to_world poses, forward flow ``F[v, u] = (du, dv)``).
"""

# the public API of the motion cues (re-exported)
from cm3d.motion.cues import flow_motion_cue, motion_cues, motion_cues_jit, sequence_motion_cues, warp_mask  # noqa: F401
from cm3d.motion.frames import FramePrior, MotionConfig, MotionCues  # noqa: F401
from cm3d.motion.geometry_cue import (  # noqa: F401
    baseline_motion_cue, ego_flow_rel, geometry_motion_cue, refine_relative_pose, relative_pose
)
from cm3d.motion.keypoint_cue import (  # noqa: F401
    candidate_regions, dynamic_keypoints, keypoint_displacements, robust_motion_cue, static_reference
)
from cm3d.motion.track_cue import moving_from_residuals, moving_tracks, segment_median, track_residuals  # noqa: F401
