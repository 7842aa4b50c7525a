"""Compiled programs kept between processes: a jitted function lowered and compiled once for a
configuration and argument shapes is serialised (``jax.experimental.serialize_executable``) to a
cache folder, and a later process loads the executable instead of tracing, lowering and compiling
it again. The file's key hashes everything that decides the program: its name, the static
configuration's ``repr``, the arguments' tree structure, shapes and dtypes, the jax and jaxlib
versions, the backend (platform, version, device kind and count), the x64 flag, ``$XLA_FLAGS`` and
the source of every ``cm3d`` module; a file whose stored key differs is never loaded (it is compiled afresh and
overwritten). Without a folder (:func:`set_cache_dir` ``None``, the library's default) a program is
compiled in memory once per process, like ``jax.jit``. A program JAX serves from its persistent
compilation cache is stored too, with the cache entry's own bytes. Host side only: nothing here is
traced."""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import threading
import warnings
from pathlib import Path

import jax
import numpy as np
from jax._src.lib import _jax, xla_client
from jax.experimental import serialize_executable

FORMAT = 1  # bump when the file layout changes
KEEP = 12  # stored files per program name: the most recently stored or loaded (older source versions go)
_lock = threading.Lock()
_state = {"dir": None, "source": None}  # "dir": set at the end of the module, from the environment
_loaded: dict = {}  # key -> jax.stages.Compiled, this process's programs


_thread = threading.local()


def _install_hit_recorder() -> bool:
    """Wrap JAX's persistent-cache reader so that the bytes of every executable JAX takes from that
    cache are kept (:data:`_raw`). Such an executable re-serialised by
    ``serialize_executable.serialize`` loses kernels on XLA:CPU (jax 0.10: the loaded copy fails
    with "Function wrapped_iota not found"); the cache entry's own bytes load and run (JAX loads
    them the same way). Records only inside JAX's compile step (:func:`_install_hit_marker`);
    without the reader (another jax) nothing is recorded and such a program is not stored."""
    try:
        from jax._src import compilation_cache as cc

        read = cc.extract_executable_and_time
    except (ImportError, AttributeError):
        return False

    def recording(blob):
        serialized, compile_time = read(blob)
        if getattr(_thread, "recording", None) is not None:
            _thread.recording.append(serialized)
        return serialized, compile_time

    cc.extract_executable_and_time = recording
    return True


_HIT_RECORDER = _install_hit_recorder()


def _count_hit(event: str, **_) -> None:
    if event == "/jax/compilation_cache/cache_hits":  # recorded in the thread that compiles
        _thread.hits = getattr(_thread, "hits", 0) + 1


jax.monitoring.register_event_listener(_count_hit)


def _hits() -> int:
    """This thread's count of JAX persistent-cache hits so far."""
    return getattr(_thread, "hits", 0)


_raw: dict = {}  # fingerprint -> cache-entry bytes of each executable JAX took from its persistent cache here


def _identity(executable):
    """An executable's XLA fingerprint (its program's; ``id`` where the backend gives none)."""
    try:
        fp = executable.fingerprint
    except Exception:  # noqa: BLE001
        fp = None
    return fp if fp is not None else id(executable)


def _install_hit_marker() -> bool:
    """Wrap JAX's compile step so that every executable it takes from the persistent cache, in any
    call of this process, is known as such, with the cache entry's bytes. JAX keeps executables in
    memory: a plain jit call served by that cache, then :func:`compiled` of the same function, gives
    :func:`compiled` the kept executable with no compile step; the bytes kept here store it."""
    try:
        from jax._src import compiler
    except ImportError:
        return False
    step = getattr(compiler, "compile_or_get_cached", None)
    if step is None:
        return False

    def marking(*args, **kwargs):
        hits, outer, _thread.recording = _hits(), getattr(_thread, "recording", None), []
        try:
            executable = step(*args, **kwargs)
        finally:
            served, _thread.recording = _thread.recording, outer
        if _hits() > hits:
            _raw[_identity(executable)] = served[0] if len(served) == 1 else None
        return executable

    compiler.compile_or_get_cached = marking
    return True


_HIT_MARKER = _install_hit_marker()


def _served_from_cache(prog) -> tuple[bool, bytes | None]:
    """Whether ``prog``'s executable came from JAX's persistent cache (unknown: assumed so), and
    that cache entry's bytes (None: unknown)."""
    executable = getattr(prog._executable, "xla_executable", None)
    if not (_HIT_MARKER and _HIT_RECORDER) or executable is None:
        return True, None
    fp = _identity(executable)
    return fp in _raw, _raw.get(fp)


