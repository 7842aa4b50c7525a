"""Chunk layout of a long video: validation, global frame ranges, overlaps, blend weights.

Chunk k's first ``o_k`` frames are chunk k-1's last ``o_k``; ``overlap`` is one int, or None to infer
each ``o_k`` from repeated timestamps. Constraints: ``1 <= o_k < len(chunk k)``, no frame in three
chunks, one image size. Problems raise :class:`StitchError` (a ``ValueError``) naming the chunk and
field, or :class:`cm3d.data.io.SequenceFormatError` for a malformed chunk.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from cm3d.data import io
from cm3d.data.sequence import Sequence


class StitchError(ValueError):
    """Chunks that cannot be stitched (layout, sizes, overlap); the message names chunk and field."""


class ChunkLayout(NamedTuple):
    """ranges: global [start, stop) per chunk; overlaps: shared frames per boundary (K-1);
    timestamps (S,) float64 of the merged frames."""

    ranges: tuple[tuple[int, int], ...]
    overlaps: tuple[int, ...]
    timestamps: np.ndarray


def check_chunks(chunks) -> list[Sequence]:
    """The chunks as a list of valid :class:`Sequence` of one image size (else :class:`StitchError`)."""
    if isinstance(chunks, Sequence) or not isinstance(chunks, (list, tuple)):
        raise StitchError(f"chunks: expected a list of Sequence, got {type(chunks).__name__}")
    if len(chunks) == 0:
        raise StitchError("chunks: empty list, need at least one chunk")
    for k, c in enumerate(chunks):
        if not isinstance(c, Sequence):
            raise StitchError(f"chunks[{k}]: expected a Sequence, got {type(c).__name__}")
        io.validate_sequence(c, source=f"chunks[{k}]")
    hw = chunks[0].image_size
    for k, c in enumerate(chunks[1:], 1):
        if c.image_size != hw:
            raise StitchError(f"chunks[{k}]: images are {c.image_size[0]}x{c.image_size[1]}, chunk 0's "
                              f"{hw[0]}x{hw[1]}: every chunk must have the same image size (intrinsics "
                              "and depth maps are per pixel)")
    return list(chunks)


def _frame_interval(chunks) -> float:
    d = np.concatenate([np.diff(np.asarray(c.timestamps, np.float64)) for c in chunks])
    d = d[d > 0]
    return float(np.median(d)) if d.size else 1.0


def chunk_layout(chunks, overlap: int | None = None):
    """Global frame ranges of the chunks and the overlap of each boundary -> :class:`ChunkLayout`
    (ranges, overlaps, merged timestamps: the chunks' when consistent, else 0..S-1)."""
    chunks = check_chunks(chunks)
    K = len(chunks)
    n = [c.num_frames for c in chunks]
    tol = 0.25 * _frame_interval(chunks)
    if overlap is not None:
        if isinstance(overlap, bool) or not isinstance(overlap, (int, np.integer)):
            raise StitchError(f"overlap: expected an int or None, got {type(overlap).__name__}")
        overlaps = [int(overlap)] * (K - 1)
    else:
        overlaps = []
        for k in range(1, K):
            ta, tb = np.asarray(chunks[k - 1].timestamps, np.float64), np.asarray(chunks[k].timestamps, np.float64)
            o = int(np.sum(tb <= ta[-1] + tol))
            if o == 0:
                raise StitchError(f"chunks[{k}]: does not overlap chunks[{k - 1}] (its first timestamp "
                                  f"{tb[0]:g} is after the previous chunk's last {ta[-1]:g}); consecutive "
                                  "chunks must share at least one frame")
            if o >= n[k] or o > n[k - 1] or np.any(np.abs(tb[:o] - ta[-o:]) > tol):
                raise StitchError(f"chunks[{k}]: timestamps ({tb[0]:g} .. {tb[-1]:g}) do not continue "
                                  f"chunks[{k - 1}]'s ({ta[0]:g} .. {ta[-1]:g}) with shared frames: per-chunk "
                                  "frame indices? pass overlap= explicitly")
            overlaps.append(o)
    for k, o in enumerate(overlaps, 1):
        if o < 1:
            raise StitchError(f"overlap: chunks[{k - 1}] and chunks[{k}] share {o} frames; need at least 1")
        if o >= n[k] or o > n[k - 1]:
            raise StitchError(f"overlap: {o} shared frames between chunks[{k - 1}] ({n[k - 1]} frames) and "
                              f"chunks[{k}] ({n[k]} frames): chunk {k} must add at least one new frame")
    for k in range(1, K - 1):
        if overlaps[k - 1] + overlaps[k] > n[k]:
            raise StitchError(f"overlap: chunks[{k}] ({n[k]} frames) shares {overlaps[k - 1]} frames with "
                              f"the previous chunk and {overlaps[k]} with the next: a frame would be in "
                              "three chunks")
    ranges, start = [], 0
    for k in range(K):
        if k:
            start = ranges[-1][1] - overlaps[k - 1]
        ranges.append((start, start + n[k]))
    S = ranges[-1][1]
    ts = np.arange(S, dtype=np.float64)
    consistent = all(
        np.all(np.abs(np.asarray(chunks[k].timestamps[:o]) - np.asarray(chunks[k - 1].timestamps[-o:])) <= tol)
        for k, o in enumerate(overlaps, 1))
    if consistent:
        for (a, b), c in zip(ranges, chunks):
            ts[a:b] = c.timestamps
        consistent = bool(np.all(np.diff(ts) > 0))
    if not consistent:
        ts = np.arange(S, dtype=np.float64)
    return ChunkLayout(tuple(ranges), tuple(overlaps), ts)


def blend_weights(ranges, overlaps) -> list[np.ndarray]:
    """Per chunk, per frame fusion weights: 1 inside, ramping across each overlap (sum 1 per frame)."""
    K = len(ranges)
    out = []
    for k, (a, b) in enumerate(ranges):
        w = np.ones(b - a)
        if k > 0:
            o = overlaps[k - 1]
            w[:o] = (np.arange(o) + 0.5) / o
        if k < K - 1:
            o = overlaps[k]
            w[b - a - o:] = 1.0 - (np.arange(o) + 0.5) / o
        out.append(w)
    return out
