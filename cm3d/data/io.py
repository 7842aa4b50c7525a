"""Sequence files: one ``.npz`` per video, a superset of VGGT's saved predictions dict.

``S`` frames of ``H x W``. The keys, shapes, dtypes and load rules are in docs/sequence_format.md:
required ``images``, ``depth``, ``intrinsic`` and ``extrinsic`` or ``cam_to_world``; optional
confidence, timestamps, point map and ground truth (``gt_*``), ``meta_json``. Never pickled;
validated on save and on load (a leading batch axis of 1 is dropped, unknown keys ignored, nothing
resized); every problem raises :class:`SequenceFormatError` naming the file, the key and the problem.
"""

from __future__ import annotations

import json
import os
import zipfile

import numpy as np

from cm3d.data.atomic import atomic_write
from cm3d.data.sequence import GroundTruth, Sequence
from cm3d.data.tum import read_tum, write_tum  # noqa: F401  (re-exported: io is the one file API)

__all__ = ["SequenceFormatError", "load_sequence", "read_tum", "save_sequence", "sequence_from_arrays",
           "validate_sequence", "write_tum"]

# Expected shape of each array key once `images` fixes S, H, W (numbers are fixed trailing dims).
_SHAPES = {
    "depth": "S H W", "depth_conf": "S H W", "intrinsic": "S 3 3", "cam_to_world": "S 4 4",
    "timestamps": "S", "world_points": "S H W 3", "gt_cam_to_world": "S 4 4", "gt_depth": "S H W",
    "gt_intrinsic": "S 3 3", "gt_dynamic_mask": "S H W", "gt_flow": "S-1 H W 2",
}
_KNOWN = ("images", "extrinsic", "gt_extrinsic", "meta_json", *_SHAPES)


class SequenceFormatError(ValueError):
    """A sequence file (or in-memory :class:`Sequence`) breaks the format; names file, key, problem."""


def _err(source, key: str, problem: str) -> SequenceFormatError:
    return SequenceFormatError(f"{source}: key '{key}': {problem}")


