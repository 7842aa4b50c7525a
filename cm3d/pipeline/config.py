"""The pipeline's options: one frozen, hashable :class:`PipelineConfig` (a static argument of the
compiled step), and the defaults for small images."""

from __future__ import annotations

import dataclasses

from cm3d import memory, trajectory
from cm3d.motion import MotionConfig
from cm3d.pipeline.global_graph import GlobalGraphConfig
from cm3d.ops.flow import FlowConfig
from cm3d.ops.gmm import GMMConfig
from cm3d.ops.keypoints import KeypointConfig
from cm3d.solvers import factors, lm


@dataclasses.dataclass(frozen=True)
class TrackCheckConfig:
    """Tracks checked against the prior before the graph
    (:func:`cm3d.pipeline.window.prior_consistent_tracks`): a track whose transfer error (px at
    reduced resolution) exceeds ``max(min_px, median + n_mad · σ_MAD)`` of the window's is dropped."""

    n_mad: float = 3.0
    min_px: float = 0.1

    def __post_init__(self):
        if not self.n_mad > 0 or not self.min_px >= 0:
            raise ValueError(f"TrackCheckConfig: n_mad > 0 and min_px >= 0 required, got {self.n_mad}, {self.min_px}")


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """All options of the pipeline (hashable, a static argument of the compiled step).

    keyframe_interval: frames per window (paper: 20); stride: cues, landmarks and memory run at 1/stride
    resolution; motion, track, assoc, refine (pixel noise at reduced resolution; its gate run by
    :func:`~cm3d.pipeline.window.gate_refinement`), track_check, memory (for a new bank; a loaded one
    brings its own): the stages' options; use_memory: recall / verify / update at all;
    min_memory_landmarks: fewest landmarks on the surface for the memory solution; memory_sigma_voxels:
    floor of the point-to-plane std in map voxels; memory_photometric: the memory solution is used only
    when the window's static pixels, warped with the prior depth, agree better under it than under the
    memory-free poses, by more than the photometric tie (besides its χ² test;
    memory_graph.photometric_test); map_min_support:
    stored entries drop voxels with fewer samples than this share of the median voxel's;
    keyframe_threshold: descriptor distance between memory keyframes; flow / keypoints: the OpenCV front
    end. The memory's features: SIFT at the input's full resolution (issue 22) at contrast 0.01, a round
    robin over an 8 x 8 image grid (a revisit then finds keypoints on the weakly textured walls a first
    visit saw, docs/memory.md, stop 44), on every ``feature_every``-th frame (t % feature_every == 0),
    ``feature_capacity`` 3D keypoints each. The motion cue's matches (frame t with its partner): from that
    full-resolution detection (then made on every frame), its keypoints that pass OpenCV's default 0.04
    (``keypoints.match_contrast``: the matches of a 0.04 detection at a sixth of the matching cost); with
    ``match_reduced``, SIFT on the image area-averaged by ``stride`` (the back end's resolution) at contrast
    ``match_contrast`` on every frame. ``match_reduced`` with features on every 2nd frame, 256 each (and
    ``match_contrast`` 0.02), cuts the host's SIFT work by two thirds and a warm run by ~5 %, but moved the
    memory's figures (one more kitchen window recalled, the chunked kitchen with memory 11 % worse): measured
    in docs/pipeline.md (stop 64), not the default; global_graph: the pose
    graph over every frame after the windows (:mod:`cm3d.pipeline.global_graph`, host side);
    refine_masks: the output masks are the motion cue's masks refined and tracked over the sequence
    (:func:`cm3d.refine.refine_sequence`, GrabCut, host side, a piece at a time beside the back end:
    :class:`cm3d.pipeline.run.MaskStream`; the landmarks and the memory use the cue's masks); seed: the
    RANSAC key.

    ``batching="native"``: the LM's sequential ``custom_vmap`` rule fails inside ``scan`` + ``cond``."""

    keyframe_interval: int = 20
    stride: int = 2
    motion: MotionConfig = MotionConfig(gmm=GMMConfig(num_components=3, max_iters=10, tol=1e-3))
    track: trajectory.TrackConfig = trajectory.TrackConfig(cell=16, keyframe_every=4, track_length=8,
                                                           border=2, min_track=3)
    assoc: trajectory.AssociationConfig = trajectory.AssociationConfig()
    refine: trajectory.RefineConfig = trajectory.RefineConfig(
        graph=factors.GraphConfig(sigma_proj=0.5),
        solver=lm.LMOptions(backward="none", max_iterations=20, max_linear_solves=40, batching="native"),
        outliers=factors.OutlierConfig(tau_min_px=1.0))
    # 4096 keypoints per map (the benchmark's 200-map bank keeps 1024): docs/memory.md, stop 54
    memory: memory.MemoryConfig = memory.MemoryConfig(max_maps=16, max_points=4096, max_keyframes=16,
                                                      max_keypoints=4096)
    track_check: TrackCheckConfig = TrackCheckConfig()
    use_memory: bool = True
    map_min_support: float = 0.2
    min_memory_landmarks: int = 12
    memory_sigma_voxels: float = 0.5
    keyframe_threshold: float = 0.25
    memory_photometric: bool = True
    feature_capacity: int = 128
    feature_every: int = 1
    match_reduced: bool = False
    flow: FlowConfig = FlowConfig()
    keypoints: KeypointConfig = KeypointConfig(max_matches=256, contrast_threshold=0.01, spread_cells=8,
                                               match_contrast=0.04)
    global_graph: GlobalGraphConfig = GlobalGraphConfig()
    refine_masks: bool = True
    seed: int = 0

    def __post_init__(self):
        for ok, what in ((self.keyframe_interval >= 2, "keyframe_interval: must be >= 2"),
                         (self.stride >= 1, "stride: must be >= 1"),
                         (self.feature_capacity >= 1, "feature_capacity: must be >= 1"),
                         (self.feature_every >= 1, "feature_every: must be >= 1"),
                         (self.min_memory_landmarks >= 1, "min_memory_landmarks: must be >= 1"),
                         (0 <= self.map_min_support < 1, "map_min_support: must be in [0, 1)"),
                         (self.memory_sigma_voxels >= 0, "memory_sigma_voxels: must be >= 0")):
            if not ok:
                name = what.split(":")[0]
                raise ValueError(f"PipelineConfig.{what}, got {getattr(self, name)}")

    @property
    def window(self) -> int:
        """Pose slots per window: the anchor plus ``keyframe_interval`` frames."""
        return self.keyframe_interval + 1

    @property
    def seed_blocks(self) -> int:
        """Landmark seeding slots per window (0, κ, 2κ, ... below ``keyframe_interval``)."""
        return -(-self.keyframe_interval // self.track.keyframe_every)


def small_config(**changes) -> PipelineConfig:
    """A config for tiny images (tests, ``--quick``): small cells, memory and capacities."""
    base = PipelineConfig(
        keyframe_interval=4, stride=1,
        track=trajectory.TrackConfig(cell=8, keyframe_every=2, track_length=4, border=2, min_track=2),
        memory=memory.MemoryConfig(max_maps=4, max_points=256, max_keyframes=4, max_keypoints=64,
                                   icp_points=64, ransac_hypotheses=64, min_inliers=20,
                                   min_keypoint_inliers=4),  # a 48x64 window has few distinct 3D points
        feature_capacity=32, feature_every=1, keypoints=KeypointConfig(max_matches=64))
    return dataclasses.replace(base, **changes)


def config_for(height: int, width: int, **changes) -> PipelineConfig:
    """The default config for an image size: :func:`small_config` below 192 px on the short side
    (landmark cells would not fit at half resolution), :class:`PipelineConfig` otherwise."""
    if min(height, width) < 192:
        return small_config(**changes)
    return dataclasses.replace(PipelineConfig(), **changes)


def bank_config(bank: memory.MemoryBank, cfg: PipelineConfig) -> memory.MemoryConfig:
    """``cfg.memory`` with the bank's capacities (a loaded bank may differ from ``cfg.memory``)."""
    caps = memory.capacities(bank)
    if all(getattr(cfg.memory, k) == v for k, v in caps.items()):
        return cfg.memory
    return dataclasses.replace(cfg.memory, **caps)
