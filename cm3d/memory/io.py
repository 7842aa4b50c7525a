"""Persistence of a bank: one file, ``MAGIC`` + a JSON header (format version, config, array names,
shapes, dtypes, SHA-256 of the payload) + the raw arrays; written atomically (temporary file, fsync,
rename), so an interrupted save leaves the previous bank intact. A truncated or altered file fails to
load with :class:`~cm3d.memory.config.MemoryFileError`."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import struct as pystruct

import jax
import jax.numpy as jnp
import numpy as np

from cm3d.data.atomic import atomic_write
from cm3d.memory.bank import MemoryBank, empty
from cm3d.memory.config import MemoryConfig, MemoryFileError, config_from_dict

MAGIC = b"CM3DMEM\x00"
FORMAT_VERSION = 3  # 2: 3D keypoints (kp_points, kp_desc, kp_valid); 3: floor keypoints (floor_kp_*)
READ_VERSIONS = (2, 3)  # a version-2 file loads with no floor keypoints (max_floor_keypoints = 0)


def _fields(bank: MemoryBank) -> dict[str, np.ndarray]:
    return {f.name: np.asarray(getattr(bank, f.name)) for f in dataclasses.fields(bank)}


def save(bank: MemoryBank, path, cfg: MemoryConfig) -> None:
    """Write the bank atomically with a versioned header and a SHA-256 checksum."""
    arrays = _fields(bank)
    for name in ("points", "normals", "conf", "cloud_desc", "kf_desc", "kp_points", "kp_desc", "floor_kp_points",
                 "floor_kp_desc"):
        bad = ~np.isfinite(arrays[name])
        if bad.any():
            raise ValueError(f"memory bank field {name!r} holds {int(bad.sum())} non-finite values; "
                             "refusing to save a corrupt bank")
    payload = b"".join(np.ascontiguousarray(a).tobytes() for a in arrays.values())
    header = json.dumps({
        "version": FORMAT_VERSION, "config": dataclasses.asdict(cfg),
        "arrays": [[k, list(a.shape), a.dtype.str] for k, a in arrays.items()],
        "sha256": hashlib.sha256(payload).hexdigest(),
    }).encode()
    with atomic_write(path) as f:
        f.write(MAGIC + pystruct.pack("<Q", len(header)) + header + payload)


def load(path) -> tuple[MemoryBank, MemoryConfig]:
    """Read a bank written by :func:`save`; any damage raises :class:`MemoryFileError`."""
    path = os.fspath(path)
    try:
        data = open(path, "rb").read()
    except FileNotFoundError:
        raise MemoryFileError(f"{path}: no such memory bank file") from None
    if not data.startswith(MAGIC):
        raise MemoryFileError(f"{path}: not a cm3d memory bank (bad magic)")
    try:
        (n,) = pystruct.unpack("<Q", data[len(MAGIC): len(MAGIC) + 8])
        start = len(MAGIC) + 8
        header = json.loads(data[start: start + n])
    except (pystruct.error, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise MemoryFileError(f"{path}: damaged header ({e})") from None
    version = header.get("version")
    if version not in READ_VERSIONS:
        raise MemoryFileError(f"{path}: format version {version}, this cm3d reads {', '.join(map(str, READ_VERSIONS))}")
    payload = data[start + n:]
    if hashlib.sha256(payload).hexdigest() != header["sha256"]:
        raise MemoryFileError(f"{path}: checksum mismatch (truncated or altered file)")
    try:
        cfg = config_from_dict(header["config"])
    except TypeError as e:
        raise MemoryFileError(f"{path}: unknown config fields ({e})") from None
    arrays, off = {}, 0
    for name, shape, dtype in header["arrays"]:
        size = int(np.prod(shape)) * np.dtype(dtype).itemsize
        arrays[name] = jnp.asarray(np.frombuffer(payload[off: off + size], dtype).reshape(shape))
        off += size
    spec = jax.eval_shape(lambda: empty(cfg))
    if version == 2:  # no floor keypoints yet (the config has max_floor_keypoints = 0)
        arrays.update({k: jnp.zeros(getattr(spec, k).shape, getattr(spec, k).dtype)
                       for k in ("floor_kp_points", "floor_kp_desc", "floor_kp_valid")})
    expected = {f.name: getattr(spec, f.name).shape for f in dataclasses.fields(spec)}
    if set(arrays) != set(expected) or any(arrays[k].shape != v for k, v in expected.items()):
        raise MemoryFileError(f"{path}: arrays do not match the stored config's capacities")
    return MemoryBank(**arrays), cfg