def set_cache_dir(path) -> None:
    """Keep serialised programs in ``path`` (created on the first write); ``None``: in memory only."""
    _state["dir"] = None if path is None else Path(path)


def cache_dir() -> Path | None:
    """The folder :func:`set_cache_dir` set (None: programs stay in memory)."""
    return _state["dir"]


def source_digest() -> str:
    """SHA-256 of every ``cm3d/**/*.py`` (relative path and bytes, sorted): any edit to the package,
    a traced module or not, changes every key."""
    if _state["source"] is None:
        root = Path(__file__).resolve().parent
        h = hashlib.sha256()
        for p in sorted(root.rglob("*.py")):
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
        _state["source"] = h.hexdigest()
    return _state["source"]


def environment() -> dict:
    """What besides the arguments decides a compiled program: versions, backend, flags, source."""
    import jaxlib

    dev = jax.devices()[0]
    return {"format": FORMAT, "jax": jax.__version__, "jaxlib": jaxlib.__version__,
            "platform": dev.platform, "platform_version": dev.client.platform_version,
            "device_kind": dev.device_kind, "devices": jax.device_count(),
            "x64": bool(jax.config.jax_enable_x64), "xla_flags": os.environ.get("XLA_FLAGS", ""),
            "source": source_digest()}


def _signature(args) -> tuple[str, list]:
    leaves, tree = jax.tree.flatten(args)
    return str(tree), [(tuple(np.shape(x)), str(x.dtype if hasattr(x, "dtype") else np.asarray(x).dtype),
                        bool(getattr(x, "weak_type", False))) for x in leaves]


def program_key(name: str, static, args, env: dict | None = None) -> str:
    """The hex key of program ``name`` compiled with ``static`` (its ``repr`` is hashed) for
    arguments shaped like ``args`` in environment ``env`` (default :func:`environment`)."""
    tree, avals = _signature(args)
    env = environment() if env is None else env
    h = hashlib.sha256()
    for part in (name, repr(static), tree, repr(avals), repr(sorted(env.items()))):
        h.update(part.encode())
        h.update(b"\0")
    return h.hexdigest()


def _path(name: str, key: str) -> Path:
    return _state["dir"] / f"{name}-{key[:40]}.jaxexe"


def _runtime_ready() -> None:
    """What lowering would have set up in this process: the LAPACK kernels that CPU programs call
    (jaxlib fills their pointers when a program using them is lowered; a loaded program is not)."""
    try:
        from jax._src.lax import linalg

        linalg.initialize_lapack()
    except Exception:  # noqa: BLE001  another jaxlib: its loaded programs are checked by the tests
        pass


def _load(path: Path, key: str):
    try:
        with open(path, "rb") as f:
            stored_key, payload, in_tree, out_tree = pickle.load(f)
    except FileNotFoundError:
        return None
    except Exception as err:  # noqa: BLE001  a damaged file: compile afresh and overwrite it
        warnings.warn(f"program cache: {path} unreadable ({type(err).__name__}: {err}); compiling afresh",
                      stacklevel=3)
        return None
    if stored_key != key:
        return None
    try:
        os.utime(path)  # used: the last to be pruned
    except OSError:
        pass
    _runtime_ready()
    try:
        return serialize_executable.deserialize_and_load(payload, in_tree, out_tree)
    except Exception as err:  # noqa: BLE001  an executable this runtime cannot load
        warnings.warn(f"program cache: {path} not loadable ({type(err).__name__}: {err}); compiling afresh",
                      stacklevel=3)
        return None


class _RawPickler(serialize_executable._JaxPjrtPickler):
    """``serialize_executable``'s pickler, with the program's one executable written as the given
    bytes (``raw``, JAX's persistent-cache entry) instead of re-serialised."""

    def __init__(self, file, raw: bytes):
        super().__init__(file)
        self.raw, self.used = raw, 0

    def persistent_id(self, obj):
        if isinstance(obj, (xla_client.LoadedExecutable, _jax.Executable)):
            self.used += 1
            return ("exec", self.raw)
        return super().persistent_id(obj)


def _serialize(compiled, raw: bytes | None) -> tuple[bytes, object, object]:
    """``serialize_executable.serialize(compiled)``; with ``raw``, the executable's bytes as JAX's
    persistent cache holds them."""
    if raw is None:
        return serialize_executable.serialize(compiled)
    unloaded = getattr(compiled._executable, "_unloaded_executable", None)
    if unloaded is None or compiled._params.const_args:
        raise ValueError("compilation does not support serialization")
    args_info_flat, in_tree = jax.tree.flatten(compiled.args_info)
    with io.BytesIO() as f:
        pickler = _RawPickler(f, raw)
        pickler.dump((unloaded, args_info_flat, compiled._no_kwargs))
        if pickler.used != 1:
            raise ValueError(f"{pickler.used} executables in the program, one expected")
        return f.getvalue(), in_tree, compiled.out_tree


