"""Input formats: Sintel/Middlebury .flo, .dpt, .cam, KITTI flow PNG, TUM RGB-D folders."""

import shutil

import cv2
import numpy as np
import pytest

from cm3d.data import sintel, synthetic, tum_rgbd
from cm3d.data.tum import write_tum
from cm3d.eval import metrics


def test_read_real_middlebury_flo(shared_data):
    flow, valid = sintel.read_flo(shared_data / "flow_samples" / "middlebury_flow_gt.flo")
    assert flow.shape == (388, 584, 2) and flow.dtype == np.float32
    assert 0.5 < valid.mean() < 1.0  # the file marks occluded pixels as unknown (> 1e9)
    assert np.all(np.isfinite(flow)) and np.abs(flow[valid]).max() < 100


def test_flo_dpt_cam_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    flow = rng.normal(size=(5, 7, 2)).astype(np.float32)
    sintel.write_flo(tmp_path / "a.flo", flow)
    back, valid = sintel.read_flo(tmp_path / "a.flo")
    np.testing.assert_array_equal(back, flow)
    assert valid.all()
    depth = rng.uniform(1, 9, size=(4, 6)).astype(np.float32)
    sintel.write_dpt(tmp_path / "a.dpt", depth)
    np.testing.assert_array_equal(sintel.read_dpt(tmp_path / "a.dpt"), depth)
    K, E = np.array([[400.0, 0, 3], [0, 410, 2], [0, 0, 1]]), rng.normal(size=(3, 4))
    sintel.write_cam(tmp_path / "a.cam", K, E)
    K2, E2 = sintel.read_cam(tmp_path / "a.cam")
    np.testing.assert_array_equal(K2, K)
    np.testing.assert_array_equal(E2, E)


def test_bad_sintel_files_are_clear_errors(tmp_path):
    (tmp_path / "bad.flo").write_bytes(b"XXXX" + b"\0" * 20)
    with pytest.raises(ValueError, match="bad tag"):
        sintel.read_flo(tmp_path / "bad.flo")
    sintel.write_flo(tmp_path / "t.flo", np.zeros((3, 3, 2)))
    (tmp_path / "t.flo").write_bytes((tmp_path / "t.flo").read_bytes()[:-4])
    with pytest.raises(ValueError, match="expected .* bytes"):
        sintel.read_flo(tmp_path / "t.flo")
    with pytest.raises(ValueError, match="cam"):
        sintel.write_cam(tmp_path / "c.cam", np.eye(3), np.eye(3))


def test_read_real_kitti_flow_png(shared_data):
    flow, valid = sintel.read_kitti_flow(shared_data / "flow_samples" / "kitti_flow_gt.png")
    assert flow.shape == (375, 1242, 2)
    assert 0.05 < valid.mean() < 0.9 and np.abs(flow[valid]).max() < 512
    assert np.all(flow[~valid] == 0)


def test_tum_rgbd_folder_with_open3d_odometry_prior(tmp_path):
    cfg = synthetic.WorldConfig(height=120, width=160, num_moving=0)
    seq = synthetic.generate(4, 0, 6, "none", cfg)
    tum_rgbd.write_tum_rgbd(tmp_path / "rgbd_dataset_synthetic", seq)
    got = tum_rgbd.load_tum_rgbd(tmp_path / "rgbd_dataset_synthetic")
    assert got.num_frames == 6 and got.gt is not None
    np.testing.assert_array_equal(got.images, seq.images)
    np.testing.assert_allclose(got.depth, seq.gt.depth, atol=1.0 / 5000)
    np.testing.assert_allclose(got.gt.cam_to_world, seq.gt.cam_to_world, atol=1e-6)
    np.testing.assert_allclose(got.cam_to_world[0], np.eye(4))
    m = metrics.evaluate_trajectories(got.timestamps, got.gt.cam_to_world, got.timestamps, got.cam_to_world)
    travel = np.linalg.norm(seq.gt.cam_to_world[-1, :3, 3] - seq.gt.cam_to_world[0, :3, 3])
    assert got.meta["odometry_failures"] == 0
    # a metric prior: SE(3) alignment suffices, and the error is a small part of the motion
    assert m["ate_se3"] < 0.01 and m["ate_se3"] < 0.2 * travel and m["rpe_rot"] < 0.2, m


