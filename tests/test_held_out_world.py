"""The held-out world renders what its docstring promises (never tune cm3d on it)."""

import numpy as np
import pytest

from cm3d.data import held_out_world as hw
from cm3d.data import io

CFG = hw.HeldOutConfig(height=48, width=64)


@pytest.fixture(scope="module")
def visits():
    return [hw.generate(0, v, 12, "moderate", CFG) for v in (0, 1)]


def test_visits_are_valid_sequences_with_ground_truth(visits):
    for seq in visits:
        io.validate_sequence(seq)
        assert seq.images.shape == (12, 48, 64, 3)
        assert (seq.gt.depth > 0).all(), "the hall is closed: every ray hits"
        assert seq.gt.dynamic_mask.any(axis=(1, 2)).all(), "a mover is in view on every frame"
    assert [s.meta["path"] for s in visits] == ["parallax", "rotation"]


def test_camera_paths_parallax_vs_rotation(visits):
    travel = [np.linalg.norm(s.gt.cam_to_world[-1, :3, 3] - s.gt.cam_to_world[0, :3, 3]) for s in visits]
    assert travel[0] > 1.0 and travel[1] < 0.05


def test_movers_enter_and_leave_and_light_changes():
    hall = hw.make_hall(1)
    _, poses = hw.movers(hall, 0, 20, CFG)
    cross = poses[:, 0, :3, 3]
    assert np.linalg.norm(cross[-1] - cross[0]) > 2.5, "the crosser traverses the view"
    slow = poses[:, 1, :3, 3]
    assert np.linalg.norm(slow[-1] - slow[0]) < 0.1, "the slow mover moves a few centimetres"
    spin = poses[:, 2]
    np.testing.assert_allclose(spin[:, :3, 3], np.broadcast_to(spin[0, :3, 3], (20, 3)))
    assert not np.allclose(spin[0, :3, :3], spin[-1, :3, :3]), "the sphere rotates in place"
    a, b = hw.lighting(1, 0), hw.lighting(1, 1)
    assert not np.allclose(a.direction, b.direction)


def test_seeded():
    a = hw.render_visit(hw.make_hall(2), 0, 2, CFG)
    b = hw.render_visit(hw.make_hall(2), 0, 2, CFG)
    np.testing.assert_array_equal(a[0], b[0])
    c = hw.render_visit(hw.make_hall(3), 0, 2, CFG)
    assert not np.array_equal(a[0], c[0])
