"""``cm3d demo``: the whole pipeline on the embedded multi-visit synthetic world, with one memory.

Renders ``visits`` visits of one scene (VGGT-like priors, 3° / 3 cm RMS pose error), runs
:func:`cm3d.pipeline.run` over them with one bank, prints metrics and window decisions, and writes
``cm3d run``'s outputs per visit (``OUT/visitNN/``) plus the bank (``OUT/memory.cm3d``).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from cm3d.data.atomic import atomic_write


def format_table(rows: list[dict]) -> str:
    cols = [("visit", "{:>5}"), ("frames", "{:>6}"), ("ate_prior", "{:>9.5f}"), ("ate_refined", "{:>11.5f}"),
            ("ate_change_pct", "{:>14.1f}"), ("rpe_t_prior", "{:>11.5f}"), ("rpe_t_refined", "{:>13.5f}"),
            ("rpe_r_prior", "{:>11.3f}"), ("rpe_r_refined", "{:>13.3f}"), ("mask_iou", "{:>8.3f}"),
            ("recalled", "{:>8}"), ("seconds", "{:>7.1f}")]
    head = " ".join(f"{name:>{len(fmt.format(rows[0][name]))}}" for name, fmt in cols)
    lines = [head, "-" * len(head)]
    lines += [" ".join(fmt.format(r[name]) for name, fmt in cols) for r in rows]
    return "\n".join(lines)


def run_demo(scene: int = 0, visits: int = 3, frames: int | None = None, quick: bool = False,
             json_path: str | None = None, out: str | None = "out/demo", height: int | None = None,
             width: int | None = None, progress=None, rerun: str | None = None) -> list[dict]:
    """Run the demo; returns one row of metrics per visit (also written as JSON to ``json_path``);
    ``rerun``: also record every visit into this ``.rrd`` file (:mod:`cm3d.viz`)."""
    import json

    from cm3d import memory, outputs, pipeline
    from cm3d.data import synthetic

    if visits < 1:
        raise ValueError(f"--visits: need at least 1, got {visits}")
    H = height or (48 if quick else 384)
    W = width or (64 if quick else 512)
    S = frames or (8 if quick else 40)
    wcfg = synthetic.WorldConfig(height=H, width=W)
    cfg = pipeline.config_for(H, W)
    print(f"scene {scene}: {visits} visits x {S} frames at {H}x{W}, moderate prior noise; "
          f"windows of {cfg.keyframe_interval} frames, one memory bank across visits")
    recorder = None
    if rerun:
        from cm3d.viz.record import Recorder

        recorder = Recorder(rerun)
    t0 = time.perf_counter()
    seqs = []
    for v in range(visits):
        seqs.append(synthetic.generate(scene, v, S, "moderate", wcfg))
        if progress is not None:
            progress("render", v + 1, visits)
    print(f"rendered in {time.perf_counter() - t0:.1f} s")
    bank, rows = None, []
    out_dir = None if out is None else Path(out)
    for v, seq in enumerate(seqs):
        t1 = time.perf_counter()
        observe = None if recorder is None else recorder.observe(cfg, visit=v)
        bank, (res,) = pipeline.run([seq], cfg, bank, progress=progress, observe=observe)
        dt = time.perf_counter() - t1
        if out_dir is not None:
            outputs.write_results(out_dir / f"visit{v:02d}", res, bank)
        m = outputs.sequence_metrics(res)
        rows.append({"visit": v, "frames": seq.num_frames, "ate_prior": m["prior"]["ate"],
                     "ate_refined": m["refined"]["ate"], "ate_change_pct": -m["ate_reduction_pct"],
                     "rpe_t_prior": m["prior"]["rpe_trans"], "rpe_t_refined": m["refined"]["rpe_trans"],
                     "rpe_r_prior": m["prior"]["rpe_rot"], "rpe_r_refined": m["refined"]["rpe_rot"],
                     "mask_iou": m.get("mask", {}).get("iou", float("nan")),
                     "recalled": "yes" if pipeline.recalled_earlier_map(res.windows) else "no",
                     "seconds": dt, "windows": res.windows})
    if out_dir is not None:
        memory.save(bank, out_dir / "memory.cm3d", cfg.memory)
    print("\nprior vs refined (ATE / RPE trans in metres after Sim3 alignment, RPE rot in degrees; "
          "seconds: flow + keypoints + back end, the first visit includes compilation)\n")
    print(format_table(rows))
    print("\nmemory decisions per window (recalled = a map stored by an earlier visit was verified and updated)")
    for r in rows:
        for w in r["windows"]:
            print(f"  visit {r['visit']}: " + outputs.window_line(w))
    mean = lambda k: float(np.mean([r[k] for r in rows]))  # noqa: E731
    red = 100.0 * (mean("ate_prior") - mean("ate_refined")) / max(mean("ate_prior"), 1e-12)
    print(f"\nmean ATE prior {mean('ate_prior'):.5f} -> refined {mean('ate_refined'):.5f} "
          f"({red:.1f} % lower); revisits recalled: {sum(r['recalled'] == 'yes' for r in rows[1:])} of {len(rows) - 1}")
    if out_dir is not None:
        print(f"outputs in {out_dir}/visitNN/ and the bank in {out_dir / 'memory.cm3d'}")
    if recorder is not None:
        path = recorder.close()
        print(f"recording {path} ({path.stat().st_size / 1e6:.1f} MB; cm3d view {path})")
    if json_path:
        with atomic_write(json_path, "w") as f:
            json.dump([{**r, "windows": [w.to_json() for w in r["windows"]]} for r in rows], f, indent=1)
    return rows
