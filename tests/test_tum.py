import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cm3d.data.tum import quat_to_rotation, read_tum, rotation_to_quat, write_tum


def _random_traj(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    ts = 1311868164.0 + np.cumsum(rng.uniform(0.01, 0.05, n))
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    T[:, :3, 3] = rng.normal(size=(n, 3))
    return ts, T


def test_quaternion_convention_matches_scipy():
    q = Rotation.random(50, random_state=1).as_quat()  # scipy: (x, y, z, w), Hamilton
    R = quat_to_rotation(q * 3.0)  # normalised inside
    np.testing.assert_allclose(R, Rotation.from_quat(q).as_matrix(), atol=1e-14)
    q2 = rotation_to_quat(R)
    q_canon = np.where(q[:, 3:4] < 0, -q, q)
    np.testing.assert_allclose(q2, q_canon, atol=1e-12)
    assert np.all(q2[:, 3] >= 0)
    # 180-degree rotations (qw = 0) and the identity.
    for rq in ([1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]):
        np.testing.assert_allclose(
            quat_to_rotation(rotation_to_quat(quat_to_rotation(np.array(rq)))),
            quat_to_rotation(np.array(rq)),
            atol=1e-14,
        )


def test_round_trip_exact(tmp_path):
    ts, T = _random_traj(30)
    path = tmp_path / "sub" / "traj.txt"
    write_tum(path, ts, T)
    ts2, T2 = read_tum(path)
    assert ts2.dtype == np.float64 and T2.dtype == np.float64 and T2.shape == (30, 4, 4)
    np.testing.assert_array_equal(ts2, ts)  # repr formatting: bit-exact
    np.testing.assert_array_equal(T2[:, :3, 3], T[:, :3, 3])
    np.testing.assert_allclose(T2, T, atol=1e-9, rtol=0)
    assert not list(path.parent.glob(".*.tmp"))  # atomic write left nothing behind


def test_evo_reads_what_we_write(tmp_path):
    from evo.tools.file_interface import read_tum_trajectory_file

    ts, T = _random_traj(20, seed=3)
    path = tmp_path / "t.txt"
    write_tum(path, ts, T)
    traj = read_tum_trajectory_file(str(path))
    np.testing.assert_array_equal(traj.timestamps, ts)
    np.testing.assert_allclose(np.stack(traj.poses_se3), T, atol=1e-12)


def test_matches_evo_reader(shared_data):
    from evo.tools.file_interface import read_tum_trajectory_file

    for name in ("freiburg1_xyz-groundtruth.txt", "fr2_desk_ORB.txt"):
        path = shared_data / "evo_tum_traj" / name
        ts, T = read_tum(path)
        traj = read_tum_trajectory_file(str(path))
        np.testing.assert_array_equal(ts, traj.timestamps)
        np.testing.assert_allclose(T, np.stack(traj.poses_se3), atol=1e-12)


def test_separators_comments_blank_lines(tmp_path):
    path = tmp_path / "t.txt"
    path.write_text(
        "# header\n\n"
        "1.0 0 0 0 0 0 0 1\n"
        "2.0,1,2,3, 0, 0, 0, 2   # trailing comment, unnormalised quaternion\n"
        "   \n"
        "3.0\t1\t2\t3\t0\t0\t1\t0\n"
    )
    ts, T = read_tum(path)
    np.testing.assert_array_equal(ts, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(T[1, :3, 3], [1, 2, 3])
    np.testing.assert_allclose(T[1, :3, :3], np.eye(3), atol=1e-15)
    np.testing.assert_allclose(T[2, :3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-15)


def test_empty_file(tmp_path):
    path = tmp_path / "e.txt"
    path.write_text("# nothing\n")
    ts, T = read_tum(path)
    assert ts.shape == (0,) and T.shape == (0, 4, 4)


@pytest.mark.parametrize(
    "line, what",
    [
        ("1.0 0 0 0 0 0 1", "8 values"),
        ("1.0 0 0 0 0 0 0 1 5", "8 values"),
        ("1.0 0 0 abc 0 0 0 1", "non-numeric"),
        ("1.0 0 nan 0 0 0 0 1", "NaN"),
        ("1.0 0 0 0 0 0 0 inf", "NaN or infinite"),
        ("1.0 0 0 0 0 0 0 0", "zero quaternion"),
    ],
)
def test_bad_lines_raise(tmp_path, line, what):
    path = tmp_path / "bad.txt"
    path.write_text("# c\n1.0 0 0 0 0 0 0 1\n\n" + line + "\n")
    with pytest.raises(ValueError) as err:
        read_tum(path)
    msg = str(err.value)
    assert f"{path}:4:" in msg and what in msg


def test_write_rejects_bad_input(tmp_path):
    ts, T = _random_traj(3)
    with pytest.raises(ValueError):
        write_tum(tmp_path / "a.txt", ts[:2], T)
    T[1, 0, 3] = np.nan
    with pytest.raises(ValueError, match="index 1"):
        write_tum(tmp_path / "a.txt", ts, T)
    assert not (tmp_path / "a.txt").exists()
