"""The command line: generate, eval (against evo's reference numbers), demo, errors, light import."""

import json
import subprocess
import sys

import numpy as np
import pytest

from cm3d import cli
from cm3d.data import io


def test_eval_json_matches_evo_reference(shared_data, capsys):
    d = shared_data / "evo_tum_traj"
    rc = cli.main(["eval", "--gt", str(d / "fr2_desk_groundtruth.txt"), "--est", str(d / "fr2_desk_ORB.txt"), "--json"])
    assert rc == 0
    m = json.loads(capsys.readouterr().out)
    assert set(m) == {"ate", "ate_se3", "rpe_trans", "rpe_rot", "rot_rmse", "extent", "ate_defined", "pairs"}
    assert m["ate_defined"] and m["extent"] > 0.1
    # figures from evo 1.38.1 (../shared/data/README.md)
    np.testing.assert_allclose([m["ate"], m["ate_se3"], m["rpe_trans"], m["rpe_rot"]],
                               [0.006123, 0.008119, 0.003485, 0.280519], atol=1e-6)
    assert m["pairs"] == 2174


def test_eval_table_and_bad_file(tmp_path, shared_data, capsys):
    d = shared_data / "evo_tum_traj"
    assert cli.main(["eval", "--gt", str(d / "freiburg1_xyz-groundtruth.txt"),
                     "--est", str(d / "freiburg1_xyz-rgbdslam.txt")]) == 0
    assert "ATE (Sim3) 0.013389" in capsys.readouterr().out
    bad = tmp_path / "bad.txt"
    bad.write_text("0 1 2 3 0 0 0\n")
    assert cli.main(["eval", "--gt", str(bad), "--est", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "bad.txt:1:" in err and "expected 8 values" in err


def test_generate_writes_loadable_sequences_and_trajectories(tmp_path, capsys):
    rc = cli.main(["generate", "--out", str(tmp_path), "--visits", "2", "--frames", "3",
                   "--height", "48", "--width", "64", "--level", "slight"])
    assert rc == 0
    seqs = sorted(tmp_path.glob("*.npz"))
    assert len(seqs) == 2
    seq = io.load_sequence(seqs[1])
    assert seq.images.shape == (3, 48, 64, 3) and seq.gt is not None and seq.meta["visit"] == 1
    ts, c2w = io.read_tum(seqs[1].with_suffix(".gt.txt"))
    np.testing.assert_allclose(c2w, seq.gt.cam_to_world, atol=1e-8)
    # the written prior trajectory evaluates against the written ground truth
    assert cli.main(["eval", "--gt", str(seqs[1].with_suffix(".gt.txt")),
                     "--est", str(seqs[1].with_suffix(".prior.txt")), "--json"]) == 0


def test_demo_quick_runs_pipeline_prints_table_and_json(tmp_path, capsys):
    out = tmp_path / "demo.json"
    assert cli.main(["demo", "--quick", "--visits", "2", "--frames", "8", "--out", str(tmp_path / "demo"),
                     "--json", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "ate_refined" in text and "memory decisions" in text and "new map 0" in text
    rows = json.loads(out.read_text())
    assert [r["visit"] for r in rows] == [0, 1]
    assert all(r["ate_prior"] > 0 and np.isfinite(r["ate_refined"]) for r in rows)
    assert (tmp_path / "demo" / "memory.cm3d").exists()
    assert (tmp_path / "demo" / "visit01" / "trajectory.txt").exists()


@pytest.fixture(scope="module")
def small_visits(tmp_path_factory):
    from cm3d.data import synthetic

    d = tmp_path_factory.mktemp("visits")
    wcfg = synthetic.WorldConfig(height=48, width=64, supersample=1)
    paths = []
    for v in range(2):
        path = d / f"visit{v}.npz"
        io.save_sequence(path, synthetic.generate(0, v, 8, "moderate", wcfg))
        paths.append(path)
    return paths


def test_run_writes_every_output_and_memory_round_trip(tmp_path, small_visits, capsys):
    bank = tmp_path / "bank.cm3d"
    v0 = str(small_visits[0])
    assert cli.main(["run", v0, "--out", str(tmp_path / "a"), "--memory", str(bank), "--quiet"]) == 0
    a = tmp_path / "a"
    for name in ("trajectory.txt", "trajectory_prior.txt", "static_map.ply", "recall.json", "metrics.json",
                 "trajectory.png", "topdown_map.png"):
        assert (a / name).is_file(), name
    assert len(list((a / "masks").glob("*.png"))) == 8 and list((a / "overlays").glob("*.png"))
    ts, c2w = io.read_tum(a / "trajectory.txt")
    assert c2w.shape == (8, 4, 4) and np.all(np.isfinite(c2w))
    m = json.loads((a / "metrics.json").read_text())
    assert {"prior", "refined", "depth_prior", "mask"} <= set(m) and m["refined"]["pairs"] == 8
    rec = json.loads((a / "recall.json").read_text())["windows"]
    assert rec[0]["created_map"] and rec[0]["map_id"] == 0 and len(rec[0]["transform"]) == 4
    assert bank.is_file()
    # the trajectory evaluates with cm3d eval (evo's protocol) against the ground truth
    io.write_tum(tmp_path / "gt.txt", ts, io.load_sequence(v0).gt.cam_to_world)
    assert cli.main(["eval", "--gt", str(tmp_path / "gt.txt"), "--est", str(a / "trajectory.txt"), "--json"]) == 0
    capsys.readouterr()
    # second run with the same bank: the scene is recalled from the saved memory
    assert cli.main(["run", v0, "--out", str(tmp_path / "b"), "--memory", str(bank), "--quiet"]) == 0
    assert "recalled map 0" in capsys.readouterr().out
    rec = json.loads((tmp_path / "b" / "recall.json").read_text())["windows"]
    assert rec[0]["accepted"] and rec[0]["recalled_map"] == 0 and not rec[0]["created_map"]
    assert cli.main(["memory", "ls", str(bank)]) == 0
    assert "1 of 4 maps" in capsys.readouterr().out  # recalled and updated, not a second map


def test_run_bad_inputs_are_one_line_errors(tmp_path, small_visits, capsys):
    assert cli.main(["run", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "no such file" in err and err.count("\n") == 1
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip file")
    assert cli.main(["run", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("cm3d run: error:") and err.count("\n") == 1
    broken = tmp_path / "broken.cm3d"
    broken.write_bytes(b"garbage")
    assert cli.main(["run", str(small_visits[0]), "--out", str(tmp_path / "o"), "--memory", str(broken)]) == 2
    assert "not a cm3d memory bank" in capsys.readouterr().err
    assert cli.main(["run", str(small_visits[0]), "--out", str(tmp_path / "o"), "--keyframe-interval", "1"]) == 2
    assert "keyframe_interval" in capsys.readouterr().err


def test_run_help():
    out = subprocess.run([sys.executable, "-m", "cm3d.cli", "run", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "--memory" in out.stdout and "static_map.ply" in out.stdout


def test_import_cm3d_is_light():
    code = ("import sys, cm3d, cm3d.cli, cm3d.ops.camera, cm3d.data.io, cm3d.data.synthetic, cm3d.eval; "
            "print(sorted(m for m in ('cv2', 'open3d', 'matplotlib') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_console_script_ends_without_teardown_yet_keeps_its_output_and_code(tmp_path):
    """``python -m cm3d.cli`` ends as the ``cm3d`` script does (``cli.finish``: ``os._exit`` after the
    streams are flushed): its files are written, its piped stdout arrives and its exit code is main's."""
    def run(*args):
        return subprocess.run([sys.executable, "-m", "cm3d.cli", "generate", "--out", str(tmp_path), *args],
                              capture_output=True, text=True)

    ok = run("--visits", "1", "--frames", "2", "--height", "16", "--width", "16")
    assert ok.returncode == 0 and str(tmp_path) in ok.stdout, ok.stderr
    assert len(list(tmp_path.glob("*.npz"))) == 1
    bad = run("--level", "extreme")
    assert bad.returncode == 2 and "level" in bad.stderr


def test_console_script_help():
    out = subprocess.run([sys.executable, "-m", "cm3d.cli", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "generate" in out.stdout and "eval" in out.stdout


@pytest.mark.parametrize("level", ["extreme"])
def test_generate_bad_level_is_clear(tmp_path, level, capsys):
    assert cli.main(["generate", "--out", str(tmp_path), "--level", level, "--frames", "2",
                     "--height", "16", "--width", "16"]) == 2
    assert "level" in capsys.readouterr().err


def test_memory_ls_show_rm(tmp_path, capsys):
    from cm3d import memory

    cfg = memory.MemoryConfig(max_maps=3, max_points=16, max_keyframes=2, max_floor_keypoints=4)
    bank = memory.empty(cfg)
    for seed in range(2):
        rng = np.random.default_rng(seed)
        entry = memory.MapEntry(
            points=rng.normal(size=(16, 3)), normals=np.zeros((16, 3)), conf=np.ones(16),
            colors=np.zeros((16, 3), np.uint8), point_valid=np.arange(16) < 10 + seed,
            kf_desc=np.zeros((2, cfg.image_dim)), kf_valid=np.array([True, False]),
            cloud_desc=np.zeros(cfg.cloud_dim), voxel_size=np.float32(0.1),
            floor_keypoints=memory.Keypoints(np.zeros((3, 3)), np.zeros((3, cfg.keypoint_dim)), np.arange(3) < seed + 1))
        bank, _ = memory.add_map(bank, entry)
    path = tmp_path / "bank.cm3d"
    memory.save(bank, path, cfg)
    assert cli.main(["memory", "ls", str(path)]) == 0
    out = capsys.readouterr().out
    assert "2 of 3 maps" in out and "map   1:     11 points" in out
    assert cli.main(["memory", "show", str(path), "1"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["points"] == 11 and shown["keypoints"] == 0 and shown["floor_keypoints"] == 2
    assert cli.main(["memory", "rm", str(path), "0"]) == 0
    capsys.readouterr()
    assert cli.main(["memory", "show", str(path), "0"]) == 2
    assert "not a stored map" in capsys.readouterr().err
    path.write_bytes(path.read_bytes()[:-10])
    assert cli.main(["memory", "ls", str(path)]) == 2
    assert "checksum" in capsys.readouterr().err


@pytest.mark.parametrize("fmt", ["tum", "images"])
def test_generate_and_run_folder_inputs(tmp_path, fmt, capsys):
    """Every folder format goes from `cm3d generate --format` through `cm3d run` to evaluated outputs."""
    gen = ["generate", "--out", str(tmp_path), "--format", fmt, "--visits", "1", "--frames", "8",
           "--height", "48", "--width", "64", "--level", "slight"]
    assert cli.main(gen) == 0
    folder = tmp_path / "scene000_visit00"
    assert folder.is_dir() and (tmp_path / "scene000_visit00.gt.txt").is_file()
    assert cli.main(["run", str(folder), "--out", str(tmp_path / "o"), "--quiet", "--no-pictures"]) == 0
    out = capsys.readouterr().out
    assert f"{folder}: 8 frames at 48x64" in out
    ts, c2w = io.read_tum(tmp_path / "o" / "trajectory.txt")
    assert c2w.shape == (8, 4, 4) and np.all(np.isfinite(c2w))
    m = json.loads((tmp_path / "o" / "metrics.json").read_text())  # ground truth travelled with the input
    assert m["refined"]["pairs"] == 8 and np.isfinite(m["refined"]["ate"])
    if fmt == "tum":  # the prior is Open3D RGB-D odometry on sensor depth: metric, first camera at the origin
        _, prior = io.read_tum(tmp_path / "o" / "trajectory_prior.txt")
        np.testing.assert_allclose(prior[0], np.eye(4), atol=1e-9)
    # writing into a non-empty image folder is refused rather than mixing two sequences
    if fmt == "images":
        assert cli.main(gen) == 2
        assert "not empty" in capsys.readouterr().err


def test_run_chunks_with_memory_from_several_files_or_one(tmp_path, capsys):
    """Chunks of one video: the pipeline per chunk threading the memory, overlap alignment, the usual
    outputs plus stitch.json; the saved bank is recalled by a second run (the one-file form)."""
    from cm3d import long_video as stitch
    from cm3d.data import synthetic

    wcfg = synthetic.WorldConfig(height=48, width=64, supersample=1)
    images, gt = synthetic.render_ground_truth(synthetic.make_scene(0, wcfg), 0, 8, wcfg)
    # 8 frames as 2 chunks of 5 sharing 2: each chunk pads to the other CLI tests' 8 frames (one program)
    chunks = synthetic.make_chunk_priors(images, gt, 5, 2, "slight", seed=0, timestamps=np.arange(8) / wcfg.fps)
    paths = [tmp_path / f"c{k}.npz" for k in range(2)]
    for p, c in zip(paths, chunks):
        io.save_sequence(p, c)
    stitch.save_chunks(tmp_path / "all.npz", chunks)
    bank = tmp_path / "bank.cm3d"
    a, b = tmp_path / "a", tmp_path / "b"
    assert cli.main(["run", *map(str, paths), "--out", str(a), "--memory", str(bank), "--quiet"]) == 0
    assert "2 chunks (5, 5 frames) at 48x64" in capsys.readouterr().out
    for name in ("trajectory.txt", "trajectory_prior.txt", "static_map.ply", "metrics.json", "stitch.json",
                 "trajectory.png", "topdown_map.png"):
        assert (a / name).is_file(), name
    assert len(list((a / "masks").glob("*.png"))) == 8 and bank.is_file()
    s = json.loads((a / "stitch.json").read_text())
    assert [list(r) for r in s["ranges"]] == [[0, 5], [3, 8]] and s["loops"] == []
    rec = json.loads((a / "recall.json").read_text())["windows"]
    assert [w["chunk"] for w in rec] == [0, 1] and [w["frames"] for w in rec] == [[0, 4], [3, 7]]
    assert rec[0]["created_map"]
    # trajectory_prior.txt: the chunks' priors aligned on their overlap (the stitching library's
    # answer); trajectory.txt: its whole-trajectory refinement (long_video.refine_frames) when kept
    ref = stitch.stitch_chunks(chunks, refine=False).sequence.cam_to_world
    np.testing.assert_allclose(io.read_tum(a / "trajectory_prior.txt")[1], ref, atol=1e-6)
    traj = io.read_tum(a / "trajectory.txt")[1]
    fr = s["frame_refinement"]
    assert fr["pairs"] == 7 and s["refined"] == fr["kept"]
    if not fr["kept"]:
        np.testing.assert_allclose(traj, ref, atol=1e-6)
    assert json.loads((a / "metrics.json").read_text())["refined"]["pairs"] == 8
    # the one-file form with the saved bank: chunk 0 recalls the map the first run stored
    assert cli.main(["run", str(tmp_path / "all.npz"), "--out", str(b), "--memory", str(bank), "--quiet",
                     "--no-pictures"]) == 0
    assert "chunk 0: frames    0-   4: recalled map 0" in capsys.readouterr().out
    rec = json.loads((b / "recall.json").read_text())["windows"]
    assert rec[0]["accepted"] and rec[0]["recalled_map"] == 0
    # the chunks' priors stitch as before; the trajectory stitches the refined chunks, which the
    # recall changed (chunk 0 refined against the remembered map)
    np.testing.assert_allclose(io.read_tum(b / "trajectory_prior.txt")[1], ref, atol=1e-6)
    traj_b = io.read_tum(b / "trajectory.txt")[1]
    assert traj_b.shape == traj.shape and np.all(np.isfinite(traj_b))
    # a chunk file among other files is refused with a one-line error
    assert cli.main(["run", str(tmp_path / "all.npz"), str(paths[0]), "--out", str(tmp_path / "x")]) == 2
    assert "loaded alone" in capsys.readouterr().err


def test_run_bad_folder_inputs_are_one_line_errors(tmp_path, capsys):
    def err_of(path):
        assert cli.main(["run", str(path), "--out", str(tmp_path / "o"), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("cm3d run: error:") and err.count("\n") == 1, err
        return err

    (tmp_path / "empty").mkdir()
    assert "not a recognised input folder" in err_of(tmp_path / "empty")
    (tmp_path / "imgs" / "images").mkdir(parents=True)
    assert "no .png/.jpg images" in err_of(tmp_path / "imgs")
    (tmp_path / "imgs" / "images" / "0.png").write_bytes(b"not a png")
    assert "cannot read image" in err_of(tmp_path / "imgs")
    tum = tmp_path / "tum"
    tum.mkdir()
    (tum / "rgb.txt").write_text("1.0 a.png\n2.0 b.png\n")
    assert "depth.txt missing" in err_of(tum)
    (tum / "depth.txt").write_text("1.0 a_d.png\nnot-a-time b_d.png\n")
    assert "depth.txt:2: bad timestamp" in err_of(tum)
    (tmp_path / "seq.txt").write_text("x")
    assert "unsupported file type" in err_of(tmp_path / "seq.txt")
