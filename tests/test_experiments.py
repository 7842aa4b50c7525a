"""Smoke test: every script in experiments/ runs with --quick and writes its headline JSON."""

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
SCRIPTS = sorted(p for p in (ROOT / "experiments").glob("*.py")
                 if not p.name.startswith("_") and p.name not in COVERED_ELSEWHERE)


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_experiment_quick(script, tmp_path):
    out = tmp_path / "figures.json"
    proc = subprocess.run([sys.executable, str(script), "--quick", "--json", str(out)], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]
    assert proc.stdout.strip(), "an experiment prints a readable table"
    figures = json.loads(out.read_text())
    assert isinstance(figures, dict) and figures, "headline figures: one flat JSON object"
    assert all(not isinstance(v, (dict, list)) for v in figures.values()), "the JSON object is flat"
