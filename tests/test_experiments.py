"""Smoke test: every script in experiments/ runs with --quick and writes its headline JSON.

Scripts that compile the same programs run in one process, one after the other (as
``python experiments/X.py --quick --json F`` would, through :func:`runpy.run_path`): the later
ones reuse the compiled pipeline instead of tracing and compiling it again (camera_pose.py's
revisit runs serve reconstruction.py and video_depth.py, and since stop 46 these run ``pipeline.run``
as held_out_world.py, long_sequence.py and real_kitchen.py do: one 48x64 ``config_for`` program for all
six, 88 s in one process against 60 + 86 s in two; descriptor_3d.py builds memory_recall.py's
banks); the small scripts share one process in two groups, which saves an interpreter start and the
imports each, and the eager helpers they compile alike (stop 43: 146 s -> 119 s of worker time)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
COVERED_ELSEWHERE = {
    "sweep.py": "tests/test_sweep.py runs it with --quick --json and checks its figures",
    "bench_motion.py": "bench_all.py --quick runs it with --quick --json and fails when it fails",
    "bench_rerun.py": "tests/test_rerun.py::test_bench_rerun_quick_in_the_demos_process runs its main --quick "
                      "--json after the demo compiled the same pipeline",
    "sensor_holes.py": "tests/test_reliability.py::test_hole_heavy_depth_refines runs its --quick case (scene 5, "
                       "48x64, blobs) through the same pipeline.run",
}
GROUPS = [("camera_pose.py", "reconstruction.py", "video_depth.py", "held_out_world.py", "long_sequence.py",
           "real_kitchen.py"),
          ("memory_recall.py", "descriptor_3d.py"),
          ("bench_backend.py", "motion_masks.py", "pose_refine.py", "prior_noise.py"),
          ("bench_icp.py", "long_video.py", "davis_track.py", "bank_concurrency.py", "sevenscenes_calibration.py")]
SCRIPTS = sorted(p.name for p in (ROOT / "experiments").glob("*.py")
                 if not p.name.startswith("_") and p.name not in COVERED_ELSEWHERE)
GROUPED = {s for g in GROUPS for s in g}
RUNS = GROUPS + [(s,) for s in SCRIPTS if s not in GROUPED]

# One process runs the scripts of a group in order, each as its own __main__ with its own argv.
MARK = "\n@@ cm3d smoke: "
_RUNNER = f"MARK = {MARK!r}\n" + """
import runpy, sys
sys.path.insert(0, sys.argv[1])
for script, out in zip(sys.argv[2::2], sys.argv[3::2]):
    sys.argv = [script, "--quick", "--json", out]
    print(f"{MARK}{script}", flush=True)
    try:
        runpy.run_path(script, run_name="__main__")
    except SystemExit as err:
        if err.code:
            raise
"""


def test_every_script_is_smoke_tested():
    assert GROUPED <= set(SCRIPTS), GROUPED - set(SCRIPTS)
    assert sorted(s for run in RUNS for s in run) == SCRIPTS


@pytest.mark.parametrize("scripts", RUNS, ids=lambda g: "+".join(g))
def test_experiment_quick(scripts, tmp_path):
    outs = [tmp_path / f"{Path(s).stem}.json" for s in scripts]
    args = [a for s, o in zip(scripts, outs) for a in (str(ROOT / "experiments" / s), str(o))]
    proc = subprocess.run([sys.executable, "-c", _RUNNER, str(ROOT / "experiments"), *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=300 * len(scripts))
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]
    printed = ("\n" + proc.stdout).split(MARK)[1:]
    assert len(printed) == len(scripts)
    for script, text, out in zip(scripts, printed, outs):
        assert text.split("\n", 1)[1].strip(), f"{script} prints a readable table"
        figures = json.loads(out.read_text())
        assert isinstance(figures, dict) and figures, f"{script}: headline figures, one flat JSON object"
        assert all(not isinstance(v, (dict, list)) for v in figures.values()), f"{script}: the JSON object is flat"
