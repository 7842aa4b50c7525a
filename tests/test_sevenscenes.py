"""7-Scenes folders (real redkitchen frames, holes included), DAVIS folders, and bad folders."""

import shutil

import numpy as np
import pytest

from cm3d.data import davis, io, priors, sevenscenes


@pytest.fixture(scope="module")
def kitchen(shared_data):
    return shared_data / "sevenscenes_redkitchen"


def test_loads_real_frames_with_holes(kitchen):
    seq = sevenscenes.load_sevenscenes(kitchen, "160:166")
    assert seq.num_frames == 3 and seq.image_size == (480, 640)
    assert seq.meta["frames"] == [160, 162, 164]
    np.testing.assert_array_equal(seq.timestamps, [160, 162, 164])
    holes = seq.depth == 0
    assert 0.01 < holes.mean() < 0.5, "real Kinect depth has holes"
    np.testing.assert_array_equal(seq.depth_conf == 0, holes)
    valid = seq.depth[~holes]
    assert 0.3 < np.median(valid) < 5.0, "metres"
    np.testing.assert_allclose(seq.intrinsic[0], [[585, 0, 320], [0, 585, 240], [0, 0, 1]])
    T = sevenscenes.read_pose(kitchen / "frame-000160.pose.txt")
    np.testing.assert_allclose(seq.gt.cam_to_world[0], T)
    np.testing.assert_allclose(seq.cam_to_world, seq.gt.cam_to_world)
    io.validate_sequence(seq)  # holes (depth 0, confidence 0) are valid input


def test_frames_spec_and_resize(kitchen):
    assert sevenscenes.frame_numbers(kitchen, "390:470:2") == [390, 394, 398, 462, 466]
    assert sevenscenes.frame_numbers(kitchen, ":104")[-1] == 102
    assert sevenscenes.parse_frames("::3") == (None, None, 3)
    for bad in ("a:b", "1:2:0", "5:3", "1:2:3:4"):
        with pytest.raises(ValueError, match="--frames"):
            sevenscenes.parse_frames(bad)
    with pytest.raises(ValueError, match="selects none"):
        sevenscenes.frame_numbers(kitchen, "2000:3000")
    seq = sevenscenes.load_sevenscenes(kitchen, "160:162", resize=0.5)
    assert seq.image_size == (240, 320)
    np.testing.assert_allclose(seq.intrinsic[0], [[292.5, 0, 159.75], [0, 292.5, 119.75], [0, 0, 1]])


def _plane_depth(K, n, d, shape):
    """Depth (H, W) of the plane n.x = d seen by a camera with intrinsics K at the origin."""
    v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    ray = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    return d / (ray @ n)


def test_depth_registered_into_a_colour_camera_sees_the_same_surface():
    """A tilted plane seen by a depth camera (f 585) and a colour camera beside it (f 525, 2.5 cm to
    the side, turned 1 degree): the registered depth equals the plane's depth in the colour camera
    (nearest splat: within the depth change across a pixel), lift_colour_pixels lands on the plane, and
    a colour camera equal to the depth camera gives the depth back unchanged."""
    shape = (120, 160)
    Kd = np.array([[146.25, 0, 79.75], [0, 146.25, 59.75], [0, 0, 1.0]])
    n_d = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    depth = _plane_depth(Kd, n_d, 2.0, shape).astype(np.float32)
    depth[50:60, 70:90] = 0.0  # a hole
    cam = sevenscenes.ColourCamera(f=131.25, cx=79.5, cy=59.5, rotvec=(0.0, np.radians(1.0), 0.0),
                                   translation=(-0.025, 0.0, 0.0))
    T = cam.depth_to_colour()
    n_c = T[:3, :3] @ n_d  # the plane in colour coordinates: n_c.x = 2 + n_c.t
    truth = _plane_depth(cam.K(), n_c, 2.0 + n_c @ T[:3, 3], shape)
    reg = sevenscenes.register_depth(depth, Kd, cam)
    seen = reg > 0
    assert 0.7 < seen.mean() < 0.9  # the colour camera's wider view reaches past the depth camera's
    assert not seen[53:57, 76:84].any()  # the hole stays a hole
    np.testing.assert_allclose(reg[seen], truth[seen], rtol=0.01)
    v, u = np.nonzero(seen)
    X, ok = sevenscenes.lift_colour_pixels(np.c_[u, v], depth, Kd, cam)
    assert ok.mean() > 0.95
    np.testing.assert_allclose(X[ok, 2], truth[v[ok], u[ok]], rtol=1e-3)  # bilinear on a plane: exact
    same = sevenscenes.ColourCamera(f=146.25, cx=79.75, cy=59.75)
    np.testing.assert_allclose(sevenscenes.register_depth(depth, Kd, same), depth, rtol=1e-6)


