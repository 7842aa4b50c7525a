"""cm3d.viz: the demo's Rerun recording read back (entity paths, frames on the timeline, the
recalled memory, the three trajectories), ``cm3d view`` without a display, and a core free of rerun.

One quick demo for the module: scene 2, 8 visits of 8 frames at 48x64, the only quick setting found
that recalls (scenes 0-59 with 4 visits recall nothing at this size): visit 7's second window
recalls map 0. It shares the compiled pipeline with the other 48x64, 8-frame tests."""

import collections
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("rerun")
from rerun.chunk import RrdReader  # noqa: E402

from cm3d import cli  # noqa: E402
from cm3d.demo import run_demo  # noqa: E402

VISITS, FRAMES = 8, 8


def read_back(rrd):
    """A recording as entity -> [(frame, visit, {column: value})], read with rerun's own reader."""
    rows_by_entity = collections.defaultdict(list)
    for chunk in RrdReader(rrd).stream():
        b = chunk.to_record_batch()
        cols = {n: b.column(n).to_pylist() for n in b.schema.names}
        for r in range(chunk.num_rows):
            rows_by_entity[chunk.entity_path].append(
                (cols.get("frame", [None] * chunk.num_rows)[r], cols.get("visit", [None] * chunk.num_rows)[r],
                 {n: v[r] for n, v in cols.items()}))
    return rows_by_entity


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    rrd = tmp_path_factory.mktemp("rerun") / "demo.rrd"
    rows = run_demo(scene=2, visits=VISITS, quick=True, out=None, rerun=str(rrd))
    return rrd, rows, read_back(rrd)


def test_recording_holds_every_stage(demo):
    rrd, _, ents = demo
    expected = {"/world/camera", "/world/camera/image", "/world/camera/image/dynamic", "/frame/image",
                "/frame/depth", "/frame/confidence", "/frame/dynamic", "/frame/cues/flow_gmm",
                "/frame/cues/geometry", "/frame/cues/residual", "/frame/cues/keypoints/kept",
                "/frame/cues/keypoints/rejected", "/world/trajectory/prior", "/world/trajectory/refined",
                "/world/trajectory/ground_truth", "/world/map/new", "/world/memory/recalled", "/world/landmarks",
                "/log/recall", "/plots/ate_so_far/refined", "/plots/lm_cost", "/plots/cue_agreement"}
    assert expected <= set(ents), expected - set(ents)
    assert rrd.stat().st_size < 5e6
    # images are logged compressed; the pinhole is the image's size
    row = ents["/world/camera/image"][-1][2]
    assert "image/jpeg" in str(row.get("EncodedImage:media_type"))
    # the host-recomputed cues reproduce the pipeline's mask
    assert min(r[2]["Scalars:scalars"][0] for r in ents["/plots/cue_agreement"]) > 0.99


def test_frames_on_the_timeline_and_windows_logged(demo):
    _, rows, ents = demo
    frames = {f for f, _, _ in ents["/world/camera/image/dynamic"]}
    assert frames == set(range(VISITS * FRAMES))
    assert {v for _, v, _ in ents["/world/camera"]} == set(range(VISITS))
    windows = sum(len(r["windows"]) for r in rows)
    assert len(ents["/log/recall"]) == len(ents["/plots/lm_cost"]) == windows
    assert all(np.isfinite(r[2]["Scalars:scalars"][0]) for r in ents["/plots/lm_cost"])
    lms = [r[2]["Points3D:positions"] for r in ents["/world/landmarks"] if r[2].get("Points3D:positions")]
    assert len(lms) == windows and all(len(p) > 0 for p in lms)


def test_memory_points_on_the_recalled_visit(demo):
    _, rows, ents = demo
    recalled = [r["visit"] for r in rows if r["recalled"] == "yes"]
    assert recalled == [7]
    mem = [(v, r) for _, v, r in ents["/world/memory/recalled"] if r.get("Points3D:positions")]
    # every window of the recalled visit that used the memory logs its points (one or both)
    assert sorted({v for v, _ in mem}) == recalled and len(mem[0][1]["Points3D:positions"]) > 50
    text = {v: " ".join(t for _, w, r in ents["/log/recall"] if w == v for t in r["TextLog:text"])
            for v in range(VISITS)}
    assert "ACCEPTED map 0" in text[7] and "not accepted" in text[1] and "candidates [0]" in text[1]


def test_three_trajectories_have_the_frames_so_far(demo):
    _, _, ents = demo
    for name in ("prior", "refined", "ground_truth"):
        strips = [(f, r["LineStrips3D:strips"]) for f, _, r in ents[f"/world/trajectory/{name}"]
                  if r.get("LineStrips3D:strips")]
        assert len(strips) == VISITS * FRAMES
        assert all(len(s[0]) == f % FRAMES + 1 for f, s in strips), name


def test_view_without_a_display_says_how(demo, monkeypatch, capsys):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert cli.main(["view", str(demo[0])]) == 0
    out = capsys.readouterr().out
    assert "no display here" in out and "--web-viewer" in out
    assert cli.main(["view", str(demo[0].parent / "missing.rrd")]) == 2
    assert cli.main(["demo", "--quick", "--rerun", str(demo[0].parent), "--quiet"]) == 2  # a folder: before work
    assert "is a folder" in capsys.readouterr().err