def _rigid_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse (..., 4, 4) float64 of rigid transforms (..., 3, 4) or (..., 4, 4): ``[R^T, -R^T t]``."""
    R, t = np.asarray(T[..., :3, :3], np.float64), np.asarray(T[..., :3, 3], np.float64)
    out = np.zeros(T.shape[:-2] + (4, 4))
    out[..., :3, :3] = np.swapaxes(R, -1, -2)
    out[..., :3, 3] = -np.einsum("...ji,...j->...i", R, t)
    out[..., 3, 3] = 1.0
    return out


def _first_frame(bad: np.ndarray) -> int:
    return int(np.argwhere(bad)[0][0])


def validate_sequence(seq: Sequence, source: str = "<memory>") -> None:
    """Raise :class:`SequenceFormatError` if ``seq`` breaks the format (shapes, dtypes, values)."""
    _validate(seq, source, {})


def _validate(seq: Sequence, source, names: dict[str, str]) -> None:
    def fail(key, problem):
        raise _err(source, names.get(key, key), problem)

    for key in ("images", "depth", "depth_conf", "intrinsic", "cam_to_world", "timestamps"):
        if getattr(seq, key) is None:
            fail(key, "missing required key")
    images = np.asarray(seq.images)
    if images.dtype != np.uint8 or images.ndim != 4 or images.shape[-1] != 3:
        fail("images", f"expected (S, H, W, 3) uint8, got shape {images.shape} dtype {images.dtype}")
    S, H, W, _ = images.shape
    dims = {"S": S, "S-1": S - 1, "H": H, "W": W}
    keys = ("depth", "depth_conf", "intrinsic", "cam_to_world", "timestamps", "world_points")
    arrays = {k: getattr(seq, k) for k in keys}
    if seq.gt is not None:
        g = seq.gt
        arrays.update(gt_cam_to_world=g.cam_to_world, gt_depth=g.depth, gt_intrinsic=g.intrinsic,
                      gt_dynamic_mask=g.dynamic_mask, gt_flow=g.flow)
    arrays = {k: np.asarray(a) for k, a in arrays.items() if a is not None}

    for key, a in arrays.items():
        spec = _SHAPES[key].split()
        want = tuple(dims[d] if d in dims else int(d) for d in spec)
        sym = "(" + ", ".join(spec) + ")"
        n_lead = sum(d in dims for d in spec)
        if a.shape != want:
            if a.ndim != len(want) or a.shape[n_lead:] != want[n_lead:]:
                fail(key, f"wrong shape {a.shape}, expected {sym}")
            fail(key, f"shape {a.shape} is inconsistent with 'images' shape {images.shape}: "
                      f"expected {sym} = {want}")
        if key == "gt_dynamic_mask":
            if a.dtype != np.bool_:
                fail(key, f"dtype {a.dtype} is not bool")
            continue
        if not np.issubdtype(a.dtype, np.floating):
            fail(key, f"dtype {a.dtype} is not floating")
        bad = ~np.isfinite(a)
        if bad.any():
            fail(key, f"{int(bad.sum())} non-finite values (NaN/inf), first in frame {_first_frame(bad)}")

    no_pos = ~(arrays["depth"] > 0).reshape(S, -1).any(axis=1)
    if no_pos.any():
        fail("depth", f"frame {_first_frame(no_pos)} has no positive depth")
    neg = arrays["depth_conf"] < 0
    if neg.any():
        fail("depth_conf", f"{int(neg.sum())} negative values, first in frame {_first_frame(neg)}")
    # sensor holes (depth 0, confidence 0) are valid; a frame must keep some usable pixel
    unusable = ~((arrays["depth"] > 0) & (arrays["depth_conf"] > 0)).reshape(S, -1).any(axis=1)
    if unusable.any():
        fail("depth", f"frame {_first_frame(unusable)} has no usable depth (no pixel with depth > 0 "
                      "and depth_conf > 0)")
    for key in ("intrinsic", "gt_intrinsic"):
        if key in arrays:
            K = arrays[key]
            det = np.linalg.det(K)
            bad = (K[:, 0, 0] <= 0) | (K[:, 1, 1] <= 0) | (np.abs(det) < 1e-9)
            if bad.any():
                i = _first_frame(bad)
                fail(key, f"frame {i} is singular or has fx/fy <= 0 "
                          f"(fx={K[i, 0, 0]}, fy={K[i, 1, 1]}, det={det[i]})")
    for key in ("cam_to_world", "gt_cam_to_world"):
        if key in arrays:
            T = arrays[key]
            R = T[:, :3, :3]
            orth = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
            det = np.linalg.det(R)
            bottom = np.abs(T[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1)
            bad = (orth > 1e-3) | (det < 0) | (bottom > 1e-6)
            if bad.any():
                i = _first_frame(bad)
                fail(key, f"frame {i} is not a rigid pose (|R^T R - I| = {orth[i]:.3g}, "
                          f"det R = {det[i]:.3g}, bottom row {T[i, 3].tolist()})")
    if not isinstance(seq.meta, dict):
        fail("meta_json", f"meta must be a dict, got {type(seq.meta).__name__}")
    try:
        json.dumps(seq.meta)
    except (TypeError, ValueError) as e:
        fail("meta_json", f"meta is not JSON-serialisable ({e})")


def sequence_arrays(seq: Sequence) -> dict[str, np.ndarray]:
    """The arrays of the file format for ``seq`` (see the module docstring), without validation."""
    c2w = np.asarray(seq.cam_to_world, np.float64)
    arrays = {
        "images": np.asarray(seq.images),
        "depth": np.asarray(seq.depth, np.float32),
        "depth_conf": np.asarray(seq.depth_conf, np.float32),
        "extrinsic": _rigid_inverse(c2w)[:, :3, :],
        "cam_to_world": c2w,
        "intrinsic": np.asarray(seq.intrinsic, np.float64),
        "timestamps": np.asarray(seq.timestamps, np.float64),
        "meta_json": np.array(json.dumps(seq.meta)),
    }
    if seq.world_points is not None:
        arrays["world_points"] = np.asarray(seq.world_points, np.float32)
    if (g := seq.gt) is not None:
        gt = {"gt_cam_to_world": (g.cam_to_world, np.float64), "gt_depth": (g.depth, np.float32),
              "gt_intrinsic": (g.intrinsic, np.float64), "gt_dynamic_mask": (g.dynamic_mask, bool),
              "gt_flow": (g.flow, np.float32)}
        arrays.update({k: np.asarray(a, dt) for k, (a, dt) in gt.items() if a is not None})
    return arrays


def save_sequence(path: str | os.PathLike, seq: Sequence, compress: bool = False) -> None:
    """Validate ``seq`` and write it atomically to ``path`` as ``.npz`` (format in the module docstring)."""
    validate_sequence(seq, source=os.fspath(path))
    arrays = sequence_arrays(seq)
    with atomic_write(path, "wb") as f:
        (np.savez_compressed if compress else np.savez)(f, **arrays)


def _float(a: np.ndarray | None, dtype, copy: bool = True) -> np.ndarray | None:
    """Cast floating arrays to ``dtype`` (a copy unless ``copy`` is False and the dtype is already
    right); others stay as they are, for validation to report."""
    return a.astype(dtype, copy=copy) if a is not None and np.issubdtype(a.dtype, np.floating) else a


def _drop_channel(a: np.ndarray | None) -> np.ndarray | None:
    """(S, H, W, 1) -> (S, H, W)."""
    return a[..., 0] if a is not None and a.ndim == 4 and a.shape[-1] == 1 else a


def _images_uint8(src, a: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Images as (S, H, W, 3) uint8 from uint8/float, channels last or first, at the depth's H x W."""
    if depth.ndim == 3 and a.ndim == 4:
        hw = depth.shape[1:]
        last, first = a.shape[1:] == (*hw, 3), a.shape[1:] == (3, *hw)
        if not (last or first):
            raise _err(src, "images", f"shape {a.shape} does not match 'depth' shape {depth.shape}: "
                                      "expected (S, H, W, 3) or (S, 3, H, W) at the depth's H x W "
                                      "(resize the images before saving)")
    else:
        last, first = a.ndim == 4 and a.shape[-1] == 3, a.ndim == 4 and a.shape[1] == 3
    if first and not last:
        a = a.transpose(0, 2, 3, 1)
    if a.dtype == np.uint8 or not np.issubdtype(a.dtype, np.floating):
        return np.ascontiguousarray(a)  # wrong dtypes are reported by validation
    if not np.isfinite(a).all():
        raise _err(src, "images", f"{int((~np.isfinite(a)).sum())} non-finite values (NaN/inf)")
    if a.size and (a.min() < -1e-3 or a.max() > 1 + 1e-3):
        raise _err(src, "images", f"float images must be in [0, 1], got [{a.min():.4g}, {a.max():.4g}]")
    return np.rint(np.clip(a, 0.0, 1.0) * 255.0).astype(np.uint8)