def test_the_colour_camera_loads_its_k_registered_depth_and_poses(kitchen):
    seq = sevenscenes.load_sevenscenes(kitchen, "160:162", resize=0.5, colour=sevenscenes.KINECT_COLOUR)
    plain = sevenscenes.load_sevenscenes(kitchen, "160:162", resize=0.5)
    np.testing.assert_allclose(seq.intrinsic[0], [[262.5, 0, 159.5], [0, 262.5, 119.5], [0, 0, 1]])
    np.testing.assert_array_equal(seq.images, plain.images)
    # the poses are the colour camera's: 2.5 cm along the depth camera's x axis (x_d = x_c - t), same rotation
    np.testing.assert_allclose(seq.gt.cam_to_world[:, :3, :3], plain.gt.cam_to_world[:, :3, :3])
    centre = plain.gt.cam_to_world[:, :3, :3] @ [0.025, 0, 0] + plain.gt.cam_to_world[:, :3, 3]
    np.testing.assert_allclose(seq.gt.cam_to_world[:, :3, 3], centre, atol=1e-9)  # T_wc = T_wd T_cd^-1
    np.testing.assert_allclose(seq.cam_to_world, seq.gt.cam_to_world)
    # the colour camera sees wider: its border has no depth, its centre the same surface
    assert (seq.depth[:, :, :8] == 0).all() and (seq.depth[:, :, -8:] == 0).all()
    c = (slice(100, 140), slice(140, 180))
    ratio = np.median(seq.depth[0][c][seq.depth[0][c] > 0]) / np.median(plain.depth[0][c][plain.depth[0][c] > 0])
    assert 0.97 < ratio < 1.03
    np.testing.assert_array_equal(seq.depth_conf == 0, seq.depth == 0)
    assert seq.meta["colour_camera"]["f"] == 525.0
    io.validate_sequence(seq)


def test_priors_from_real_frames_keep_holes(kitchen):
    seq = sevenscenes.load_sevenscenes(kitchen, "160:180", resize=0.25)
    p = priors.priors_for(seq, "moderate", seed=3)
    holes = seq.depth == 0
    assert (p.depth[holes] == 0).all() and (p.depth_conf[holes] == 0).all()
    assert (p.depth_conf[~holes] >= 1).all()
    np.testing.assert_allclose(p.cam_to_world[0], np.eye(4), atol=1e-12)
    io.validate_sequence(p)


def _copy(kitchen, tmp_path, frames=(160, 162)):
    d = tmp_path / "seq"
    d.mkdir()
    shutil.copy(kitchen / "camera-intrinsics.txt", d)
    for n in frames:
        for kind in ("color.jpg", "depth.png", "pose.txt"):
            shutil.copy(kitchen / f"frame-{n:06d}.{kind}", d)
    return d


