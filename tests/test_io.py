"""Sequence .npz files: round trip, VGGT predictions dicts, one test per format error, atomic writes."""

import json
import os
import re
from pathlib import Path

import numpy as np
import pytest

from cm3d.data import io
from cm3d.data.io import SequenceFormatError, load_sequence, save_sequence, validate_sequence
from cm3d.data.sequence import GroundTruth, Sequence

S, H, W = 3, 8, 10
ROOT = Path(__file__).resolve().parents[1]


def rot_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def poses() -> np.ndarray:
    """cam_to_world (S, 4, 4) float64 with awkward digits, so a lossy round trip would show."""
    T = np.tile(np.eye(4), (S, 1, 1))
    for i in range(S):
        T[i, :3, :3] = rot_z(17.3 * i + 0.1)
        T[i, :3, 3] = [0.1 * i + 1 / 3, -2 / 7, np.pi * i]
    return T


def make_seq(gt: bool = True) -> Sequence:
    rng = np.random.default_rng(0)
    K = np.tile(np.array([[12.0, 0.0, 5.0], [0.0, 11.0, 4.0], [0.0, 0.0, 1.0]]), (S, 1, 1))
    depth = rng.uniform(0.5, 3.0, (S, H, W)).astype(np.float32)
    truth = None
    if gt:
        truth = GroundTruth(
            cam_to_world=poses()[::-1].copy(),
            depth=2 * depth,
            intrinsic=K.copy(),
            dynamic_mask=rng.uniform(size=(S, H, W)) > 0.7,
            flow=rng.normal(size=(S - 1, H, W, 2)).astype(np.float32),
        )
    return Sequence(
        images=rng.integers(0, 256, (S, H, W, 3), dtype=np.uint8),
        depth=depth,
        depth_conf=rng.uniform(0.0, 5.0, (S, H, W)).astype(np.float32),
        intrinsic=K,
        cam_to_world=poses(),
        timestamps=np.array([0.0, 0.033, 0.0667]),
        world_points=rng.normal(size=(S, H, W, 3)).astype(np.float32),
        gt=truth,
        meta={"scene": "toy", "noise": 0.5, "tags": ["a", "é"]},
    )


def file_dict(seq: Sequence) -> dict:
    """The arrays save_sequence writes, to mutate into bad files."""
    d = {
        "images": seq.images, "depth": seq.depth, "depth_conf": seq.depth_conf,
        "extrinsic": io._rigid_inverse(seq.cam_to_world)[:, :3], "intrinsic": seq.intrinsic,
        "timestamps": seq.timestamps, "world_points": seq.world_points,
        "gt_cam_to_world": seq.gt.cam_to_world, "gt_depth": seq.gt.depth, "gt_flow": seq.gt.flow,
        "meta_json": np.array(json.dumps(seq.meta)),
    }  # fmt: skip
    return {k: v.copy() for k, v in d.items()}


