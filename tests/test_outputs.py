"""Output writers and pictures: readable by Open3D / OpenCV / evo, atomic, clear errors."""

import dataclasses

import cv2
import numpy as np
import pytest

from cm3d import outputs
from cm3d.eval import plots


def test_ply_reads_back_in_open3d(tmp_path):
    import open3d as o3d

    rng = np.random.default_rng(0)
    pts = rng.normal(size=(100, 3)).astype(np.float32)
    cols = rng.integers(0, 256, size=(100, 3)).astype(np.uint8)
    outputs.write_ply(tmp_path / "m.ply", pts, cols)
    pcd = o3d.io.read_point_cloud(str(tmp_path / "m.ply"))
    np.testing.assert_allclose(np.asarray(pcd.points), pts, atol=1e-6)
    np.testing.assert_allclose(np.asarray(pcd.colors) * 255, cols, atol=1e-3)
    outputs.write_ply(tmp_path / "bare.ply", pts)
    assert len(o3d.io.read_point_cloud(str(tmp_path / "bare.ply")).points) == 100
    with pytest.raises(ValueError, match="non-finite"):
        outputs.write_ply(tmp_path / "bad.ply", np.full((2, 3), np.nan))


def test_masks_json_and_pictures(tmp_path):
    masks = np.zeros((3, 8, 10), bool)
    masks[1, 2:5, 3:6] = True
    paths = outputs.write_masks(tmp_path / "masks", masks)
    assert [p.name for p in paths] == ["000000.png", "000001.png", "000002.png"]
    back = cv2.imread(str(paths[1]), cv2.IMREAD_UNCHANGED)
    assert back.dtype == np.uint8 and set(np.unique(back)) == {0, 255}
    np.testing.assert_array_equal(back == 255, masks[1])

    outputs.write_json(tmp_path / "m.json", {"a": np.float32(1.5), "T": np.eye(2)})
    assert (tmp_path / "m.json").read_text().count("1.5") == 1

    images = np.full((3, 8, 10, 3), 100, np.uint8)
    over = plots.mask_overlay(images[1], masks[1])
    assert over[3, 4, 0] > 100 and over[0, 0, 0] == 100
    plots.save_mask_overlays(tmp_path / "ov", images, masks)
    t = np.linspace(0, 1, 20)
    traj = np.stack([t, np.sin(t), 0 * t], -1)
    plots.plot_trajectories(tmp_path / "traj.png", {"prior": traj, "refined": traj + 0.01})
    plots.plot_topdown_map(tmp_path / "map.png", np.random.default_rng(1).normal(size=(500, 3)),
                           from_memory=np.arange(500) < 100)
    for name in ("traj.png", "map.png", "ov/overlay_000001.png"):
        img = cv2.imread(str(tmp_path / name))
        assert img is not None and img.std() > 1


def _toy_result(with_gt: bool = True):
    """A hand-made SequenceResult (no pipeline run): a camera sliding along x over a plane at z = 2."""
    from cm3d.data.sequence import GroundTruth, Sequence
    from cm3d.pipeline import SequenceResult, WindowRecord

    S, H, W = 4, 16, 20
    K = np.broadcast_to(np.array([[20.0, 0, 9.5], [0, 20.0, 7.5], [0, 0, 1]]), (S, 3, 3)).copy()
    poses = np.tile(np.eye(4), (S, 1, 1))
    poses[:, 0, 3] = 0.1 * np.arange(S)
    depth = np.full((S, H, W), 2.0, np.float32)
    images = np.random.default_rng(0).integers(0, 256, (S, H, W, 3)).astype(np.uint8)
    masks = np.zeros((S, H, W), bool)
    masks[:, 4:8, 4:8] = True
    gt = GroundTruth(cam_to_world=poses, depth=depth, intrinsic=K, dynamic_mask=masks) if with_gt else None
    seq = Sequence(images=images, depth=depth, depth_conf=np.ones((S, H, W), np.float32), intrinsic=K,
                   cam_to_world=poses, timestamps=np.arange(S) * 0.1, gt=gt)
    noisy = poses.copy()
    noisy[:, 1, 3] += 0.01 * np.array([0.0, 1.0, -1.0, 0.5])
    win = WindowRecord(frames=(0, 3), memory=True, candidates=(), votes=(), scores=(), keypoint_inliers=(),
                       accepted=False, recalled_map=-1, inlier_count=0, rmse=0.0, fitness=0.0, scale=1.0,
                       transform=np.eye(4), placement=np.eye(4), map_id=0, created_map=True, refined=True,
                       gate_stat=1.0, gate_threshold=0.5, landmarks=3, memory_landmarks=0, memory_used=False,
                       memory_stat=0.0, memory_threshold=0.0, inconsistent_tracks=0, observations=9, inliers=9,
                       lm_iterations=2)
    return SequenceResult(poses=poses, prior=noisy, masks=masks, windows=[win], sequence=seq)


