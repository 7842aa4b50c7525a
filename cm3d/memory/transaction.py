"""Bank writes as transactions (host side): concurrent runs on one bank file never lose a map.

A run reads a :class:`Snapshot` (no lock: a save replaces the file by a rename, so a reader sees a
whole bank), works for as long as it needs, then :func:`commit`\\ s: under an exclusive ``flock`` on
``BANK.lock`` it re-reads the bank, applies the maps this run changed (slots that differ from its
snapshot) onto the fresh bank, and writes it atomically. When another process wrote the bank in
between, the change is a three-way merge per map slot: a slot only this run changed is written in
place; a slot both changed (this run's recall decision was taken against a map that changed since,
or both stored a new map in the same free slot) keeps the other writer's map, and this run's map is
appended in a free slot. :class:`CommitReport` says where each map went (``recall.json`` holds it).
:func:`modify` is the read-modify-write of a whole bank under the same lock (``cm3d memory rm``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from pathlib import Path
from typing import Callable

import jax.numpy as jnp
import numpy as np

from cm3d.data.atomic import check_writable_file, locked
from cm3d.memory.bank import MemoryBank, empty
from cm3d.memory.config import MemoryConfig, MemoryFileError
from cm3d.memory.io import _fields, read, save


@dataclasses.dataclass(frozen=True, eq=False)
class Snapshot:
    """The bank a run starts from: ``bank``/``cfg`` (None when there is no file yet), ``digest`` of the
    file read (None: none), the file's format version and its note (:class:`~cm3d.memory.io.StoredBank`)."""

    path: str
    bank: MemoryBank | None = None
    cfg: MemoryConfig | None = None
    digest: str | None = None
    version: int | None = None
    note: str | None = None


def snapshot(path) -> Snapshot:
    """Read the bank at ``path`` (an empty snapshot when there is no file); takes no lock."""
    path = os.fspath(path)
    if not os.path.exists(path):
        return Snapshot(path)
    s = read(path)
    return Snapshot(path, s.bank, s.cfg, s.digest, s.version, s.note)


def check_bank_path(path) -> Path:
    """Fail early (``ValueError``, one line) when the bank at ``path`` could not be written later."""
    return check_writable_file(path, "--memory")


@dataclasses.dataclass(frozen=True)
class MapWrite:
    """Where one map this run changed went: ``run_map`` (its slot in the run's bank), ``bank_map``
    (its slot in the saved bank; -1: not stored), ``action`` ("new", "updated", "appended" or "not
    stored") and why."""

    run_map: int
    bank_map: int
    action: str
    reason: str = ""


@dataclasses.dataclass(frozen=True)
class CommitReport:
    """What :func:`commit` wrote: whether another process changed the bank after this run read it,
    one :class:`MapWrite` per map this run changed, the maps in the saved bank, the format version
    that was rewritten (None: none) and the stale temporary files removed."""

    path: str
    bank_changed: bool
    maps: tuple = ()
    num_maps: int = 0
    upgraded_from: int | None = None
    removed_temps: int = 0

    def bank_map(self, run_map: int) -> int:
        """The saved slot of the run's map ``run_map`` (itself when this run did not change it)."""
        for w in self.maps:
            if w.run_map == run_map:
                return w.bank_map
        return run_map

    def to_json(self) -> dict:
        return {"bank": self.path, "bank_changed": self.bank_changed, "num_maps": self.num_maps,
                "maps": [dataclasses.asdict(w) for w in self.maps], "upgraded_from": self.upgraded_from,
                "removed_temps": self.removed_temps}


def _slot_digests(arrays: dict[str, np.ndarray]) -> list[bytes]:
    """SHA-256 of every map slot (all per-map fields; the hash planes are the bank's, not a map's)."""
    names = [k for k in arrays if k != "planes"]
    M = arrays["map_valid"].shape[0]
    out = []
    for m in range(M):
        h = hashlib.sha256()
        for k in names:
            h.update(np.ascontiguousarray(arrays[k][m]).tobytes())
        out.append(h.digest())
    return out


def _same_layout(a: dict, b: dict) -> bool:
    return all(a[k].shape == b[k].shape and a[k].dtype == b[k].dtype for k in a) and np.array_equal(a["planes"],
                                                                                                   b["planes"])


