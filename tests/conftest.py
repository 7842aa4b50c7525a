import os
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# One persistent XLA compilation cache per test run, shared by the xdist workers and by the
# scripts the tests start (they inherit the environment): the pipeline, the solvers and the
# experiments compile the same programs in several processes. Keyed by the run, so every run
# (and CI, from a clean checkout) starts cold and its timings stay honest.
_RUN = os.environ.get("PYTEST_XDIST_TESTRUNUID") or str(os.getpid())
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(Path(tempfile.gettempdir()) / f"cm3d-test-xla-{_RUN}"))
# The CLI points JAX at its own cache (``$CM3D_JAX_CACHE``, default ~/.cache/cm3d/jax): the same
# directory here, or an in-process ``cm3d demo`` would move the whole worker to another cache. The
# directory is part of a program's cache key (JAX's compile options name XLA caches inside it), so
# one directory for everything is what lets a smoke run reuse the program a test compiled.
os.environ["CM3D_JAX_CACHE"] = os.environ["JAX_COMPILATION_CACHE_DIR"]

# The whole run compiles at LLVM -O0, in-process tests and the scripts they start alike: compilation
# is most of this suite's CPU time (measured on test_lm + test_pipeline + test_descriptors: 353 s
# of CPU at -O0 vs 411 s at the default), and one flag everywhere lets the persistent cache above
# share a program between a test and an experiment smoke run (the flags are part of its key).
# XLA's HLO passes are the same at every LLVM level and XLA's CPU backend compiles without
# fast-math, so the numerics do not depend on it; the benchmarks under experiments/ never use it.
#
# Two more compile-time flags, measured on the largest program of the suite (the 48x64 pipeline with
# memory, experiments/camera_pose.py --quick, XLA compile alone): 36.8 s at -O0, 28.1 s with XLA:CPU's
# older elemental emitters instead of its MLIR fusion emitters, 26.2 s with LLVM's expensive passes
# off as well; the figures it prints were the same to the last digit. Neither flag is a promise of
# XLA's, so a jaxlib that no longer knows one (XLA aborts on an unknown flag) runs without both; the
# probe runs once, in the process that starts the run (xdist workers and scripts inherit the result).
_FAST_COMPILE = "--xla_cpu_use_fusion_emitters=false --xla_llvm_disable_expensive_passes=true"


def _xla_accepts(flags: str) -> bool:
    import subprocess
    import sys

    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    probe = "import jax, jax.numpy as jnp; jnp.ones(2).sum().block_until_ready()"
    return subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, timeout=120).returncode == 0


if "--xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    flags = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0").strip()
    if _xla_accepts(f"{flags} {_FAST_COMPILE}"):
        flags = f"{flags} {_FAST_COMPILE}"
    os.environ["XLA_FLAGS"] = flags

import jax  # noqa: E402  (after the variable: a jax imported earlier by a plugin gets it here)

jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The project's real data samples: ``../shared/data`` beside the checkout (or $CM3D_SHARED_DATA)."""
    path = Path(os.environ.get("CM3D_SHARED_DATA", ROOT.parent / "shared" / "data"))
    assert path.is_dir(), f"shared test data not found at {path}; set CM3D_SHARED_DATA"
    return path


# The slowest modules first (each holds tests of 15-80 s: compiled pipelines, experiment smoke
# runs), so that the xdist workers, which steal work from each other (``--dist worksteal``), end
# together instead of one worker finishing a long test alone at the end of the run.
SLOW_FIRST = ("test_sweep.py", "test_experiments.py", "test_cli.py", "test_pipeline.py", "test_align.py",
              "test_lm.py", "test_memory.py")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(SLOW_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(SLOW_FIRST)))