def test_static_map_skips_dynamic_pixels_and_lifts_with_poses():
    res = _toy_result()
    pts, cols = outputs.static_map(res.sequence, res.poses, res.masks, stride=1)
    assert len(pts) > 0 and cols.dtype == np.uint8 and pts.shape == cols.shape
    np.testing.assert_allclose(pts[:, 2], 2.0, atol=1e-5)  # the plane z = 2 in the world
    everything = np.ones_like(res.masks)
    assert len(outputs.static_map(res.sequence, res.poses, everything)[0]) == 0
    # the voxel means against a dict of voxels, in the rows' lexicographic order (np.unique(axis=0)'s)
    seq = res.sequence
    rng = np.random.default_rng(0)
    depth = np.asarray(seq.depth) * rng.uniform(0.5, 3.0, np.shape(seq.depth))
    seq = dataclasses.replace(seq, depth=depth)
    pts, cols = outputs.static_map(seq, res.poses, res.masks, stride=1, voxel_ratio=7.0)
    d, keep = np.asarray(seq.depth), ~np.asarray(res.masks) & (np.asarray(seq.depth_conf) >= np.quantile(
        np.asarray(seq.depth_conf)[~np.asarray(res.masks)], 0.3))
    S, H, W = d.shape
    v, u = np.mgrid[0:H, 0:W]
    K = np.asarray(seq.intrinsic, np.float64)
    K = K if K.ndim == 3 else np.broadcast_to(K, (S, 3, 3))
    lifted, colours = [], []
    for s in range(S):
        ray = np.linalg.solve(K[s], np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3).T).T
        cam = ray * d[s].reshape(-1, 1)
        world = cam @ np.asarray(res.poses[s], np.float64)[:3, :3].T + np.asarray(res.poses[s], np.float64)[:3, 3]
        lifted.append(world[keep[s].reshape(-1)])
        colours.append(np.asarray(seq.images[s]).reshape(-1, 3)[keep[s].reshape(-1)])
    lifted, colours = np.concatenate(lifted), np.concatenate(colours).astype(np.float64)
    vs = np.max(np.ptp(lifted, axis=0)) / 7.0
    voxels = {}
    for p, c, k in zip(lifted, colours, map(tuple, np.floor(lifted / vs).astype(np.int64))):
        voxels.setdefault(k, []).append((p, c))
    want = [np.mean([p for p, _ in voxels[k]], 0) for k in sorted(voxels)]
    np.testing.assert_allclose(pts, np.array(want), atol=1e-5)
    assert np.array_equal(cols, np.clip(np.round([np.mean([c for _, c in voxels[k]], 0) for k in sorted(voxels)]),
                                         0, 255).astype(np.uint8))


def test_write_results_writes_every_file(tmp_path):
    import json

    m = outputs.write_results(tmp_path / "o", _toy_result(), bank=None, overlay_every=2)
    o = tmp_path / "o"
    for name in ("trajectory.txt", "trajectory_prior.txt", "static_map.ply", "recall.json", "metrics.json",
                 "trajectory.png", "topdown_map.png"):
        assert (o / name).is_file(), name
    assert len(list((o / "masks").glob("*.png"))) == 4 and len(list((o / "overlays").glob("*.png"))) == 2
    assert m["refined"]["ate"] < 1e-6 < m["prior"]["ate"] and m["mask"]["iou"] == 1.0
    assert json.loads((o / "recall.json").read_text())["windows"][0]["created_map"]
    outputs.write_results(tmp_path / "n", _toy_result(with_gt=False), pictures=False)
    assert not (tmp_path / "n" / "metrics.json").exists() and (tmp_path / "n" / "trajectory.txt").exists()
