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
# Every program into that cache, not only those over JAX's default 1 s of compile time: the suite's
# ~20 processes compile thousands of small programs (eager operations, helpers; 6600 compiles under
# 1 s, 310 s of CPU in one run), many of them the same in several processes.
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
# The CLI's stored programs (cm3d.programs, default ~/.cache/cm3d/programs): per run too, never the user's.
os.environ.setdefault("CM3D_PROGRAM_CACHE", str(Path(tempfile.gettempdir()) / f"cm3d-test-programs-{_RUN}"))

# The whole run compiles at LLVM -O0, in-process tests and the scripts they start alike: compilation
# is most of this suite's CPU time (measured on test_lm + test_pipeline + test_descriptors: 353 s
# of CPU at -O0 vs 411 s at the default), and one flag everywhere lets the persistent cache above
# share a program between a test and an experiment smoke run (the flags are part of its key).
# XLA's HLO passes are the same at every LLVM level and XLA's CPU backend compiles without
# fast-math, so the numerics do not depend on it; the benchmarks under experiments/ never use it.
if "--xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0").strip()
# ... and without LLVM's expensive passes (what ``jax_disable_most_optimizations`` sets beside -O0; LLVM
# only, the HLO the numerics come from is the same): 10-11 % less wall time on test_pipeline + test_lm and on
# four experiment smoke runs (stop 43, each A/B on the same machine, both orders).
if "xla_llvm_disable_expensive_passes" not in os.environ["XLA_FLAGS"]:
    os.environ["XLA_FLAGS"] += " --xla_llvm_disable_expensive_passes=true"
# ... and with XLA's older IR emitters for fusions instead of its MLIR fusion emitters (a code-generation setting;
# the numerics move by float32 round-off: one gradient check's tolerance had to follow): the same wall time for
# one compile alone, but 15 % less CPU (stop 63: the 48x64 memory demo compiled in 64.8 s
# wall / 68.8 s CPU against 64.6 s / 81.2 s), CPU the suite's two workers share; the whole suite on 2 cores:
# 785 s -> 478 s, most of it in the thousands of small programs.
if "xla_cpu_use_fusion_emitters" not in os.environ["XLA_FLAGS"]:
    os.environ["XLA_FLAGS"] += " --xla_cpu_use_fusion_emitters=false"
# The flag cm3d.cli adds for stored programs (cli.XLA_CPU_FLAGS), here too: an in-process cm3d run
# would add it to the environment of the scripts started after it, and flags are part of XLA's key.
if "xla_cpu_parallel_codegen_split_count" not in os.environ["XLA_FLAGS"]:
    os.environ["XLA_FLAGS"] += " --xla_cpu_parallel_codegen_split_count=1"

import jax  # noqa: E402  (after the variable: a jax imported earlier by a plugin gets it here)

jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
jax.config.update("jax_persistent_cache_min_compile_time_secs",
                  float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The project's real data samples: ``../shared/data`` beside the checkout (or $CM3D_SHARED_DATA)."""
    path = Path(os.environ.get("CM3D_SHARED_DATA", ROOT.parent / "shared" / "data"))
    assert path.is_dir(), f"shared test data not found at {path}; set CM3D_SHARED_DATA"
    return path


# The slowest modules first (each holds tests of 15-80 s: compiled pipelines, experiment smoke
# runs), so that the xdist workers, which take the next test as they finish one, end together instead
# of one worker finishing a long test alone at the end of the run.
SLOW_FIRST = ("test_sweep.py", "test_experiments.py", "test_cli.py", "test_rerun.py", "test_pipeline.py",
              "test_align.py", "test_reliability.py", "test_lm.py", "test_memory.py")
# Modules whose tests share a module fixture that compiles a large program (15-30 s): each runs whole
# on one worker, or every worker that takes one of its tests compiles the fixture again (stop 47:
# test_pipeline's ``scanned`` 28 s of set-up on each of the two workers, test_memory's ``visits`` 28 s
# each, test_rerun's ``demo`` 15 s each, in one run). Modules of one unit share it: test_rerun's demo
# and test_pipeline's memory tests compile the same 48x64 memory program (82 s and 52 s when the two
# ran at once on the two workers); one after the other, the second reads it from JAX's cache.
# The same holds for modules whose tests jit the same function with the same configuration (stop 61, a run
# with JAX's compile log: test_recall_real's kitchen fixture, ``_prepare`` and ``identify`` compiled on both
# workers at the same second, 10 s twice; test_motion's and test_occlusion's ``motion_cues``, test_icp's
# ``icp`` and test_lm's ``solve`` twice for the same configuration).
ONE_WORKER = {"test_pipeline.py": "pipeline48", "test_rerun.py": "pipeline48", "test_memory.py": "memory",
              "test_recall_real.py": "recall_real", "test_motion.py": "motion", "test_occlusion.py": "occlusion",
              "test_icp.py": "icp", "test_lm.py": "lm"}


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(SLOW_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(SLOW_FIRST)))


def pytest_xdist_make_scheduler(config, log):
    """``--dist loadgroup``: a unit of work is a test, or the modules of one :data:`ONE_WORKER` unit; the
    workers take the next unit as they finish one, the units with most tests first. (xdist's own
    ``xdist_group`` marks do not group under pytest 9: pytest-dev/pytest-xdist#1386.)"""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class ModuleGroups(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return ONE_WORKER.get(Path(nodeid.split("::", 1)[0]).name, nodeid)

    return ModuleGroups(config, log)
