"""cm3d.programs: stored executables give the results of tracing afresh, and a changed
configuration, jax version or source never loads a stale one."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cm3d import programs
from cm3d.eval import metrics


@dataclasses.dataclass(frozen=True)
class _Cfg:
    power: int = 2
    scale: float = 0.5


@functools.partial(jax.jit, static_argnames="cfg")
def _program(x, y, cfg: _Cfg = _Cfg()):
    return {"a": jnp.sum(jnp.sin(x) ** cfg.power) * cfg.scale + y @ y.T, "b": jnp.cumsum(x)}


@pytest.fixture
def cache(tmp_path):
    before = programs.cache_dir()
    programs.set_cache_dir(tmp_path)
    programs.clear_memory()
    yield tmp_path
    programs.set_cache_dir(before)  # the suite's folder ($CM3D_PROGRAM_CACHE), for the tests after these
    programs.clear_memory()


def _args(seed=0):
    r = np.random.default_rng(seed)
    return r.normal(size=64).astype(np.float32), r.normal(size=(8, 3)).astype(np.float32)


def _equal(a, b):
    return jax.tree.structure(a) == jax.tree.structure(b) and all(
        np.array_equal(np.asarray(u), np.asarray(v)) for u, v in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def test_loaded_program_equals_tracing_afresh(cache):
    x, y = _args()
    _, how = programs.compiled("p", _program, {"cfg": _Cfg()}, x, y)
    assert how == "compiled" and len(list(cache.glob("p-*.jaxexe"))) == 1
    programs.clear_memory()  # as a second process: from the file, not traced
    prog, how = programs.compiled("p", _program, {"cfg": _Cfg()}, x, y)
    assert how == "loaded"
    assert programs.compiled("p", _program, {"cfg": _Cfg()}, x, y)[1] == "memory"
    x2, y2 = _args(1)
    assert _equal(prog(x2, y2), _program(x2, y2, cfg=_Cfg()))  # bitwise, on other values too
    # the trajectory metrics (float64, a pytree of results) through the cache equal the plain jit
    est, gt = np.tile(np.eye(4), (6, 1, 1)), np.tile(np.eye(4), (6, 1, 1))
    est[:, :3, 3] = np.random.default_rng(2).normal(size=(6, 3))
    gt[:, :3, 3] = est[:, :3, 3] * 2 + 0.01
    with jax.enable_x64(True):
        fresh = metrics._trajectory_metrics_jit(jnp.asarray(est), jnp.asarray(gt))
        programs.call("traj", metrics._trajectory_metrics_jit, {}, jnp.asarray(est), jnp.asarray(gt))
        programs.clear_memory()
        loaded = programs.call("traj", metrics._trajectory_metrics_jit, {}, jnp.asarray(est), jnp.asarray(gt))
    assert _equal(fresh, loaded)


def test_changed_config_version_or_source_never_loads_a_stale_program(cache, monkeypatch):
    x, y = _args()
    programs.compiled("p", _program, {"cfg": _Cfg()}, x, y)
    programs.clear_memory()
    other = _Cfg(power=3)
    prog, how = programs.compiled("p", _program, {"cfg": other}, x, y)
    assert how == "compiled" and _equal(prog(x, y), _program(x, y, cfg=other))
    assert programs.compiled("p", _program, {"cfg": _Cfg()}, x[:32], y)[1] == "compiled"  # other shape
    env = programs.environment()
    for field, value in (("jax", "0.0.1"), ("jaxlib", "0.0.1"), ("source", "0" * 64), ("platform", "tpu")):
        key = programs.program_key("p", (("cfg", _Cfg()),), (x, y), {**env, field: value})
        assert key != programs.program_key("p", (("cfg", _Cfg()),), (x, y), env), field
    programs.clear_memory()
    monkeypatch.setattr(jax, "__version__", "0.0.1")  # another jax: its key names no stored file
    assert programs.compiled("p", _program, {"cfg": _Cfg()}, x, y)[1] == "compiled"
    monkeypatch.undo()
    # a file whose stored key is another's (a truncated-name clash) is not loaded
    programs.clear_memory()
    real = programs.program_key("p", (("cfg", _Cfg()),), (x, y))
    path = programs._path("p", real)
    wrong = programs._path("p", programs.program_key("p", (("cfg", other),), (x, y)))
    path.write_bytes(wrong.read_bytes())
    prog, how = programs.compiled("p", _program, {"cfg": _Cfg()}, x, y)
    assert how == "compiled" and _equal(prog(x, y), _program(x, y, cfg=_Cfg()))


def test_a_damaged_file_is_compiled_afresh(cache):
    x, y = _args()
    programs.compiled("p", _program, {"cfg": _Cfg()}, x, y)
    (path,) = cache.glob("p-*.jaxexe")
    path.write_bytes(b"not a program")
    programs.clear_memory()
    with pytest.warns(UserWarning, match="unreadable"):
        prog, how = programs.compiled("p", _program, {"cfg": _Cfg()}, x, y)
    assert how == "compiled" and _equal(prog(x, y), _program(x, y, cfg=_Cfg()))
    programs.clear_memory()
    assert programs.compiled("p", _program, {"cfg": _Cfg()}, x, y)[1] == "loaded"  # rewritten


def test_without_a_folder_programs_stay_in_memory(tmp_path):
    before = programs.cache_dir()
    programs.set_cache_dir(None)
    programs.clear_memory()
    try:
        x, y = _args()
        assert programs.compiled("p", _program, {"cfg": _Cfg()}, x, y)[1] == "compiled"
        assert programs.compiled("p", _program, {"cfg": _Cfg()}, x, y)[1] == "memory"
        assert not list(tmp_path.iterdir())
    finally:  # the suite's folder for the tests after this one, pass or fail
        programs.clear_memory()
        programs.set_cache_dir(before)


def test_a_process_started_with_the_variable_uses_its_folder(tmp_path):
    import os
    import subprocess
    import sys

    code = "from cm3d import programs; print(programs.cache_dir())"
    for value, want in ((str(tmp_path), str(tmp_path)), ("off", "None")):
        env = {**os.environ, "CM3D_PROGRAM_CACHE": value}
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
        assert out.stdout.strip() == want
    env = {k: v for k, v in os.environ.items() if k != "CM3D_PROGRAM_CACHE"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "None"  # the library's default: in memory


def test_the_prefetched_piece_is_shaped_like_the_prepared_one():
    """pipeline.run loads the pieces' program from piece_spec before any OpenCV work: its key must
    be the prepared piece's (else the prefetch loads a program nobody calls)."""
    from cm3d import pipeline
    from cm3d.data import synthetic
    from cm3d.pipeline.prepare import piece_spec

    cfg = pipeline.small_config()
    seq = synthetic.generate(0, 0, 6, "moderate", synthetic.WorldConfig(height=48, width=64))
    _, piece = next(pipeline.prepare_chunks(seq, cfg))
    spec = piece_spec(seq, cfg)
    x = jax.tree.map(jnp.asarray, piece)
    assert programs.program_key("p", (), spec) == programs.program_key("p", (), x)


