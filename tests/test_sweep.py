"""The sharded sweep (experiments/sweep.py): ``vmap`` over two sequences per device, sharded over 2
emulated CPU devices, equals each sequence run alone on one device.

This is also the sweep's smoke test (``--quick --json``), so tests/test_experiments.py skips it, and
the suite's test of ``vmap`` over sequences (until stop 47 a separate test_pipeline.py test that
compiled its own vmapped 48x64 program)."""

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
    assert figures["window_ends_equal"] == 1.0 and figures["windows_equal"] == 1.0
    assert figures["mask_agreement"] > 0.999
    # the objective agrees to float32 round-off; poses too, except along directions tiny windows leave
    # nearly flat, where the batched operations' round-off moves the LM's optimum (at 48x64, 4-frame
    # windows: 88 % of entries within 1e-3, the worst 0.039; here ~1e-5)
    assert figures["poses_within_1e-3"] > 0.85 and figures["sharded_equals_single"] < 0.1
    for level in ("slight", "moderate"):
        assert figures[f"ate_cm3d_{level}"] < figures[f"ate_prior_{level}"]
    rows = list(csv.DictReader((tmp_path / "sweep" / "sweep.csv").open()))
    assert len(rows) == 4 and {(r["seed"], r["level"]) for r in rows} == {(a, b) for a in "01"
                                                                           for b in ("slight", "moderate")}
    assert (tmp_path / "sweep" / "ate_vs_noise.png").stat().st_size > 0
