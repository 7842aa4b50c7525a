"""Output writers and pictures: readable by Open3D / OpenCV / evo, atomic, clear errors."""

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
