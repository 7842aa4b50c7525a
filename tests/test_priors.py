"""The one VGGT-like prior model (cm3d.data.priors): frame, scale, noise levels, holes, seeds."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cm3d.data import GroundTruth, priors, synthetic


def _ground_truth(S=40, H=24, W=32, seed=0, holes=True):
    rng = np.random.default_rng(seed)
    c2w = np.tile(np.eye(4), (S, 1, 1))
    c2w[:, :3, :3] = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.02, (S, 3)), 0)).as_matrix()
    c2w[:, :3, 3] = np.cumsum(rng.normal(0, 0.05, (S, 3)), 0) + [1.0, -2.0, 0.5]
    depth = rng.uniform(1.0, 3.0, (S, H, W)).astype(np.float32)
    if holes:
        depth[rng.random((S, H, W)) < 0.2] = 0.0
    K = np.broadcast_to(np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]]), (S, 3, 3)).copy()
    return np.zeros((S, H, W, 3), np.uint8), GroundTruth(cam_to_world=c2w, depth=depth, intrinsic=K)


def _rot_err_deg(seq):
    gt = seq.gt.cam_to_world
    rel = np.linalg.inv(gt[0]) @ gt
    dR = np.swapaxes(rel[:, :3, :3], 1, 2) @ seq.cam_to_world[:, :3, :3]
    return np.degrees(np.linalg.norm(Rotation.from_matrix(dR).as_rotvec(), axis=1))


def test_none_is_exact_up_to_the_unknown_similarity():
    images, gt = _ground_truth()
    seq = priors.make_priors(images, gt, "none", seed=1)
    s = seq.meta["prior_scale"]
    rel = np.linalg.inv(gt.cam_to_world[0]) @ gt.cam_to_world
    np.testing.assert_allclose(seq.cam_to_world[:, :3, :3], rel[:, :3, :3], atol=1e-9)
    np.testing.assert_allclose(seq.cam_to_world[:, :3, 3], s * rel[:, :3, 3], atol=1e-9)
    np.testing.assert_allclose(seq.depth, s * gt.depth, rtol=1e-6)
    np.testing.assert_allclose(seq.cam_to_world[0], np.eye(4), atol=1e-12)


def test_holes_stay_holes_with_zero_confidence():
    images, gt = _ground_truth()
    seq = priors.make_priors(images, gt, "severe", seed=2)
    holes = gt.depth == 0
    assert holes.any()
    assert (seq.depth[holes] == 0).all() and (seq.depth_conf[holes] == 0).all()
    assert (seq.depth[~holes] > 0).all() and (seq.depth_conf[~holes] >= 1).all()


def test_levels_follow_table6_sizes_and_grow():
    images, gt = _ground_truth(S=200, H=8, W=8, holes=False)
    rms = {}
    for level, (deg, _) in priors.NOISE_LEVELS.items():
        errs = [_rot_err_deg(priors.make_priors(images, gt, level, seed=k))[1:] for k in range(4)]
        rms[level] = float(np.sqrt(np.mean(np.square(errs))))
        if deg:
            assert 0.4 * deg < rms[level] < 1.6 * deg, (level, rms[level])
    assert rms["none"] == 0 and rms["slight"] < rms["moderate"] < rms["severe"]


def test_seeded_and_scale_unknown():
    images, gt = _ground_truth()
    a = priors.make_priors(images, gt, "moderate", seed=5)
    b = priors.make_priors(images, gt, "moderate", seed=5)
    c = priors.make_priors(images, gt, "moderate", seed=6)
    np.testing.assert_array_equal(a.cam_to_world, b.cam_to_world)
    np.testing.assert_array_equal(a.depth, b.depth)
    assert not np.allclose(a.cam_to_world, c.cam_to_world)
    assert a.meta["prior_scale"] != c.meta["prior_scale"]
    with pytest.raises(ValueError, match="unknown noise level"):
        priors.make_priors(images, gt, "extreme")


def test_segments_each_in_their_own_frame():
    images, gt = _ground_truth()
    segs = priors.segment_priors(images, gt, [(0, 15), (15, 30), (25, 40)], "slight", seed=1)
    assert [s.num_frames for s in segs] == [15, 15, 15]
    for k, s in enumerate(segs):
        np.testing.assert_allclose(s.cam_to_world[0], np.eye(4), atol=1e-12)
        assert s.meta["chunk"] == k
    np.testing.assert_array_equal(segs[1].gt.cam_to_world, gt.cam_to_world[15:30])
    assert len({s.meta["prior_scale"] for s in segs}) == 3


def test_synthetic_world_uses_this_prior_model():
    images, gt = _ground_truth(holes=False)
    a = synthetic.make_priors(images, gt, "moderate", seed=4)
    b = priors.make_priors(images, gt, "moderate", seed=4)
    for k in ("depth", "depth_conf", "cam_to_world"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    assert synthetic.NOISE_LEVELS is priors.NOISE_LEVELS