def test_bench_rerun_quick_in_the_demos_process(demo, tmp_path):
    """``experiments/bench_rerun.py --quick`` (its smoke test, see test_experiments.COVERED_ELSEWHERE),
    run in this process after the module's demo compiled the same 48x64 pipeline and recorder: a
    separate process would compile everything again (100 s of the suite)."""
    import importlib.util
    import json
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "experiments" / "bench_rerun.py"
    spec = importlib.util.spec_from_file_location("bench_rerun", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    out = tmp_path / "figures.json"
    got = bench.main(["--quick", "--json", str(out)])
    figures = json.loads(out.read_text())
    assert set(figures) == set(got) and all(not isinstance(v, (dict, list)) for v in figures.values())
    assert figures["plain_s"] > 0 and figures["recorded_s"] > 0 and figures["rrd_mb"] > 0
    assert np.isfinite(figures["overhead_pct"]) and figures["quick"]


def test_a_chunked_video_is_one_timeline_with_its_chunks(tmp_path):
    """``cm3d run CHUNKS.npz --rerun``: the stitched video's 8 frames on one timeline, each chunk's
    placed prior as its own strip, the chunk boundary in the log (2 chunks of 5 frames sharing 2, the
    shapes of test_cli's chunk test)."""
    from cm3d import long_video as stitch
    from cm3d.data import synthetic

    wcfg = synthetic.WorldConfig(height=48, width=64, supersample=1)
    images, gt = synthetic.render_ground_truth(synthetic.make_scene(0, wcfg), 0, 8, wcfg)
    chunks = synthetic.make_chunk_priors(images, gt, 5, 2, "slight", seed=0, timestamps=np.arange(8) / wcfg.fps)
    stitch.save_chunks(tmp_path / "all.npz", chunks)
    rrd = tmp_path / "video.rrd"
    assert cli.main(["run", str(tmp_path / "all.npz"), "--out", str(tmp_path / "out"), "--rerun", str(rrd),
                     "--quiet", "--no-pictures"]) == 0
    ents = read_back(rrd)
    assert {f for f, _, _ in ents["/world/camera/image/dynamic"]} == set(range(8))
    for k in (0, 1):
        strips = [r["LineStrips3D:strips"] for _, _, r in ents[f"/world/chunks/{k}"] if r.get("LineStrips3D:strips")]
        assert len(strips) == 1 and len(strips[0][0]) == 5, k  # the chunk's 5 placed prior centres
    text = [t for _, _, r in ents["/log/chunks"] for t in r["TextLog:text"]]
    assert any(t.startswith("chunk 0: frames 0-4") for t in text)
    assert any(t.startswith("chunk 1: frames 3-7; boundary with chunk 0") for t in text), text
    refined = [r["LineStrips3D:strips"][0] for _, _, r in ents["/world/trajectory/refined"]
               if r.get("LineStrips3D:strips")]
    assert [len(s) for s in refined] == list(range(1, 9))


def test_a_loop_closure_is_drawn_and_logged(tmp_path):
    """The loop-closure layer of a long video: the stitched 2-chunk video above, recorded with one loop
    closure added to its stitch result (chunk 1's first window recalling chunk 0's map, left out by
    the pose graph): a segment between the two windows' mean camera centres and a WARN log line."""
    import dataclasses

    from cm3d import long_video as stitch
    from cm3d.data import synthetic
    from cm3d.viz.record import Recorder

    wcfg = synthetic.WorldConfig(height=48, width=64, supersample=1)
    images, gt = synthetic.render_ground_truth(synthetic.make_scene(0, wcfg), 0, 8, wcfg)
    chunks = synthetic.make_chunk_priors(images, gt, 5, 2, "slight", seed=0, timestamps=np.arange(8) / wcfg.fps)
    cfg = stitch.memory_config_for_chunks(48, 64, [c.num_frames for c in chunks])
    rec, facts = Recorder(tmp_path / "loop.rrd"), []
    st = stitch.stitch_with_memory(chunks, pipeline_config=cfg, observe=rec.chunk_observer(cfg, facts))
    lc = stitch.LoopClosure(chunk=1, other=0, frames=(0, 3), transform=np.eye(4), inliers=50, rmse=0.01,
                            other_frames=(0, 3))
    st = dataclasses.replace(st, loops=(lc,), refinement={**st.refinement, "loop_kept": [False]})
    whole = stitch.memory_sequence_result(st, chunks)
    rec.long_video(st, whole, facts, cfg)
    ents = read_back(rec.close())
    segs = [r["LineStrips3D:strips"] for _, _, r in ents["/world/loops/0"] if r.get("LineStrips3D:strips")]
    centres = np.asarray(whole.poses)[:, :3, 3]
    want = np.stack([centres[3:7].mean(0), centres[0:4].mean(0)])  # chunk 1 starts at global frame 3
    assert len(segs) == 1 and np.allclose(np.asarray(segs[0][0], np.float64), want, atol=1e-5)
    text = [(t, r.get("TextLog:level")) for _, _, r in ents["/log/chunks"] for t in r["TextLog:text"]]
    assert any(t.startswith("loop closure: chunk 1 (frames 3-6) recalled the map of chunk 0 (frames 0-3)")
               and "left out" in t for t, _ in text), text


def test_core_does_not_import_rerun():
    code = ("import sys, cm3d, cm3d.cli, cm3d.demo, cm3d.pipeline, cm3d.long_video, cm3d.outputs; "
            "assert not [m for m in sys.modules if m.split('.')[0] in ('rerun', 'rerun_bindings')]")
    subprocess.run([sys.executable, "-c", code], check=True)
