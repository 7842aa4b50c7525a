"""Chunk files: every chunk of a long video in one ``.npz``, and back.

The chunks' frames concatenated (shared frames repeated) in the sequence format plus a ``chunk``
key (S_total,) int, non-decreasing; meta is ``{"chunks": [meta_k, ...]}``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from cm3d.data import io
from cm3d.data.atomic import atomic_write
from cm3d.data.sequence import GroundTruth, Sequence
from cm3d.long_video.layout import StitchError, check_chunks


def concat_chunks(chunks) -> tuple[Sequence, np.ndarray]:
    """Chunks concatenated frame by frame -> (Sequence, chunk index (S_total,)); straddling ``gt_flow`` is 0."""
    chunks = check_chunks(chunks)
    idx = np.concatenate([np.full(c.num_frames, k, np.int64) for k, c in enumerate(chunks)])
    cat = lambda xs: np.concatenate(xs)  # noqa: E731
    wp = None if any(c.world_points is None for c in chunks) else cat([c.world_points for c in chunks])
    gt = None
    if all(c.gt is not None for c in chunks):
        gts = [c.gt for c in chunks]
        flow = None
        if all(g.flow is not None for g in gts):
            z = np.zeros((1,) + gts[0].flow.shape[1:], np.float32)
            flow = cat([x for g in gts for x in (g.flow, z)][:-1])
        gt = GroundTruth(cam_to_world=cat([g.cam_to_world for g in gts]), depth=cat([g.depth for g in gts]),
                         intrinsic=cat([g.intrinsic for g in gts]),
                         dynamic_mask=None if any(g.dynamic_mask is None for g in gts)
                         else cat([g.dynamic_mask for g in gts]), flow=flow)
    seq = Sequence(images=cat([c.images for c in chunks]), depth=cat([c.depth for c in chunks]),
                   depth_conf=cat([c.depth_conf for c in chunks]), intrinsic=cat([c.intrinsic for c in chunks]),
                   cam_to_world=cat([c.cam_to_world for c in chunks]), timestamps=cat([c.timestamps for c in chunks]),
                   world_points=wp, gt=gt, meta={"chunks": [c.meta for c in chunks]})
    return seq, idx


def split_chunks(seq: Sequence, chunk_index, source: str = "<memory>") -> list[Sequence]:
    """Split a concatenated sequence by its per-frame ``chunk`` index (S,) int (0, 1, ..., K-1 in
    non-decreasing order, every index present) into K chunks; inverse of :func:`concat_chunks`."""
    c = np.asarray(chunk_index)
    if c.shape != (seq.num_frames,):
        raise StitchError(f"{source}: key 'chunk': shape {c.shape}, expected ({seq.num_frames},) (one per frame)")
    if not np.issubdtype(c.dtype, np.integer):
        raise StitchError(f"{source}: key 'chunk': dtype {c.dtype} is not an integer type")
    if c.size == 0 or c[0] != 0 or np.any(np.diff(c) < 0) or np.any(np.diff(c) > 1):
        raise StitchError(f"{source}: key 'chunk': must run 0, 1, ..., K-1 in non-decreasing order without "
                          f"gaps (chunks stored one after the other), got {np.unique(c).tolist()[:10]}")
    metas = seq.meta.get("chunks") if isinstance(seq.meta.get("chunks"), list) else None
    K = int(c[-1]) + 1
    if metas is not None and len(metas) != K:
        metas = None
    out = []
    for k in range(K):
        a, b = np.flatnonzero(c == k)[[0, -1]]
        part = seq.slice(int(a), int(b) + 1)
        out.append(part.replace(meta=dict(metas[k]) if metas is not None else dict(seq.meta)))
    return out


def save_chunks(path: str | os.PathLike, chunks, compress: bool = False) -> None:
    """Write every chunk to one ``.npz``: the sequence format plus a ``chunk`` key (atomic)."""
    seq, idx = concat_chunks(chunks)
    path = Path(path)
    tmp = path.with_name(f".{path.name}.chunks.npz")
    try:
        io.save_sequence(tmp, seq, compress=compress)
        with np.load(tmp, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    finally:
        if tmp.exists():
            tmp.unlink()
    arrays["chunk"] = idx
    with atomic_write(path, "wb") as f:
        (np.savez_compressed if compress else np.savez)(f, **arrays)


def load_chunks(paths) -> list[Sequence]:
    """Chunks from a list of chunk ``.npz`` files (one sequence each, in temporal order), or from one
    file (a path or a one-element list) holding a ``chunk`` key (module docstring)."""
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    paths = [Path(p) for p in paths]
    if not paths:
        raise StitchError("paths: empty list, need at least one chunk file")
    for p in paths:
        if not p.is_file():
            raise FileNotFoundError(f"{p}: no such file")
    if len(paths) == 1:
        with np.load(paths[0], allow_pickle=False) as npz:
            chunk = npz["chunk"] if "chunk" in npz.files else None
        seq = io.load_sequence(paths[0])
        return [seq] if chunk is None else split_chunks(seq, chunk, source=str(paths[0]))
    out = []
    for p in paths:
        with np.load(p, allow_pickle=False) as npz:
            if "chunk" in npz.files:
                raise StitchError(f"{p}: key 'chunk': a file holding several chunks must be loaded alone")
        out.append(io.load_sequence(p))
    return out