def merge_banks(base: MemoryBank, ours: MemoryBank, theirs: MemoryBank) -> tuple[MemoryBank, tuple]:
    """Three-way merge per map slot (host): ``theirs`` with the slots ``ours`` changed since ``base``
    written in place when ``theirs`` left them as in ``base`` (or made them equal), else appended in
    a free slot (not stored when none is left). Returns (bank, MapWrite per changed slot)."""
    b, o, t = _fields(base), _fields(ours), _fields(theirs)
    if not (_same_layout(o, t) and _same_layout(o, b)):
        raise MemoryFileError("the bank was replaced by one of other capacities or hash planes while this run "
                              "worked; this run's maps were not stored")
    db, do, dt = _slot_digests(b), _slot_digests(o), _slot_digests(t)
    result = {k: np.array(v) for k, v in t.items()}
    names = [k for k in result if k != "planes"]

    def put(src: int, dst: int):
        for k in names:
            result[k][dst] = o[k][src]

    writes, conflicts = [], []
    for m in range(len(do)):
        if do[m] == db[m]:
            continue
        if dt[m] == db[m] or dt[m] == do[m]:
            put(m, m)
            if o["map_valid"][m]:
                writes.append(MapWrite(m, m, "updated" if b["map_valid"][m] else "new"))
        else:
            conflicts.append(m)
    for m in conflicts:
        if not o["map_valid"][m]:
            continue  # this run freed a slot another writer changed since: theirs stays
        why = (f"slot {m} changed in the bank after this run read it"
               + (" (this run had updated that map: its copy, with this visit merged, is a new map)"
                  if b["map_valid"][m] else ""))
        free = np.flatnonzero(~result["map_valid"])
        if len(free) == 0:
            writes.append(MapWrite(m, -1, "not stored", why + "; the bank is full"))
            continue
        put(m, int(free[0]))
        writes.append(MapWrite(m, int(free[0]), "appended", why))
    return MemoryBank(**{k: jnp.asarray(v) for k, v in result.items()}), tuple(sorted(writes, key=lambda w: w.run_map))


def commit(path, base: Snapshot, bank: MemoryBank, cfg: MemoryConfig) -> tuple[MemoryBank, CommitReport]:
    """Store what this run changed in ``bank`` (relative to the snapshot ``base`` it started from) in
    the bank file at ``path``, as one transaction (see the module docstring). Nothing is written when
    this run changed no map. Returns (the saved bank, :class:`CommitReport`)."""
    path = os.fspath(path)
    with locked(path):
        current = snapshot(path)
        changed = current.digest != base.digest
        start = base.bank if base.bank is not None else empty(cfg)
        if current.bank is None:
            theirs, cfg_out = (start if not changed else empty(cfg)), cfg
        else:
            theirs, cfg_out = current.bank, current.cfg
        if not changed:
            o, s = _fields(bank), _fields(start)
            if not _same_layout(o, s):
                raise MemoryFileError(f"{path}: this run's bank has other capacities than the one it read")
            do, ds = _slot_digests(o), _slot_digests(s)
            writes = tuple(MapWrite(m, m, "updated" if s["map_valid"][m] else "new")
                           for m in range(len(do)) if do[m] != ds[m] and o["map_valid"][m])
            merged = bank
            touched = any(do[m] != ds[m] for m in range(len(do)))
        else:
            try:
                merged, writes = merge_banks(start, bank, theirs)
            except MemoryFileError as e:
                raise MemoryFileError(f"{path}: {e}") from None
            touched = bool(writes)
        if not touched:
            return theirs, CommitReport(path, changed, (), int(np.sum(np.asarray(theirs.map_valid))))
        removed = save(merged, path, cfg_out)
    return merged, CommitReport(path, changed, writes, int(np.sum(np.asarray(merged.map_valid))),
                                upgraded_from=current.version if current.version is not None and current.version < 4 else None,
                                removed_temps=len(removed))


def modify(path, change: Callable[[MemoryBank, MemoryConfig], MemoryBank]) -> tuple[MemoryBank, MemoryConfig]:
    """Read the bank at ``path``, apply ``change(bank, cfg) -> bank`` and save it, all under the bank's
    lock (so no concurrent commit is lost). Returns (the saved bank, its config)."""
    with locked(path):
        s = read(path)
        new = change(s.bank, s.cfg)
        save(new, path, s.cfg)
    return new, s.cfg