def _store(path: Path, key: str, compiled, raw: bytes | None = None) -> None:
    from cm3d.data.atomic import atomic_write

    try:
        payload, in_tree, out_tree = _serialize(compiled, raw)
        blob = pickle.dumps((key, payload, in_tree, out_tree), protocol=pickle.HIGHEST_PROTOCOL)
        with atomic_write(path) as f:
            f.write(blob)
        _prune(path)
    except Exception as err:  # noqa: BLE001  a cache that cannot be written only costs time
        warnings.warn(f"program cache: could not write {path} ({type(err).__name__}: {err})", stacklevel=3)


def _prune(path: Path) -> None:
    """Keep the :data:`KEEP` most recently used files of ``path``'s program name (every source edit
    or upgrade stores new ones: the folder stays bounded)."""
    name = path.name[: -len("-") - 40 - len(".jaxexe")]
    files = []
    for p in path.parent.glob(f"{name}-*.jaxexe"):
        if len(p.name) == len(path.name):  # this name's files only (another name may share the prefix)
            try:
                files.append((p.stat().st_mtime, p))
            except FileNotFoundError:  # removed by another process meanwhile
                pass
    for _, p in sorted(files, reverse=True)[KEEP:]:
        p.unlink(missing_ok=True)


def compiled(name: str, fn, static: dict, *args):
    """The compiled ``fn`` (a ``jax.jit`` function) for ``static`` keyword arguments and arguments
    shaped like ``args``: from this process's table, else from the cache folder, else lowered and
    compiled (and stored). Returns ``(a jax.stages.Compiled to call with *args, how)``, ``how``
    one of "memory", "loaded", "compiled"."""
    key = program_key(name, tuple(sorted(static.items())), args)
    with _lock:
        prog = _loaded.get(key)
        if prog is not None:
            return prog, "memory"
        how = "loaded"
        prog = _load(_path(name, key), key) if _state["dir"] is not None else None
        if prog is None:
            how = "compiled"
            prog = fn.lower(*args, **static).compile()
            if _state["dir"] is not None:
                cached, raw = _served_from_cache(prog)
                if not cached:  # compiled in this process, now or earlier (kept by JAX)
                    _store(_path(name, key), key, prog)
                elif raw is not None:  # from JAX's persistent cache, now or earlier: the entry's bytes
                    _store(_path(name, key), key, prog, raw)
                # else: from that cache, bytes unknown (another jax): not stored
        _loaded[key] = prog
        return prog, how


def call(name: str, fn, static: dict, *args):
    """``fn(*args, **static)`` through :func:`compiled` (the result of the same program)."""
    return compiled(name, fn, static, *args)[0](*args)


def discard(name: str, static: dict, *args) -> None:
    """Forget program ``name`` for these arguments, in memory and on disk (one that loads but fails
    to run): the next :func:`compiled` traces and compiles it again, and stores the new one."""
    key = program_key(name, tuple(sorted(static.items())), args)
    with _lock:
        _loaded.pop(key, None)
        if _state["dir"] is not None:
            _path(name, key).unlink(missing_ok=True)


def clear_memory() -> None:
    """Forget this process's compiled programs (the next call loads or compiles again); tests."""
    with _lock:
        _loaded.clear()


def prefetch(name: str, fn, static: dict, *args) -> threading.Thread:
    """Start :func:`compiled` in a thread (loading a stored executable overlaps host work);
    ``args`` may be ``jax.ShapeDtypeStruct`` trees. Returns the started thread."""
    t = threading.Thread(target=compiled, args=(name, fn, static, *args), daemon=True)
    t.start()
    return t


def dir_from_env(default) -> Path | None:
    """The folder named by ``$CM3D_PROGRAM_CACHE`` (``off``/``0``/empty: None), else ``default``."""
    path = os.environ.get("CM3D_PROGRAM_CACHE")
    if path is None:
        return None if default is None else Path(default)
    return None if path.lower() in ("", "0", "off", "none") else Path(path)


# A process started with $CM3D_PROGRAM_CACHE set keeps its programs there from the start (an
# experiment, a notebook, the test suite's scripts); unset, the library keeps them in memory.
set_cache_dir(dir_from_env(None))
