"""Atomic file writes (write beside the target, fsync, rename over it), the exclusive lock of a
read-modify-write, and the early writability checks of an output path."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import re
import tempfile
import time
from pathlib import Path

STALE_TEMP_SECONDS = 600.0  # a temporary file of ours this old belongs to a writer that died


def file_mode() -> int:
    """``0o666 & ~umask``: the mode ``open()`` gives a new file (mkstemp's 0600 is not)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)  # no /proc: read the umask by setting it (and put it back at once)
    os.umask(mask)
    return 0o666 & ~mask


def _temp_prefix(path: Path) -> str:
    return f".{path.name}."


def temp_pattern(path: str | os.PathLike) -> re.Pattern:
    """The names :func:`atomic_write` gives its temporary files for ``path`` (``.NAME.XXXXXXXX.tmp``)."""
    return re.compile(re.escape(_temp_prefix(Path(path))) + r"[a-z0-9_]{8}\.tmp")


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb"):
    """Yield a file object; on success it replaces ``path`` atomically (mode ``0o666 & ~umask``), on
    error ``path`` is untouched."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=_temp_prefix(path), suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, file_mode())
        with os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    with contextlib.suppress(OSError):  # the rename itself survives a crash once the folder is synced
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


def remove_stale_temps(path: str | os.PathLike, older_than: float = STALE_TEMP_SECONDS) -> list[Path]:
    """Delete the temporary files :func:`atomic_write` left for ``path`` (a killed writer) that are
    older than ``older_than`` seconds; only names of our own pattern. Returns the files removed."""
    path = Path(path)
    pattern = temp_pattern(path)
    now = time.time()
    removed = []
    with contextlib.suppress(OSError):
        for p in path.parent.iterdir():
            if not pattern.fullmatch(p.name):
                continue
            with contextlib.suppress(OSError):
                if now - p.lstat().st_mtime > older_than and p.is_file():
                    p.unlink()
                    removed.append(p)
    return removed


def lock_path(path: str | os.PathLike) -> Path:
    """The lock file beside ``path``: ``PATH.lock`` (never deleted: deleting a lock file races)."""
    path = Path(path)
    return path.with_name(path.name + ".lock")


@contextlib.contextmanager
def locked(path: str | os.PathLike, timeout: float = 600.0, poll: float = 0.02):
    """Hold an exclusive ``fcntl.flock`` on :func:`lock_path` of ``path`` (other processes and other
    open files of this one wait); ``TimeoutError`` after ``timeout`` seconds. The kernel drops the
    lock when its holder dies, so a killed writer never blocks the next one."""
    lp = lock_path(path)
    lp.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(lp, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        deadline = time.monotonic() + timeout
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except OSError as e:
                if e.errno not in (errno.EAGAIN, errno.EACCES):
                    raise
                if time.monotonic() > deadline:
                    raise TimeoutError(f"{path}: another process has held {lp.name} for over {timeout:.0f} s") from None
                time.sleep(poll)
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock


def _why(e: OSError) -> str:
    return e.strerror or type(e).__name__


def check_writable_folder(folder: str | os.PathLike, what: str) -> Path:
    """Create ``folder`` if needed and prove a file can be written there (a temporary file, removed);
    ``ValueError`` ``"WHAT FOLDER: cannot write there (reason)"`` otherwise. Returns the folder."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{what} {folder}: exists and is not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".cm3d-write-check.", dir=folder)
        os.close(fd)
        os.unlink(tmp)
    except OSError as e:
        raise ValueError(f"{what} {folder}: cannot write there ({_why(e)})") from None
    return folder


def check_writable_file(path: str | os.PathLike, what: str) -> Path:
    """``path`` can be replaced atomically (its folder writable, it is no folder) and its lock file
    opened; ``ValueError`` naming ``what`` otherwise. Creates the folder, never the file."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{what} {path}: is a folder, not a file")
    if path.exists() and not os.access(path, os.R_OK):
        raise ValueError(f"{what} {path}: cannot read it (permission denied)")
    check_writable_folder(path.parent, what=f"{what} {path}: its folder")
    try:
        os.close(os.open(lock_path(path), os.O_RDWR | os.O_CREAT, 0o666))
    except OSError as e:
        raise ValueError(f"{what} {path}: cannot open its lock file {lock_path(path).name} ({_why(e)})") from None
    return path
