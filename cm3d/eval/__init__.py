"""Evaluation: trajectory (ATE/RPE, evo-compatible), depth, dynamic-mask and reconstruction metrics.

Importing this package loads only numpy and jax; scipy is imported inside
:func:`cm3d.eval.metrics.reconstruction_metrics` when it is called.
"""

from cm3d.eval.metrics import (
    align_depth_scale_shift,
    align_trajectory,
    associate,
    ate,
    depth_metrics,
    evaluate_trajectories,
    evaluate_trajectory_files,
    mask_metrics,
    pose_metrics,
    reconstruction_metrics,
    rpe,
    umeyama,
)

__all__ = [
    "align_depth_scale_shift",
    "align_trajectory",
    "associate",
    "ate",
    "depth_metrics",
    "evaluate_trajectories",
    "evaluate_trajectory_files",
    "mask_metrics",
    "pose_metrics",
    "reconstruction_metrics",
    "rpe",
    "umeyama",
]