def test_tum_rgbd_real_pair_uses_freiburg2_calibration(tmp_path, shared_data):
    src = shared_data / "tum_fr2_pair"
    folder = tmp_path / "rgbd_dataset_freiburg2_pair"
    folder.mkdir()
    for name in ("1.png", "2.png", "1_depth.png", "2_depth.png"):
        shutil.copy(src / name, folder / name)
    (folder / "rgb.txt").write_text("1.000 1.png\n1.033 2.png\n")
    (folder / "depth.txt").write_text("1.001 1_depth.png\n1.034 2_depth.png\n")
    seq = tum_rgbd.load_tum_rgbd(folder)
    assert seq.images.shape == (2, 480, 640, 3) and seq.gt is None
    np.testing.assert_allclose(seq.intrinsic[0, 0, 0], 520.9)
    assert 0.3 < (seq.depth > 0).mean() <= 1.0 and seq.depth.max() < 13.2  # uint16 / 5000
    T = seq.cam_to_world[1]
    np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-6)
    assert np.linalg.norm(T[:3, 3]) < 0.5  # two nearby real frames: a small, finite motion


def test_tum_rgbd_bad_folders(tmp_path):
    with pytest.raises(ValueError, match="rgb.txt missing"):
        tum_rgbd.load_tum_rgbd(tmp_path)
    (tmp_path / "rgb.txt").write_text("1.0 a.png\n")
    (tmp_path / "depth.txt").write_text("5.0 b.png\n")
    with pytest.raises(ValueError, match="fewer than 2"):
        tum_rgbd.load_tum_rgbd(tmp_path)
    (tmp_path / "depth.txt").write_text("x b.png\n")
    with pytest.raises(ValueError, match="depth.txt:1: bad timestamp"):
        tum_rgbd.load_tum_rgbd(tmp_path)


def test_load_input_dispatches_every_format(tmp_path):
    from cm3d.data import io, loaders

    seq = synthetic.generate(6, 0, 3, "slight", synthetic.WorldConfig(height=48, width=64))
    io.save_sequence(tmp_path / "s.npz", seq)
    np.testing.assert_array_equal(loaders.load_input(tmp_path / "s.npz").images, seq.images)

    folder = tmp_path / "folder"
    (folder / "images").mkdir(parents=True)
    for i, im in enumerate(seq.images):
        cv2.imwrite(str(folder / f"images/{i:04d}.png"), cv2.cvtColor(im, cv2.COLOR_RGB2BGR))
    np.savez(folder / "priors.npz", depth=seq.depth[..., None], intrinsic=seq.intrinsic,
             extrinsic=np.linalg.inv(seq.cam_to_world)[:, :3])
    got = loaders.load_input(folder)
    np.testing.assert_array_equal(got.images, seq.images)
    np.testing.assert_allclose(got.cam_to_world, seq.cam_to_world, atol=1e-9)

    tum_rgbd.write_tum_rgbd(tmp_path / "tum", seq)
    assert loaders.load_input(tmp_path / "tum").meta["source"] == "tum_rgbd"

    with pytest.raises(FileNotFoundError):
        loaders.load_input(tmp_path / "missing")
    (tmp_path / "x.txt").write_text("")
    with pytest.raises(ValueError, match="unsupported file type"):
        loaders.load_input(tmp_path / "x.txt")
    with pytest.raises(ValueError, match="not a recognised input folder"):
        loaders.load_input(tmp_path / "tum" / "rgb")
    (folder / "priors.npz").unlink()
    with pytest.raises(ValueError, match="priors.npz missing"):
        loaders.load_input(folder)
