"""Concurrent writers on one memory bank file: do all their maps survive?

Each repeat starts from an empty bank (the ``cm3d run`` mode: from no bank file); N processes read
the bank, wait until all have read it (so every one decides against the same, soon stale, bank),
then each stores one new map at the same moment. Modes:

- ``transaction``: ``cm3d.memory.snapshot`` -> add a map -> ``cm3d.memory.commit`` (the locked
  re-read and three-way merge of issue 25), tiny synthetic maps put in by numpy;
- ``naive``: ``memory.load`` -> add a map -> ``memory.save``, what ``cm3d run`` did before (no lock,
  the last writer wins); full run only;
- ``cm3d run``: N real ``cm3d run`` processes on N synthetic scenes (48x64, 8 frames) with one
  ``--memory`` bank, started together (no barrier: they race as a user's would); full run only.

    .venv/bin/python experiments/bank_concurrency.py            # 4 writers, 10 repeats per mode
    .venv/bin/python experiments/bank_concurrency.py --quick    # transactions only, 1 repeat, threads
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _cfg():
    from cm3d import memory

    return memory.MemoryConfig(max_maps=8, max_points=64, max_keyframes=2, max_keypoints=8)


def with_tiny_map(bank, i: int):
    """``bank`` with map i stored in its first free slot, on the host (numpy; no compilation): a
    tiny map whose identity is its point count (10 + i valid points)."""
    import dataclasses

    import numpy as np

    from cm3d import memory

    f = {x.name: np.array(getattr(bank, x.name)) for x in dataclasses.fields(bank)}
    slot = int(np.flatnonzero(~f["map_valid"])[0])
    rng = np.random.default_rng(i)
    f["points"][slot] = rng.normal(size=f["points"].shape[1:])
    f["point_valid"][slot] = np.arange(f["point_valid"].shape[1]) < 10 + i
    f["kf_valid"][slot, 0] = True
    f["map_valid"][slot], f["visits"][slot], f["voxel_size"][slot] = True, 1, 0.1
    return memory.MemoryBank(**f)


def worker(mode: str, bank: str, i: int, sync: str) -> None:
    """One writer: read the bank, add map i, report ready, wait for ``go``, write."""
    from cm3d import memory

    cfg = _cfg()
    if mode == "transaction":
        snap = memory.snapshot(bank)
        base = snap.bank
    else:
        base = memory.load(bank)[0]
    new = with_tiny_map(base, i)
    Path(sync, f"ready{i}").touch()
    while not Path(sync, "go").exists():
        time.sleep(0.002)
    if mode == "transaction":
        memory.commit(bank, snap, new, cfg)
    else:
        memory.save(new, bank, cfg)


def _maps_in(bank: Path) -> tuple[int, list[int]]:
    """(maps stored, their point counts) of a bank file (none: 0)."""
    import numpy as np

    from cm3d import memory

    if not bank.exists():
        return 0, []
    b, _ = memory.load(bank)
    valid = np.asarray(b.map_valid)
    return int(valid.sum()), sorted(int(n) for n in np.asarray(b.point_valid).sum(1)[valid])


def library_repeat(mode: str, writers: int, work: Path, empty_bank: bytes, threads: bool = False) -> dict:
    """One repeat of the library-level race from an empty bank file (writers are processes, or threads
    of this one: each opens the lock file itself, so ``flock`` excludes them as it does processes);
    returns maps kept and the wall time."""
    bank = work / "bank.cm3d"
    bank.write_bytes(empty_bank)
    sync = work / "sync"
    sync.mkdir()
    t0 = time.perf_counter()
    if threads:
        import threading

        errors = []

        def run(i):
            try:
                worker(mode, str(bank), i, str(sync))
            except Exception as e:  # noqa: BLE001  reported below
                errors.append(e)

        class _Thread(threading.Thread):
            def poll(self):
                return 1 if errors else (None if self.is_alive() else 0)

            def wait(self):
                self.join()
                return 1 if errors else 0

        procs = [_Thread(target=run, args=(i,)) for i in range(writers)]
        for p in procs:
            p.start()
    else:
        procs = [subprocess.Popen([sys.executable, __file__, "--worker", mode, str(bank), str(i), str(sync)],
                                  cwd=ROOT) for i in range(writers)]
    deadline = time.monotonic() + 300
    while sum(1 for p in sync.iterdir() if p.name.startswith("ready")) < writers:
        if time.monotonic() > deadline or any(p.poll() not in (None, 0) for p in procs):
            raise RuntimeError("a writer failed before the race")
        time.sleep(0.005)
    (sync / "go").touch()
    codes = [p.wait() for p in procs]
    if any(codes):
        raise RuntimeError(f"writer exit codes {codes}")
    n, counts = _maps_in(bank)
    return {"maps": n, "all_present": counts == [10 + i for i in range(writers)],
            "seconds": time.perf_counter() - t0, "changed_commits": None}


def _sequences(work: Path, writers: int) -> list[Path]:
    from cm3d.data import io, synthetic

    wcfg = synthetic.WorldConfig(height=48, width=64, supersample=1)
    paths = []
    for i in range(writers):
        p = work / f"scene{i}.npz"
        io.save_sequence(p, synthetic.generate(i, 0, 8, "moderate", wcfg))
        paths.append(p)
    return paths


def _cm3d_run(seq: Path, out: Path, bank: Path, env) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "cm3d.cli", "run", str(seq), "--out", str(out), "--memory",
                             str(bank), "--quiet", "--no-pictures"], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def cli_repeat(seqs: list[Path], work: Path, env) -> dict:
    """One repeat of N concurrent ``cm3d run`` processes on one bank."""
    bank = work / "bank.cm3d"
    t0 = time.perf_counter()
    procs = [_cm3d_run(s, work / f"out{i}", bank, env) for i, s in enumerate(seqs)]
    for p in procs:
        _, err = p.communicate()
        if p.returncode:
            raise RuntimeError(f"cm3d run failed: {err[-2000:]}")
    n, _ = _maps_in(bank)
    changed = sum(json.loads((work / f"out{i}" / "recall.json").read_text())["memory"]["bank_changed"]
                  for i in range(len(seqs)))
    return {"maps": n, "all_present": n == len(seqs), "seconds": time.perf_counter() - t0, "changed_commits": changed}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="transactions only, one repeat, writers as threads of this process (a smoke test)")
    ap.add_argument("--writers", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--json", default=None, metavar="PATH", help="also write the headline figures (flat JSON)")
    ap.add_argument("--worker", nargs=4, metavar=("MODE", "BANK", "I", "SYNC"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        mode, bank, i, sync = args.worker
        worker(mode, bank, int(i), sync)
        return
    repeats = 1 if args.quick else args.repeats
    modes = ["transaction"] if args.quick else ["transaction", "naive", "cm3d run"]
    rows = {}
    with tempfile.TemporaryDirectory(prefix="cm3d-concurrency-") as tmp:
        tmp = Path(tmp)
        env = dict(os.environ)
        if "cm3d run" in modes:
            seqs = _sequences(tmp, args.writers)
            env.setdefault("CM3D_JAX_CACHE", str(tmp / "jax-cache"))
            warm = tmp / "warm"  # one run first: the four racing runs then share its compiled program
            p = _cm3d_run(seqs[0], warm / "out", warm / "bank.cm3d", env)
            if p.wait():
                raise RuntimeError(p.stderr.read()[-2000:])
        from cm3d import memory

        empty_bank = memory.io.encode(memory.empty(_cfg()), _cfg())
        for mode in modes:
            runs = []
            for r in range(repeats):
                work = tmp / f"{mode.replace(' ', '_')}{r}"
                work.mkdir()
                runs.append(cli_repeat(seqs, work, env) if mode == "cm3d run"
                            else library_repeat(mode, args.writers, work, empty_bank, threads=args.quick))
            rows[mode] = runs
    print(f"{args.writers} concurrent writers ({'threads' if args.quick else 'processes'}) on one bank file, "
          f"{repeats} repeat(s) per mode")
    print(f"{'mode':12s} {'maps kept (min / mean / max)':>30s} {'repeats with all':>17s} "
          f"{'commits that merged':>20s} {'s per repeat':>13s}")
    figures = {"writers": args.writers, "repeats": repeats}
    for mode, runs in rows.items():
        maps = [r["maps"] for r in runs]
        full = sum(r["all_present"] for r in runs)
        changed = [r["changed_commits"] for r in runs if r["changed_commits"] is not None]
        merged = f"{sum(changed)} of {len(changed) * args.writers}" if changed else "-"
        secs = sum(r["seconds"] for r in runs) / len(runs)
        print(f"{mode:12s} {min(maps):>16d} / {sum(maps) / len(maps):4.1f} / {max(maps):<5d} "
              f"{full:>10d} of {len(runs):<4d} {merged:>20s} {secs:>13.1f}")
        key = mode.replace(" ", "_")
        figures.update({f"{key}_maps_min": min(maps), f"{key}_maps_mean": sum(maps) / len(maps),
                        f"{key}_repeats_all_present": full, f"{key}_seconds_per_repeat": round(secs, 2)})
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=1) + "\n")


if __name__ == "__main__":
    main()