def test_bad_folders(kitchen, tmp_path):
    d = _copy(kitchen, tmp_path)
    (d / "camera-intrinsics.txt").unlink()
    with pytest.raises(ValueError, match="camera-intrinsics.txt missing"):
        sevenscenes.load_sevenscenes(d)
    shutil.copy(kitchen / "camera-intrinsics.txt", d)
    (d / "frame-000162.depth.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="frame-000162.depth.png: unreadable depth"):
        sevenscenes.load_sevenscenes(d)
    shutil.copy(kitchen / "frame-000162.depth.png", d)
    (d / "frame-000162.pose.txt").unlink()
    seq = sevenscenes.load_sevenscenes(d)  # without --prior-noise a missing pose is allowed
    assert seq.gt is None
    with pytest.raises(ValueError, match="frame 162: frame-000162.pose.txt missing"):
        sevenscenes.load_sevenscenes(d, require_poses=True)
    with pytest.raises(ValueError, match="ground-truth poses"):
        priors.priors_for(seq, "moderate")
    with pytest.raises(ValueError, match="not a 7-Scenes folder"):
        sevenscenes.frame_numbers(tmp_path)


def test_frame_without_any_depth_is_named(kitchen, tmp_path):
    import cv2

    d = _copy(kitchen, tmp_path)
    cv2.imwrite(str(d / "frame-000162.depth.png"), np.zeros((480, 640), np.uint16))
    with pytest.raises(ValueError, match="frame 162 has no usable depth"):
        sevenscenes.load_sevenscenes(d)


def test_davis_frames(shared_data):
    images, masks = davis.load_davis(shared_data / "davis2016" / "blackswan", resize=0.25, max_frames=3)
    assert images.shape == (3, 120, 214, 3) and images.dtype == np.uint8
    assert masks.shape == (3, 120, 214) and masks.dtype == bool
    assert 0.02 < masks.mean() < 0.5, "a foreground object on every frame"
    with pytest.raises(ValueError, match="DAVIS layout"):
        davis.load_davis(shared_data / "davis2016")


def test_holes_round_trip_through_npz(kitchen, tmp_path):
    seq = priors.priors_for(sevenscenes.load_sevenscenes(kitchen, "160:164", resize=0.25), "slight", seed=0)
    io.save_sequence(tmp_path / "k.npz", seq)
    back = io.load_sequence(tmp_path / "k.npz")
    np.testing.assert_array_equal(back.depth, seq.depth)
    np.testing.assert_array_equal(back.depth_conf == 0, seq.depth == 0)
    np.testing.assert_array_equal(back.gt.depth, seq.gt.depth)


def _cli_error(args, capsys):
    from cm3d import cli

    rc = cli.main(args)
    err = capsys.readouterr().err.strip()
    return rc, err


def test_cli_bad_folders_exit_2_with_one_line(kitchen, tmp_path, capsys):
    d = _copy(kitchen, tmp_path)
    out = str(tmp_path / "out")
    (d / "camera-intrinsics.txt").unlink()
    rc, err = _cli_error(["run", str(d), "--out", out], capsys)
    assert rc == 2 and len(err.splitlines()) == 1 and "camera-intrinsics.txt missing" in err
    shutil.copy(kitchen / "camera-intrinsics.txt", d)
    (d / "frame-000160.depth.png").write_bytes(b"garbage")
    rc, err = _cli_error(["run", str(d), "--out", out], capsys)
    assert rc == 2 and len(err.splitlines()) == 1 and "unreadable depth" in err
    shutil.copy(kitchen / "frame-000160.depth.png", d)
    (d / "frame-000162.pose.txt").unlink()
    rc, err = _cli_error(["run", str(d), "--out", out, "--prior-noise", "moderate", "--seed", "1"], capsys)
    assert rc == 2 and len(err.splitlines()) == 1 and "frame-000162.pose.txt missing" in err
    rc, err = _cli_error(["run", str(d), "--out", out, "--frames", "500:600"], capsys)
    assert rc == 2 and "selects none" in err


def test_load_input_dispatches_sevenscenes(kitchen):
    from cm3d.data.loaders import load_input

    seq = load_input(kitchen, frames="160:170:2", require_poses=True)
    assert seq.meta["source"] == "sevenscenes" and seq.meta["frames"] == [160, 164, 168]


def test_cli_reads_a_sevenscenes_folder_with_the_colour_camera(kitchen, tmp_path, capsys):
    from cm3d import cli

    seq, _ = cli._load_inputs([kitchen], "160:164", camera="kinect")
    np.testing.assert_allclose(seq.intrinsic[0], sevenscenes.KINECT_COLOUR.K())
    assert tuple(seq.meta["colour_camera"]["translation"]) == (-0.025, 0.0, 0.0)
    npz = tmp_path / "seq.npz"
    io.save_sequence(npz, seq)
    rc, err = _cli_error(["run", str(npz), "--out", str(tmp_path / "o"), "--colour-camera", "kinect"], capsys)
    assert rc == 2 and len(err.splitlines()) == 1 and "only for 7-Scenes folders" in err