def _pose(src, raw: dict, ext_key: str, c2w_key: str) -> tuple[np.ndarray | None, str]:
    """cam_to_world (S, 4, 4) float64 from ``c2w_key`` or the inverse of ``ext_key``; also the key used."""
    E, T = raw.get(ext_key), raw.get(c2w_key)
    if E is not None and (E.ndim != 3 or E.shape[1:] not in ((3, 4), (4, 4))):
        raise _err(src, ext_key, f"wrong shape {E.shape}, expected (S, 3, 4) or (S, 4, 4)")
    if T is None:
        return (None if E is None else _rigid_inverse(E)), ext_key
    T = _float(T, np.float64)
    if E is not None and T.shape == (E.shape[0], 4, 4):
        diff = np.abs(_rigid_inverse(E) - T).max(axis=(1, 2))
        agree = diff <= 1e-6 * (1.0 + np.abs(T).max(axis=(1, 2)))  # NaN disagrees
        if not agree.all():
            i = _first_frame(~agree)
            raise _err(src, c2w_key, f"frame {i} disagrees with the inverse of '{ext_key}' "
                                     f"(max diff {diff[i]:.3g})")
    return T, c2w_key


def _read_archive(path, src) -> dict[str, np.ndarray]:
    """The known keys of an ``.npz``, every member's CRC checked first (so a damaged byte anywhere
    raises instead of loading different numbers). Missing files and permissions raise their OSError;
    anything else that fails to read raises :class:`SequenceFormatError`."""
    with open(path, "rb") as f:
        head = f.read(8)
    if not zipfile.is_zipfile(path):
        if head.startswith(b"\x93NUMPY"):
            raise _err(src, "<file>", "is a single .npy array, not an .npz archive")
        raise _err(src, "<file>", f"not an .npz archive (no zip structure; it starts with {head!r})")
    try:
        with zipfile.ZipFile(path) as z:
            bad = z.testzip()
        if bad is not None:
            raise _err(src, "<file>", f"damaged .npz archive (member {bad!r} fails its CRC check)")
        raw = {}
        with np.load(path, allow_pickle=False) as npz:
            for key in _KNOWN:
                if key in npz.files:
                    try:
                        raw[key] = npz[key]
                    except ValueError as e:
                        if "pickle" in str(e):  # object arrays need pickle
                            raise _err(src, key, f"cannot be read without pickle ({e})") from e
                        raise
    except SequenceFormatError:
        raise
    except (FileNotFoundError, PermissionError, IsADirectoryError):
        raise
    except Exception as e:  # noqa: BLE001  zipfile / numpy raise many kinds on a damaged archive
        raise _err(src, "<file>", f"not a readable .npz archive ({type(e).__name__}: {e})") from e
    return raw


