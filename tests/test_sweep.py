"""The sharded sweep (experiments/sweep.py) on 2 emulated CPU devices equals the one-device run.

This is also the sweep's smoke test (``--quick --json``), so tests/test_experiments.py skips it.
"""

import csv
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_sharded_sweep_equals_single_device(tmp_path):
    out = tmp_path / "figures.json"
    proc = subprocess.run([sys.executable, str(ROOT / "experiments" / "sweep.py"), "--quick", "--json", str(out),
                           "--out", str(tmp_path / "sweep")], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]
    figures = json.loads(out.read_text())
    assert figures["devices"] == 2
    assert figures["sharded_equals_single"] <= 1e-6
    assert figures["ate_cm3d_moderate"] < figures["ate_prior_moderate"]
    rows = list(csv.DictReader((tmp_path / "sweep" / "sweep.csv").open()))
    assert len(rows) == 2 and {r["seed"] for r in rows} == {"0", "1"}
    assert (tmp_path / "sweep" / "ate_vs_noise.png").stat().st_size > 0
