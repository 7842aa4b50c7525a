"""Persistence of a bank: one file, ``MAGIC`` + the header length + a JSON header (format version,
config, array names, shapes, dtypes) + the raw arrays + the SHA-256 of everything before it (32
bytes), so a change anywhere, header included, is found. Written atomically (temporary file, fsync,
rename, mode ``0o666 & ~umask``), so an interrupted save leaves the previous bank intact, and a save
removes the temporary files killed saves left (older than ``STALE_TEMP_SECONDS``). A truncated,
altered or unknown file fails to load with :class:`~cm3d.memory.config.MemoryFileError`.

Versions 2 and 3 (a SHA-256 of the payload inside the header, which itself was not covered) still
load, with a note (:attr:`StoredBank.note`); the next save writes version 4. Concurrent writers go
through :mod:`cm3d.memory.transaction`."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import struct as pystruct

import jax
import jax.numpy as jnp
import numpy as np

from cm3d.data.atomic import atomic_write, remove_stale_temps
from cm3d.memory.bank import MemoryBank, empty
from cm3d.memory.config import MemoryConfig, MemoryFileError, config_from_dict

MAGIC = b"CM3DMEM\x00"
FORMAT_VERSION = 4  # 2: 3D keypoints; 3: floor keypoints (floor_kp_*); 4: one SHA-256 over header and payload
READ_VERSIONS = (2, 3, 4)  # 2 loads with no floor keypoints; 2 and 3 with a note (their header is not checksummed)
DIGEST_BYTES = 32
_PREFIX = len(MAGIC) + 8


@dataclasses.dataclass(frozen=True, eq=False)
class StoredBank:
    """A bank as read from its file: the bank, its config, the file's format version, ``digest``
    (SHA-256 of the whole file: which state of the bank this is) and ``note`` (None, or what a user
    should know: an older format that the next save rewrites)."""

    bank: MemoryBank
    cfg: MemoryConfig
    version: int
    digest: str
    note: str | None = None


def _fields(bank: MemoryBank) -> dict[str, np.ndarray]:
    return {f.name: np.asarray(getattr(bank, f.name)) for f in dataclasses.fields(bank)}


def encode(bank: MemoryBank, cfg: MemoryConfig) -> bytes:
    """The bytes of a version-4 bank file (refuses a bank holding non-finite values)."""
    arrays = _fields(bank)
    for name in ("points", "normals", "conf", "cloud_desc", "kf_desc", "kp_points", "kp_desc", "floor_kp_points",
                 "floor_kp_desc"):
        bad = ~np.isfinite(arrays[name])
        if bad.any():
            raise ValueError(f"memory bank field {name!r} holds {int(bad.sum())} non-finite values; "
                             "refusing to save a corrupt bank")
    header = json.dumps({
        "version": FORMAT_VERSION, "config": dataclasses.asdict(cfg),
        "arrays": [[k, list(a.shape), a.dtype.str] for k, a in arrays.items()],
    }).encode()
    body = b"".join([MAGIC, pystruct.pack("<Q", len(header)), header,
                     *(np.ascontiguousarray(a).tobytes() for a in arrays.values())])
    return body + hashlib.sha256(body).digest()


def save(bank: MemoryBank, path, cfg: MemoryConfig) -> list:
    """Write the bank atomically as format version 4 (one SHA-256 over header and payload) and remove
    stale temporary files of earlier, killed saves. Not a transaction: for a bank other processes
    may write, use :func:`cm3d.memory.commit` or :func:`cm3d.memory.modify`. Returns the stale
    temporary files removed."""
    data = encode(bank, cfg)
    removed = remove_stale_temps(path)
    with atomic_write(path) as f:
        f.write(data)
    return removed


def _header(path, data: bytes):
    """(header dict, payload start) of a file that starts with ``MAGIC``; MemoryFileError when damaged."""
    if len(data) < _PREFIX:
        raise MemoryFileError(f"{path}: damaged header (the file ends after {len(data)} bytes)")
    (n,) = pystruct.unpack("<Q", data[len(MAGIC): _PREFIX])
    if n > len(data) - _PREFIX:
        raise MemoryFileError(f"{path}: damaged header (its length, {n} bytes, runs past the end of the file)")
    try:
        header = json.loads(data[_PREFIX: _PREFIX + n])
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise MemoryFileError(f"{path}: damaged header (not JSON: {e})") from None
    if not isinstance(header, dict):
        raise MemoryFileError(f"{path}: damaged header (not a JSON object)")
    return header, _PREFIX + n


def _version(path, header: dict) -> int:
    v = header.get("version")
    if "version" not in header or not isinstance(v, int) or isinstance(v, bool):
        raise MemoryFileError(f"{path}: damaged header (no format version)")
    if v not in READ_VERSIONS:
        newer = " (written by a newer cm3d)" if v > FORMAT_VERSION else ""
        raise MemoryFileError(f"{path}: format version {v}{newer}; this cm3d reads versions "
                              f"{', '.join(map(str, READ_VERSIONS))}")
    return v


def decode(data: bytes, path="<bytes>") -> StoredBank:
    """A :class:`StoredBank` from the bytes of a bank file; any damage raises MemoryFileError."""
    if not data.startswith(MAGIC):
        raise MemoryFileError(f"{path}: not a cm3d memory bank (bad magic)")
    intact = len(data) >= _PREFIX + DIGEST_BYTES and hashlib.sha256(data[:-DIGEST_BYTES]).digest() == data[-DIGEST_BYTES:]
    header, start = _header(path, data)
    version = _version(path, header)
    note = None
    if version >= 4:
        if not intact:
            raise MemoryFileError(f"{path}: checksum mismatch (truncated or altered file)")
        payload = data[start:-DIGEST_BYTES]
    else:
        payload = data[start:]
        sha = header.get("sha256")
        if not isinstance(sha, str) or hashlib.sha256(payload).hexdigest() != sha:
            raise MemoryFileError(f"{path}: checksum mismatch (truncated or altered file)")
        note = (f"{path}: format version {version}, whose header is not covered by its checksum; it loads, "
                f"and the next save rewrites it as version {FORMAT_VERSION}")
    conf = header.get("config")
    if not isinstance(conf, dict):
        raise MemoryFileError(f"{path}: damaged header (no config object)")
    try:
        cfg = config_from_dict(conf)
    except (TypeError, ValueError) as e:
        raise MemoryFileError(f"{path}: bad config in the header ({e})") from None
    arrays = _arrays(path, header.get("arrays"), payload)
    spec = jax.eval_shape(lambda: empty(cfg))
    if version == 2:  # no floor keypoints yet (the config has max_floor_keypoints = 0)
        arrays.update({k: np.zeros(getattr(spec, k).shape, getattr(spec, k).dtype)
                       for k in ("floor_kp_points", "floor_kp_desc", "floor_kp_valid")})
    expected = {f.name: getattr(spec, f.name) for f in dataclasses.fields(spec)}
    if set(arrays) != set(expected) or any(arrays[k].shape != v.shape or arrays[k].dtype != v.dtype
                                           for k, v in expected.items()):
        raise MemoryFileError(f"{path}: arrays do not match the stored config's capacities")
    bank = MemoryBank(**{k: jnp.asarray(arrays[k]) for k in expected})
    return StoredBank(bank=bank, cfg=cfg, version=version, digest=hashlib.sha256(data).hexdigest(), note=note)


def _arrays(path, table, payload: bytes) -> dict[str, np.ndarray]:
    """The arrays the header's table describes, cut from the payload (which they must fill exactly)."""
    bad = MemoryFileError(f"{path}: damaged header (bad array table)")
    if not isinstance(table, list):
        raise bad
    arrays, off = {}, 0
    for item in table:
        if not (isinstance(item, list) and len(item) == 3 and isinstance(item[0], str) and isinstance(item[2], str)
                and isinstance(item[1], list) and all(isinstance(d, int) and d >= 0 for d in item[1])):
            raise bad
        name, shape, dtype = item
        try:
            dt = np.dtype(dtype)
        except TypeError:
            raise bad from None
        if dt.hasobject or dt.itemsize == 0 or name in arrays:
            raise bad
        count = math.prod(shape)
        size = count * dt.itemsize
        if off + size > len(payload):
            raise MemoryFileError(f"{path}: payload shorter than the array table says (truncated file)")
        arrays[name] = np.frombuffer(payload, dt, count=count, offset=off).reshape(shape)
        off += size
    if off != len(payload):
        raise MemoryFileError(f"{path}: payload longer than the array table says ({len(payload) - off} extra bytes)")
    return arrays


def read_bytes(path) -> bytes:
    """The bytes of a bank file; MemoryFileError when there is none."""
    path = os.fspath(path)
    try:
        with open(path, "rb") as f:
            return f.read()
    except FileNotFoundError:
        raise MemoryFileError(f"{path}: no such memory bank file") from None
    except IsADirectoryError:
        raise MemoryFileError(f"{path}: is a folder, not a memory bank file") from None


def read(path) -> StoredBank:
    """Read a bank file with its version, digest and note; any damage raises MemoryFileError. No lock
    is taken: saves replace the file by a rename, so a reader sees the old or the new bank, whole."""
    return decode(read_bytes(path), os.fspath(path))


def load(path) -> tuple[MemoryBank, MemoryConfig]:
    """Read a bank written by :func:`save` -> (bank, config); any damage raises MemoryFileError."""
    s = read(path)
    return s.bank, s.cfg