def assert_seq_equal(a: Sequence, b: Sequence) -> None:
    for name in ("images", "depth", "depth_conf", "intrinsic", "cam_to_world", "timestamps", "world_points"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype, name
        np.testing.assert_array_equal(x, y, err_msg=name)
    for name in ("cam_to_world", "depth", "intrinsic", "dynamic_mask", "flow"):
        x, y = getattr(a.gt, name), getattr(b.gt, name)
        assert x.dtype == y.dtype, name
        np.testing.assert_array_equal(x, y, err_msg=f"gt.{name}")
    assert a.meta == b.meta


@pytest.mark.parametrize("compress", [False, True])
def test_round_trip_is_exact(tmp_path, compress):
    seq = make_seq()
    path = tmp_path / "seq.npz"
    save_sequence(path, seq, compress=compress)
    back = load_sequence(path)
    assert_seq_equal(seq, back)
    assert back.cam_to_world.dtype == np.float64
    with np.load(path, allow_pickle=False) as z:  # every key readable without pickle
        arrays = {k: z[k] for k in z.files}
    assert all(a.dtype != object for a in arrays.values())
    assert arrays["extrinsic"].shape == (S, 3, 4) and arrays["meta_json"].ndim == 0
    E, centre = arrays["extrinsic"], seq.cam_to_world[:, :3, 3, None]
    np.testing.assert_allclose(E[:, :, :3] @ centre + E[:, :, 3:], 0.0, atol=1e-12)  # camera centre -> origin


def test_sequence_from_arrays_copies_unless_asked_not_to():
    arrays = io.sequence_arrays(make_seq())
    seq = io.sequence_from_arrays(arrays)
    before = seq.depth.copy()
    arrays["depth"] += 1.0  # the caller's arrays change afterwards: the sequence does not
    np.testing.assert_array_equal(seq.depth, before)
    shared = io.sequence_from_arrays(arrays, copy=False)  # what load_sequence does with the arrays it read
    assert np.shares_memory(shared.depth, arrays["depth"])
    np.testing.assert_array_equal(shared.depth, before + 1.0)


def test_without_ground_truth_or_optionals(tmp_path):
    seq = make_seq(gt=False).replace(world_points=None, meta={})
    save_sequence(tmp_path / "s.npz", seq)
    back = load_sequence(tmp_path / "s.npz")
    assert back.gt is None and back.world_points is None and back.meta == {}


def vggt_dict(extrinsic: np.ndarray) -> dict:
    """A VGGT predictions dict as saved by its demo: batch axis, float [S, 3, H, W] images, [S, H, W, 1] depth."""
    rng = np.random.default_rng(1)
    K = np.tile(np.array([[12.0, 0.0, 5.0], [0.0, 11.0, 4.0], [0.0, 0.0, 1.0]], np.float32), (S, 1, 1))
    return {
        "images": rng.uniform(size=(S, 3, H, W)).astype(np.float32)[None],
        "depth": rng.uniform(0.5, 2.0, (S, H, W, 1)).astype(np.float32)[None],
        "depth_conf": rng.uniform(1.0, 3.0, (S, H, W)).astype(np.float32)[None],
        "extrinsic": extrinsic.astype(np.float32)[None],
        "intrinsic": K[None],
        "world_points": rng.normal(size=(S, H, W, 3)).astype(np.float32)[None],
        "world_points_conf": np.ones((1, S, H, W), np.float32),
        "pose_enc": rng.normal(size=(1, S, 9)).astype(np.float32),
        "images_path": np.array([f"frame_{i}.png" for i in range(S)]),
    }


def known_extrinsic() -> np.ndarray:
    E = np.zeros((S, 3, 4))
    E[:, :3, :3] = np.eye(3)
    E[1, :3, :3] = rot_z(90.0)  # [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    E[1, :3, 3] = [1.0, 2.0, 3.0]
    E[2, :3, 3] = [0.0, 0.0, -1.0]
    return E


def test_vggt_predictions_dict(tmp_path):
    d = vggt_dict(known_extrinsic())
    np.savez(tmp_path / "pred.npz", **d)
    seq = load_sequence(tmp_path / "pred.npz")
    assert seq.images.shape == (S, H, W, 3) and seq.images.dtype == np.uint8
    assert seq.depth.shape == (S, H, W) and seq.depth_conf.shape == (S, H, W)
    assert seq.world_points.shape == (S, H, W, 3) and seq.intrinsic.shape == (S, 3, 3)
    assert seq.cam_to_world.shape == (S, 4, 4) and seq.cam_to_world.dtype == np.float64
    np.testing.assert_array_equal(seq.timestamps, [0.0, 1.0, 2.0])
    assert seq.gt is None and seq.meta == {}
    # channels-first floats -> channels-last uint8, same pixel
    assert seq.images[1, 2, 3, 0] == round(float(d["images"][0, 1, 0, 2, 3]) * 255)
    assert seq.images[1, 2, 3, 2] == round(float(d["images"][0, 1, 2, 2, 3]) * 255)
    # world-to-camera [R | t] -> cam_to_world [R^T | -R^T t], by hand for frame 1
    want = np.array([[0.0, 1.0, 0.0, -2.0], [-1.0, 0.0, 0.0, 1.0], [0.0, 0.0, 1.0, -3.0], [0.0, 0.0, 0.0, 1.0]])
    np.testing.assert_allclose(seq.cam_to_world[1], want, atol=1e-6)
    np.testing.assert_allclose(seq.cam_to_world[2, :3, 3], [0.0, 0.0, 1.0], atol=1e-7)
    np.testing.assert_array_equal(seq.cam_to_world[0], np.eye(4))


@pytest.mark.parametrize("variant", ["channels_last_float", "extrinsic_4x4", "cam_to_world_key", "unbatched"])
def test_vggt_variants(tmp_path, variant):
    E = known_extrinsic()
    d = vggt_dict(E)
    if variant == "channels_last_float":
        d["images"] = d["images"].transpose(0, 1, 3, 4, 2)
    elif variant == "extrinsic_4x4":
        d["extrinsic"] = np.concatenate([d["extrinsic"], np.tile([0.0, 0.0, 0.0, 1.0], (1, S, 1, 1))], axis=2)
    elif variant == "cam_to_world_key":
        d["cam_to_world"] = io._rigid_inverse(E)[None]
        del d["extrinsic"]
    else:
        d = {k: (v[0] if k != "images_path" else v) for k, v in d.items()}
    np.savez(tmp_path / "pred.npz", **d)
    seq = load_sequence(tmp_path / "pred.npz")
    assert seq.images.shape == (S, H, W, 3) and seq.depth.shape == (S, H, W)
    np.testing.assert_allclose(seq.cam_to_world, io._rigid_inverse(E), atol=1e-6)


def _set(d, key, fn):
    d[key] = fn(d[key])


# (id, mutation of the file dict, key the message must name, other text it must contain)
BAD_FILES = [
    ("missing images", lambda d: d.pop("images"), "images", "missing"),
    ("missing depth", lambda d: d.pop("depth"), "depth", "missing"),
    ("missing intrinsic", lambda d: d.pop("intrinsic"), "intrinsic", "missing"),
    ("missing pose", lambda d: d.pop("extrinsic"), "extrinsic", "cam_to_world"),
    ("S mismatch", lambda d: _set(d, "depth_conf", lambda a: a[:2]), "depth_conf", "'images' shape (3, 8, 10, 3)"),
    ("W mismatch", lambda d: _set(d, "world_points", lambda a: a[:, :, :9]), "world_points", "(3, 8, 9, 3)"),
    ("image/depth size", lambda d: _set(d, "images", lambda a: a[:, :7]), "images", "'depth' shape (3, 8, 10)"),
    ("float image size", lambda d: _set(d, "images", lambda a: np.zeros((S, 3, 16, 20), np.float32)),
     "images", "'depth' shape (3, 8, 10)"),
    ("trailing shape", lambda d: _set(d, "world_points", lambda a: a[..., :2]), "world_points", "wrong shape"),
    ("extrinsic shape", lambda d: _set(d, "extrinsic", lambda a: a[:, :, :3]), "extrinsic", "(S, 3, 4)"),
    ("int depth", lambda d: _set(d, "depth", lambda a: (a * 10).astype(np.int32)), "depth", "not floating"),
    ("nan conf", lambda d: _set(d, "depth_conf", lambda a: np.where(np.arange(W) < 2, np.nan, a)),
     "depth_conf", "48 non-finite"),
    ("inf intrinsic", lambda d: _set(d, "intrinsic", lambda a: a + np.array([0, 0, np.inf])[:, None, None]),
     "intrinsic", "frame 2"),
    ("no positive depth", lambda d: _set(d, "depth", lambda a: a * (np.arange(S) != 1)[:, None, None]),
     "depth", "frame 1"),
    ("negative conf", lambda d: _set(d, "depth_conf", lambda a: a - 10 * (np.arange(S) == 2)[:, None, None]),
     "depth_conf", "frame 2"),
    ("zero fx", lambda d: d["intrinsic"].__setitem__((1, 0, 0), 0.0), "intrinsic", "frame 1"),
    ("singular K", lambda d: d["intrinsic"].__setitem__((2, 2, 2), 0.0), "intrinsic", "frame 2"),
    ("gt singular K", lambda d: d.update(gt_intrinsic=d["intrinsic"] * [1, -1, 1]), "gt_intrinsic", "frame 0"),
    ("scaled R", lambda d: d["extrinsic"].__setitem__((1, slice(None, 3), slice(None, 3)), 1.1 * np.eye(3)),
     "extrinsic", "frame 1"),
    ("reflection", lambda d: d["extrinsic"].__setitem__((2, 2, 2), -1.0), "extrinsic", "frame 2"),
    ("gt reflection", lambda d: d["gt_cam_to_world"].__setitem__((1, 0, 0), -d["gt_cam_to_world"][1, 0, 0]),
     "gt_cam_to_world", "frame 1"),
    ("gt_flow frames", lambda d: _set(d, "gt_flow", lambda a: np.concatenate([a, a[:1]])), "gt_flow", "S-1"),
    ("gt without depth", lambda d: d.pop("gt_depth"), "gt_depth", "missing"),
    ("gt without pose", lambda d: d.pop("gt_cam_to_world"), "gt_cam_to_world", "missing"),
    ("bad meta", lambda d: d.update(meta_json=np.array("{not json")), "meta_json", "JSON"),
    ("images range", lambda d: _set(d, "images", lambda a: a.astype(np.float32)), "images", "[0, 1]"),
    ("pose keys disagree", lambda d: d.update(cam_to_world=io._rigid_inverse(np.roll(d["extrinsic"], 1, 0))),
     "cam_to_world", "frame 0"),
    ("partial batch", lambda d: d.update({k: v[None] for k, v in d.items() if k not in ("depth", "meta_json")}),
     "depth", "batch axis"),
    ("object array", lambda d: d.update(timestamps=np.array([0.0, "x", None], dtype=object)), "timestamps", "pickle"),
]


@pytest.mark.parametrize("mutate,key,text", [b[1:] for b in BAD_FILES], ids=[b[0] for b in BAD_FILES])
def test_bad_file_raises_naming_key(tmp_path, mutate, key, text):
    d = file_dict(make_seq())
    mutate(d)
    path = tmp_path / "bad.npz"
    np.savez(path, **d)
    with pytest.raises(SequenceFormatError) as err:
        load_sequence(path)
    msg = str(err.value)
    assert str(path) in msg and f"'{key}'" in msg and text in msg, msg


def test_not_an_npz(tmp_path):
    path = tmp_path / "junk.npz"
    path.write_bytes(b"this is not a zip archive")
    with pytest.raises(SequenceFormatError, match="junk.npz"):
        load_sequence(path)


def test_validate_in_memory():
    validate_sequence(make_seq())
    with pytest.raises(SequenceFormatError, match=r"<memory>: key 'gt_flow'.*inconsistent"):
        validate_sequence(make_seq().replace(gt=GroundTruth(**{**vars(make_seq().gt), "flow": np.zeros((S, H, W, 2))})))
    with pytest.raises(SequenceFormatError, match="'meta_json'.*JSON"):
        validate_sequence(make_seq().replace(meta={"x": object()}))


def test_failed_save_leaves_existing_file_untouched(tmp_path):
    path = tmp_path / "seq.npz"
    save_sequence(path, make_seq())
    before = path.read_bytes()
    depth = make_seq().depth.copy()
    depth[1, 2, 3] = np.nan
    with pytest.raises(SequenceFormatError, match=r"'depth'.*1 non-finite.*frame 1"):
        save_sequence(path, make_seq().replace(depth=depth))
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["seq.npz"]


def test_docs_table_lists_every_key_the_module_knows():
    docs = (ROOT / "docs" / "sequence_format.md").read_text()
    keys = re.findall(r"^\| `(\w+)` \|", docs, flags=re.M)
    assert sorted(keys) == sorted(io._KNOWN)
    for key, shape in io._SHAPES.items():  # the documented shape is the one load checks
        row = next(line for line in docs.splitlines() if line.startswith(f"| `{key}` |"))
        assert row.split("|")[2].strip().strip("()").replace(",", "").rstrip() == shape, (key, row)
    assert re.search(r"allow_pickle=False", docs)