def test_a_persistent_cache_hit_is_stored_with_its_own_bytes(cache):
    """An executable JAX serves from its persistent cache re-serialises without some kernels (loaded,
    it failed with "Function wrapped_iota not found"), and a process whose program key is new (a
    source edit leaves the HLO unchanged) meets only such hits. compiled() stores the cache entry's
    own bytes: the stored program loads in a fresh state and gives the plain jit's results bitwise."""
    from jax._src import compilation_cache

    assert programs._HIT_RECORDER
    assert compilation_cache.is_cache_used(jax.devices()[0].client), "conftest turns JAX's cache on"
    f = jax.jit(lambda x: (jnp.cumsum(x[3:17] * 2.0)[::2], jnp.arange(5.0) * x[0]))  # slices, an iota
    x = jnp.arange(32, dtype=jnp.float32)
    old = (jax.config.jax_persistent_cache_min_compile_time_secs, jax.config.jax_persistent_cache_min_entry_size_bytes)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    try:
        want = f.lower(x).compile()(x)  # into JAX's persistent cache (or from it, on a rerun)
        jax.clear_caches()
        hits = programs._hits()
        prog, how = programs.compiled("sliced", f, {}, x)  # its persistent-cache hit
        assert how == "compiled" and programs._hits() > hits
        assert _equal(prog(x), want)
        assert len(list(cache.glob("sliced-*.jaxexe"))) == 1, "the cache hit was not stored"
        programs.clear_memory()
        jax.clear_caches()
        prog, how = programs.compiled("sliced", f, {}, x)
        assert how == "loaded"
        x2 = jnp.linspace(-3.0, 5.0, 32, dtype=jnp.float32)
        assert _equal(prog(x2), f(x2))
    finally:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", old[0])
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", old[1])


