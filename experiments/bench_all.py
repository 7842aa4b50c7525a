"""Every benchmark of the project in one run, side by side with its peers -> BENCHMARKS.md.

    .venv/bin/python experiments/bench_all.py [--only motion icp lm memory backend] [--report BENCHMARKS.md]
        [--quick] [--json PATH]

Runs each benchmark script (its own peers measured in the same process: scikit-learn and
scikit-image for the motion cue, Open3D and small_gicp for voxel/ICP, GTSAM, optimistix and jaxopt
for the factor graph, brute force for memory recall, OpenCV flow for the back end) with
``--json``, collects their headline figures, and writes one Markdown report with the machine
(CPU, cores, devices, versions), the command of each benchmark, its wall time and its figures
(ratios are cm3d against the peer measured in the same run). When JAX sees an accelerator the
scripts run on it and the report's device column says so; run the script once per machine and
keep both reports.

``--quick`` runs only the motion benchmark with ``--quick`` and writes the report to a temporary
folder unless ``--report`` is given (the smoke test must not touch the committed report).
Headline JSON keys: ``<bench>_<key>`` for every figure of every benchmark run, ``<bench>_wall_s``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: name -> (script, extra arguments, what it compares)
BENCHES = {
    "motion": ("bench_motion.py", [], "GMM vs scikit-learn, Otsu/components vs scikit-image, motion cue fps"),
    "icp": ("bench_icp.py", [], "voxel downsample and ICP (p2p, p2l) vs Open3D and small_gicp"),
    "lm": ("bench_lm.py", [], "LM factor graph vs GTSAM, optimistix, jaxopt; vmap; implicit gradient"),
    "memory": ("memory_recall.py", [], "memory recall accuracy / false accepts / queries per second"),
    "backend": ("bench_backend.py", [], "whole back end frames per second vs OpenCV flow"),
}


def machine() -> dict:
    import jax

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    versions = {}
    for mod in ("jax", "jaxlib", "numpy", "open3d", "cv2", "gtsam", "sklearn", "skimage", "small_gicp"):
        try:
            m = __import__(mod)
            versions[mod] = getattr(m, "__version__", "?")
        except Exception:  # noqa: BLE001 - an optional peer may be missing
            versions[mod] = "missing"
    devs = jax.devices()
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(),
            "devices": f"{len(devs)} x {devs[0].platform} ({devs[0].device_kind})", **versions}


def run_bench(name: str, quick: bool, tmp: Path) -> dict:
    script, extra, _ = BENCHES[name]
    out = tmp / f"{name}.json"
    cmd = [sys.executable, str(ROOT / "experiments" / script), *extra, "--json", str(out)] + (["--quick"] if quick else [])
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    shown = " ".join([".venv/bin/python", f"experiments/{script}", *extra] + (["--quick"] if quick else []))
    if proc.returncode != 0:
        return {"command": shown, "wall_s": wall, "error": (proc.stderr or proc.stdout)[-600:], "figures": {}}
    return {"command": shown, "wall_s": wall, "figures": json.loads(out.read_text()), "stdout": proc.stdout}


def report(results: dict, info: dict) -> str:
    lines = ["# cm3d benchmarks", "",
             "Written by `.venv/bin/python experiments/bench_all.py` "
             f"on {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. Each benchmark measures its peers in the "
             "same process; ratios are cm3d against that peer (these machines are noisy: compare ratios, "
             "not absolute times, across machines).", "", "## Machine", "",
             "| | |", "|---|---|"]
    lines += [f"| {k} | {v} |" for k, v in info.items()]
    for name, r in results.items():
        lines += ["", f"## {name}: {BENCHES[name][2]}", "", f"`{r['command']}` — {r['wall_s']:.0f} s", ""]
        if "error" in r:
            lines += ["**failed**:", "", "```", r["error"], "```"]
            continue
        lines += ["| figure | value |", "|---|---|"]
        for k, v in r["figures"].items():
            lines.append(f"| {k} | {v:.4g} |" if isinstance(v, float) else f"| {k} | {v} |")
        if r.get("stdout"):
            lines += ["", "<details><summary>full output</summary>", "", "```", r["stdout"].rstrip(), "```", "",
                      "</details>"]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", choices=list(BENCHES), default=None)
    ap.add_argument("--report", default=None, help="Markdown report (default BENCHMARKS.md; temp with --quick)")
    ap.add_argument("--quick", action="store_true", help="the motion benchmark only, --quick, temporary report")
    ap.add_argument("--json", default=None, metavar="PATH")
    args = ap.parse_args()
    names = args.only or (["motion"] if args.quick else list(BENCHES))
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        path = Path(args.report) if args.report else (tmp / "BENCHMARKS.md" if args.quick else ROOT / "BENCHMARKS.md")
        info = machine()
        results = {}
        print(f"{'benchmark':>9} | {'wall s':>7} | headline figures")
        for name in names:
            r = results[name] = run_bench(name, args.quick, tmp)
            head = ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}"
                             for k, v in list(r["figures"].items())[:6])
            print(f"{name:>9} | {r['wall_s']:>7.0f} | {head or 'FAILED: ' + r.get('error', '')[-200:]}")
        from cm3d.data.atomic import atomic_write
        from cm3d.outputs import write_json

        with atomic_write(path, "w") as f:
            f.write(report(results, info))
        print(f"\nwrote {path if args.report or not args.quick else 'a temporary report (--quick)'}")
        figures = {f"{n}_{k}": v for n, r in results.items() for k, v in r["figures"].items()
                   if isinstance(v, (int, float, str, bool))}
        figures.update({f"{n}_wall_s": r["wall_s"] for n, r in results.items()})
        if args.json:
            write_json(args.json, figures)
        if any("error" in r for r in results.values()):
            sys.exit(1)


if __name__ == "__main__":
    main()