def load_sequence(path: str | os.PathLike) -> Sequence:
    """Read a ``.npz`` written by :func:`save_sequence` or saved from VGGT's predictions dict."""
    src = os.fspath(path)
    return sequence_from_arrays(_read_archive(path, src), src, copy=False)  # arrays just read: nobody else's


def sequence_from_arrays(arrays: dict, source: str = "<arrays>", copy: bool = True) -> Sequence:
    """A validated :class:`Sequence` from a dict of arrays with the keys of the file format (a
    VGGT predictions dict, for example); unknown keys are ignored. ``copy=False``: arrays that already
    have their dtype are used as they are (the sequence shares their memory), not copied."""
    src = source
    for key in ("images", "depth", "intrinsic"):
        if key not in arrays:
            raise _err(src, key, "missing required key")
    if "extrinsic" not in arrays and "cam_to_world" not in arrays:
        raise _err(src, "extrinsic", "missing required key (or 'cam_to_world')")
    raw = {k: np.asarray(v) for k, v in arrays.items() if k in _KNOWN}
    if raw["intrinsic"].ndim == 4:  # leading batch axis [1, S, ...] on every array
        for key, a in raw.items():
            if key != "meta_json":
                if a.ndim == 0 or a.shape[0] != 1:
                    raise _err(src, key, f"shape {a.shape} lacks the leading batch axis of size 1 "
                                         f"that 'intrinsic' {raw['intrinsic'].shape} has")
                raw[key] = a[0]

    depth = _float(_drop_channel(raw["depth"]), np.float32, copy)
    images = _images_uint8(src, raw["images"], depth)
    S = images.shape[0] if images.ndim else 0  # a bad shape is reported by validation
    conf = raw.get("depth_conf")
    conf = np.ones(depth.shape, np.float32) if conf is None else _float(_drop_channel(conf), np.float32, copy)
    ts = raw.get("timestamps")
    if ts is None:
        ts = np.arange(S, dtype=np.float64)
    elif ts.dtype.kind in "iuf":
        ts = ts.astype(np.float64)
    c2w, pose_key = _pose(src, raw, "extrinsic", "cam_to_world")
    meta = {}
    if "meta_json" in raw:
        m = raw["meta_json"]
        if m.ndim != 0 or m.dtype.kind != "U":
            raise _err(src, "meta_json", f"expected a 0-d unicode string, got {m.shape} {m.dtype}")
        try:
            meta = json.loads(str(m[()]))
        except json.JSONDecodeError as e:
            raise _err(src, "meta_json", f"invalid JSON ({e})") from e
        if not isinstance(meta, dict):
            raise _err(src, "meta_json", f"expected a JSON object, got {type(meta).__name__}")

    gt, gt_pose_key = None, "gt_cam_to_world"
    gt_keys = sorted(k for k in raw if k.startswith("gt_"))
    if gt_keys:
        if "gt_depth" not in raw:
            raise _err(src, "gt_depth", f"missing, required for ground truth (file has {gt_keys})")
        gt_c2w, gt_pose_key = _pose(src, raw, "gt_extrinsic", "gt_cam_to_world")
        if gt_c2w is None:
            raise _err(src, "gt_cam_to_world",
                       f"missing (or 'gt_extrinsic'), required for ground truth (file has {gt_keys})")
        mask = raw.get("gt_dynamic_mask")
        if mask is not None and mask.dtype.kind in "iu":
            mask = mask.astype(bool)
        gt = GroundTruth(
            cam_to_world=gt_c2w,
            depth=_float(_drop_channel(raw["gt_depth"]), np.float32, copy),
            intrinsic=_float(raw.get("gt_intrinsic", raw["intrinsic"]), np.float64, copy),
            dynamic_mask=mask,
            flow=_float(raw.get("gt_flow"), np.float32, copy),
        )
    seq = Sequence(
        images=images,
        depth=depth,
        depth_conf=conf,
        intrinsic=_float(raw["intrinsic"], np.float64, copy),
        cam_to_world=c2w,
        timestamps=ts,
        world_points=_float(raw.get("world_points"), np.float32, copy),
        gt=gt,
        meta=meta,
    )
    _validate(seq, src, {"cam_to_world": pose_key, "gt_cam_to_world": gt_pose_key})
    return seq