def test_an_executable_jax_holds_from_an_earlier_cache_hit_is_stored_with_the_entrys_bytes(cache):
    """A plain jit call that JAX served from its persistent cache leaves the executable in JAX's
    in-process cache; compiled() then gets that executable without a backend step. Re-serialised,
    such an executable lost kernels ("Function wrapped_slice not found" when the stored file was
    loaded and run: the suite's order met it at stop 47); the cache entry's bytes, kept when JAX
    read them, are stored instead, and the stored file loads and runs."""
    f = jax.jit(lambda x: (jnp.cumsum(x[5:21] * 3.0)[::3], jnp.arange(7.0) * x[1]))
    x = jnp.arange(40, dtype=jnp.float32)
    old = (jax.config.jax_persistent_cache_min_compile_time_secs, jax.config.jax_persistent_cache_min_entry_size_bytes)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    try:
        f(x)  # into JAX's persistent cache (or from it, on a rerun)
        jax.clear_caches()
        hits = programs._hits()
        want = f(x)  # a persistent-cache hit, kept in memory by JAX
        assert programs._hits() > hits
        prog, how = programs.compiled("held", f, {}, x)
        assert how == "compiled" and _equal(prog(x), want)
        assert len(list(cache.glob("held-*.jaxexe"))) == 1
        programs.clear_memory()
        prog, how = programs.compiled("held", f, {}, x)
        assert how == "loaded" and _equal(prog(x), want)
    finally:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", old[0])
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", old[1])


def test_the_folder_keeps_the_most_recently_used_programs_per_name(cache, monkeypatch):
    """Every source edit stores new files: each name keeps its programs.KEEP most recently stored or
    loaded ones, and other names' files are untouched."""
    import os

    monkeypatch.setattr(programs, "KEEP", 3)
    x, y = _args()
    programs.compiled("q", _program, {"cfg": _Cfg()}, x, y)  # another name: never pruned by "p"
    sizes = (8, 16, 24, 32, 40)
    for n in sizes[:3]:
        programs.compiled("p", _program, {"cfg": _Cfg()}, x[:n], y)
    first = programs._path("p", programs.program_key("p", (("cfg", _Cfg()),), (x[:8], y)))
    for f in cache.glob("*.jaxexe"):  # distinct times on a coarse clock: the order they were stored
        os.utime(f, (1000.0, 1000.0 + (0 if f == first else 1)))
    programs.clear_memory()
    assert programs.compiled("p", _program, {"cfg": _Cfg()}, x[:8], y)[1] == "loaded"  # now the newest
    for n in sizes[3:]:
        programs.compiled("p", _program, {"cfg": _Cfg()}, x[:n], y)
    kept = sorted(cache.glob("p-*.jaxexe"))
    assert len(kept) == 3 and first in kept
    assert len(list(cache.glob("q-*.jaxexe"))) == 1
