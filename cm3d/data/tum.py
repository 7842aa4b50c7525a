"""TUM RGB-D trajectory files: ``timestamp tx ty tz qx qy qz qw`` per line, poses cam_to_world.

Hamilton unit quaternions, ``qw`` last. Reading accepts ``#`` comments, blank lines, whitespace or
commas, and normalises quaternions (as evo). Writing uses ``repr`` floats (an exact round trip).
"""

from __future__ import annotations

import math
import os
import re

import numpy as np

from cm3d.data.atomic import atomic_write

_SPLIT = re.compile(r"[,\s]+")
_QUAT_EPS = 1e-12


def quat_to_rotation(q_xyzw: np.ndarray) -> np.ndarray:
    """Hamilton quaternions (..., 4) as ``(qx, qy, qz, qw)``, normalised here -> rotations (..., 3, 3)."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    rows = [
        [1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy)],
        [2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx)],
        [2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy)],
    ]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def rotation_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotations (..., 3, 3) -> unit Hamilton quaternions (..., 4) ``(qx, qy, qz, qw)`` with ``qw >= 0``.

    Uses the symmetric 4x4 matrix whose top eigenvector is the quaternion (Bar-Itzhack), so a
    slightly non-orthonormal input maps to the closest unit quaternion.
    """
    R = np.asarray(R, dtype=np.float64)
    r = lambda i, j: R[..., i, j]  # noqa: E731
    # For an exact rotation K = 4 q q^T - I in the (x, y, z, w) order.
    K = np.empty(R.shape[:-2] + (4, 4))
    K[..., 0, 0] = r(0, 0) - r(1, 1) - r(2, 2)
    K[..., 1, 1] = r(1, 1) - r(0, 0) - r(2, 2)
    K[..., 2, 2] = r(2, 2) - r(0, 0) - r(1, 1)
    K[..., 3, 3] = r(0, 0) + r(1, 1) + r(2, 2)
    off = {
        (0, 1): r(0, 1) + r(1, 0),
        (0, 2): r(0, 2) + r(2, 0),
        (1, 2): r(1, 2) + r(2, 1),
        (0, 3): r(2, 1) - r(1, 2),
        (1, 3): r(0, 2) - r(2, 0),
        (2, 3): r(1, 0) - r(0, 1),
    }
    for (i, j), v in off.items():
        K[..., i, j] = v
        K[..., j, i] = v
    _, vecs = np.linalg.eigh(K)
    q = vecs[..., :, -1]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0.0, -q, q)


def read_tum(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory -> (timestamps float64 (N,) in s, cam_to_world float64 (N, 4, 4)).

    Raises ``ValueError`` naming the file and line for a wrong column count, a non-numeric or
    non-finite value, or a zero quaternion. An empty file (only comments) gives N = 0.
    """
    rows: list[list[float]] = []
    with open(path, encoding="utf-8-sig") as f:
        for lineno, raw in enumerate(f, start=1):
            line = raw.split("#", 1)[0].strip()
            if not line:
                continue
            fields = [s for s in _SPLIT.split(line) if s]
            if len(fields) != 8:
                raise ValueError(
                    f"{path}:{lineno}: expected 8 values 'timestamp tx ty tz qx qy qz qw', "
                    f"got {len(fields)}: {line!r}"
                )
            try:
                vals = [float(s) for s in fields]
            except ValueError:
                raise ValueError(f"{path}:{lineno}: non-numeric value in {line!r}") from None
            if not all(math.isfinite(v) for v in vals):
                raise ValueError(f"{path}:{lineno}: NaN or infinite value in {line!r}")
            if math.sqrt(sum(v * v for v in vals[4:])) < _QUAT_EPS:
                raise ValueError(f"{path}:{lineno}: zero quaternion in {line!r}")
            rows.append(vals)
    if not rows:
        return np.zeros((0,), np.float64), np.zeros((0, 4, 4), np.float64)
    mat = np.asarray(rows, dtype=np.float64)
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :3] = quat_to_rotation(mat[:, 4:8])
    T[:, :3, 3] = mat[:, 1:4]
    return mat[:, 0].copy(), T


def write_tum(path: str | os.PathLike, timestamps, cam_to_world) -> None:
    """Write timestamps (N,) in s and cam_to_world poses (N, 4, 4) as a TUM file, atomically.

    Values are written with ``repr`` precision (exact round trip); quaternions are unit, ``qw >= 0``.
    Raises ``ValueError`` for mismatched shapes or non-finite values.
    """
    ts = np.asarray(timestamps, dtype=np.float64)
    T = np.asarray(cam_to_world, dtype=np.float64)
    if ts.ndim != 1 or T.shape != (ts.shape[0], 4, 4):
        raise ValueError(
            f"write_tum({path}): need timestamps (N,) and cam_to_world (N, 4, 4), "
            f"got {ts.shape} and {T.shape}"
        )
    if not (np.all(np.isfinite(ts)) and np.all(np.isfinite(T))):
        bad = np.flatnonzero(~(np.isfinite(ts) & np.all(np.isfinite(T), axis=(1, 2))))
        raise ValueError(f"write_tum({path}): non-finite timestamp or pose at index {int(bad[0])}")
    q = rotation_to_quat(T[:, :3, :3]) if len(ts) else np.zeros((0, 4))
    with atomic_write(path, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        for t, p, qi in zip(ts.tolist(), T[:, :3, 3].tolist(), q.tolist()):
            f.write(" ".join(repr(float(v)) for v in (t, *p, *qi)) + "\n")
