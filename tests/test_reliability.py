"""Issue 25: a memory bank that never loses or corrupts a map, and runs that refuse to make things
worse. One regression test per reported case: racing writers, a tampered header, a killed save,
file modes, noise input, sensor holes, tiny motion, depth holes in the metric, late failures,
misleading messages, and a fuzz of both file readers on random byte damage."""

import dataclasses
import hashlib
import json
import os
import struct
import subprocess
import sys
import textwrap
import time
import types

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cm3d import cli, memory, outputs
from cm3d.data import io, synthetic
from cm3d.data.sequence import Sequence

CFG = memory.MemoryConfig(max_maps=4, max_points=16, max_keyframes=2, max_keypoints=8, hash_bits=32)


def with_map(bank, i: int):
    """``bank`` with a tiny map i (10 + i valid points) in its first free slot (host side, no compile)."""
    f = {x.name: np.array(getattr(bank, x.name)) for x in dataclasses.fields(bank)}
    slot = int(np.flatnonzero(~f["map_valid"])[0])
    f["points"][slot] = np.random.default_rng(i).normal(size=f["points"].shape[1:])
    f["point_valid"][slot] = np.arange(f["point_valid"].shape[1]) < 10 + i
    f["map_valid"][slot], f["visits"][slot], f["voxel_size"][slot] = True, 1, 0.1
    return memory.MemoryBank(**f)


def point_counts(bank) -> list:
    valid = np.asarray(bank.map_valid)
    return sorted(int(n) for n in np.asarray(bank.point_valid).sum(1)[valid])


@pytest.fixture(scope="module")
def empty_bank():
    return memory.empty(CFG)


# ---------------------------------------------------------------------------------------------
# the bank file: transactions, checksum, killed saves, modes
# ---------------------------------------------------------------------------------------------


def test_two_processes_racing_on_one_bank_keep_both_maps(tmp_path, empty_bank):
    path = tmp_path / "bank.cm3d"
    memory.save(empty_bank, path, CFG)
    script = textwrap.dedent(f"""
        import sys, time, pathlib
        sys.path.insert(0, {os.path.dirname(__file__)!r})
        from cm3d import memory
        from test_reliability import CFG, with_map
        snap = memory.snapshot({str(path)!r})
        new = with_map(snap.bank, 1)
        pathlib.Path({str(tmp_path / 'ready')!r}).touch()
        while not pathlib.Path({str(tmp_path / 'go')!r}).exists():
            time.sleep(0.001)
        memory.commit({str(path)!r}, snap, new, CFG)
    """)
    mine = memory.snapshot(path)  # both read the same bank, then both store a new map at once
    child = subprocess.Popen([sys.executable, "-c", script])
    new = with_map(mine.bank, 0)
    deadline = time.monotonic() + 120
    while not (tmp_path / "ready").exists():
        assert child.poll() is None and time.monotonic() < deadline, "the other writer failed"
        time.sleep(0.002)
    (tmp_path / "go").touch()
    _, report = memory.commit(path, mine, new, CFG)
    assert child.wait() == 0
    bank, _ = memory.load(path)
    assert point_counts(bank) == [10, 11]  # both maps: no lost update, whichever committed first
    w = report.maps[0]
    assert (w.action, w.bank_map) in (("new", 0), ("appended", 1)) and report.bank_changed == (w.action == "appended")


def test_merge_keeps_both_updates_of_one_map_and_records_the_move(empty_bank):
    base = with_map(empty_bank, 0)

    def updated(bank, visits):  # a visit merged into map 0
        return bank.replace(visits=np.where(np.arange(CFG.max_maps) == 0, visits, np.asarray(bank.visits)))

    ours, theirs = updated(base, 2), updated(with_map(base, 3), 5)  # both merged a visit into map 0
    merged, writes = memory.merge_banks(base, ours, theirs)
    assert [(w.run_map, w.bank_map, w.action) for w in writes] == [(0, 2, "appended")]
    assert list(np.asarray(merged.visits)[:3]) == [5, 1, 2]  # theirs kept in place, ours appended
    assert "changed in the bank" in writes[0].reason
    # a slot only this run changed is written in place
    merged, writes = memory.merge_banks(base, with_map(base, 1), updated(base, 4))
    assert [(w.run_map, w.bank_map, w.action) for w in writes] == [(1, 1, "new")]
    assert point_counts(merged) == [10, 11] and int(merged.visits[0]) == 4


def _flip(data: bytes, needle: bytes, offset: int, bit: int) -> bytes:
    i = data.index(needle) + offset
    out = bytearray(data)
    out[i] ^= 1 << bit
    return bytes(out)


def test_a_flipped_header_bit_fails_to_load(tmp_path, empty_bank):
    path = tmp_path / "bank.cm3d"
    memory.save(with_map(empty_bank, 0), path, CFG)
    data = path.read_bytes()
    # accept_bias 0.5388 -> 8.5388 (the reported case), hash_seed 0 -> 1, max_rmse 0.775 -> 0.?75
    for needle, offset, bit in ((b'"accept_bias": 0.5', 15, 3), (b'"hash_seed": 0', 13, 0), (b'"max_rmse": 0.7', 14, 0)):
        path.write_bytes(_flip(data, needle, offset, bit))
        with pytest.raises(memory.MemoryFileError, match="checksum mismatch"):
            memory.load(path)


def test_damaged_headers_say_so_and_old_versions_load_with_a_note_then_upgrade(tmp_path, empty_bank):
    path = tmp_path / "bank.cm3d"
    header = json.dumps({"config": {}}).encode()
    path.write_bytes(memory.MAGIC + struct.pack("<Q", len(header)) + header)
    with pytest.raises(memory.MemoryFileError, match="no format version") as e:
        memory.load(path)
    assert "None" not in str(e.value)
    path.write_bytes(memory.MAGIC + struct.pack("<Q", 5) + b"[1,2]")
    with pytest.raises(memory.MemoryFileError, match="not a JSON object"):
        memory.load(path)
    # a version-3 file (payload checksum inside an unchecked header) loads with a note ...
    bank = with_map(empty_bank, 0)
    arrays = memory.io._fields(bank)
    payload = b"".join(np.ascontiguousarray(a).tobytes() for a in arrays.values())
    h = json.dumps({"version": 3, "config": dataclasses.asdict(CFG),
                    "arrays": [[k, list(a.shape), a.dtype.str] for k, a in arrays.items()],
                    "sha256": hashlib.sha256(payload).hexdigest()}).encode()
    path.write_bytes(memory.MAGIC + struct.pack("<Q", len(h)) + h + payload)
    snap = memory.snapshot(path)
    assert snap.version == 3 and "version 3" in snap.note and "rewrites it as version 4" in snap.note
    # ... and the next save writes version 4
    _, report = memory.commit(path, snap, with_map(snap.bank, 1), CFG)
    assert report.upgraded_from == 3 and memory.read(path).version == memory.FORMAT_VERSION == 4
    assert memory.read(path).note is None and point_counts(memory.load(path)[0]) == [10, 11]


def test_kill_9_at_random_points_in_save_never_leaves_an_unreadable_bank(tmp_path):
    cfg = memory.MemoryConfig(max_maps=8, max_points=4096, max_keyframes=4, max_keypoints=64, hash_bits=32)
    path = tmp_path / "bank.cm3d"
    a, b = tmp_path / "a.cm3d", tmp_path / "b.cm3d"
    empty = memory.empty(cfg)
    banks = [empty, with_map(empty, 0)]
    for bank, p in zip(banks, (a, b)):
        memory.save(bank, p, cfg)
        np.savez(p.with_suffix(".npz"), **{f.name: np.asarray(getattr(bank, f.name)) for f in dataclasses.fields(bank)})
    path.write_bytes(a.read_bytes())
    (tmp_path / "cfg.json").write_text(json.dumps(dataclasses.asdict(cfg)))
    # a writer that saves A and B in turn, forked afresh for each kill (numpy banks: it never touches JAX)
    script = textwrap.dedent(f"""
        import json, os, random, signal, time
        import numpy as np
        from cm3d import memory
        cfg = memory.config_from_dict(json.load(open({str(tmp_path / "cfg.json")!r})))
        banks = [memory.MemoryBank(**dict(np.load(p))) for p in ({str(a.with_suffix(".npz"))!r},
                                                                  {str(b.with_suffix(".npz"))!r})]
        whole = {{open({str(a)!r}, "rb").read(), open({str(b)!r}, "rb").read()}}
        rng, states = random.Random(25), []
        for k in range(20):
            pid = os.fork()
            if pid == 0:
                i = k
                while True:
                    memory.save(banks[i % 2], {str(path)!r}, cfg)
                    i += 1
            time.sleep(rng.uniform(0.0, 0.012))
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            states.append(open({str(path)!r}, "rb").read() in whole)
        print(json.dumps(states))
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-3000:]
    states = json.loads(out.stdout.strip().splitlines()[-1])
    assert len(states) == 20 and all(states)  # after every kill: bank A or bank B, whole, never torn
    memory.load(path)
    # the temporary files killed saves left: the next save removes ours once they are stale, and only those
    import re

    ours = re.compile(r"\.bank\.cm3d\.[a-z0-9_]{8}\.tmp")  # atomic_write's temporary names for bank.cm3d
    left = [p for p in tmp_path.iterdir() if ours.fullmatch(p.name)]
    (tmp_path / ".bank.cm3d.abcd1234.tmp").write_bytes(b"x" * 1000)  # one more, should no kill have left any
    left.append(tmp_path / ".bank.cm3d.abcd1234.tmp")
    fresh = tmp_path / ".bank.cm3d.young123.tmp"  # a save in flight elsewhere: too young to touch
    fresh.write_bytes(b"x")
    other = tmp_path / ".other.cm3d.abcdefgh.tmp"  # not ours
    other.write_bytes(b"x")
    old = time.time() - 3600
    for p in left + [other]:
        os.utime(p, (old, old))
    memory.save(empty, path, cfg)
    assert not [p for p in left if p.exists()] and fresh.exists() and other.exists()


def test_files_are_written_with_the_umask(tmp_path, empty_bank):
    mask = os.umask(0o027)
    try:
        memory.save(empty_bank, tmp_path / "bank.cm3d", CFG)
        outputs.write_json(tmp_path / "facts.json", {"a": 1})
    finally:
        os.umask(mask)
    for name in ("bank.cm3d", "facts.json"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o640, name


# ---------------------------------------------------------------------------------------------
# runs that refuse to make things worse
# ---------------------------------------------------------------------------------------------

WORLD = synthetic.WorldConfig(height=48, width=64, supersample=1)


def test_input_statistics_equal_their_plain_formulas():
    from cm3d.data import quality

    rng = np.random.default_rng(4)
    smooth = np.cumsum(rng.integers(0, 3, (2, 20, 24, 3)), axis=2).clip(0, 255)
    images = np.concatenate([smooth, rng.integers(0, 256, (1, 20, 24, 3)), np.full((1, 20, 24, 3), 7)]).astype(np.uint8)
    grey = quality.grey_levels(images)
    assert np.array_equal(grey, images.astype(np.float64).mean(-1))
    r = lambda a, b: np.corrcoef(a.ravel(), b.ravel())[0, 1]  # noqa: E731
    corr = [0.5 * (r(g[:, :-1], g[:, 1:]) + r(g[:-1], g[1:])) for g in grey[:3]]
    np.testing.assert_allclose(quality.neighbour_correlation(grey), corr + [1.0], atol=1e-12)  # constant frame: 1
    gx, gy = np.diff(grey, axis=2)[:, :-1], np.diff(grey, axis=1)[:, :, :-1]
    np.testing.assert_array_equal(quality.textured_share(grey),
                                  (np.hypot(gx, gy) > quality.TEXTURE_LEVELS).mean((1, 2)))


def test_input_assessment_takes_its_image_medians_over_evenly_spaced_frames():
    from cm3d.data import quality

    seq = synthetic.generate(0, 0, 8, "moderate", WORLD)
    n = 40
    tile = lambda a: np.concatenate([np.asarray(a)] * (n // 8))  # noqa: E731
    long = seq.replace(images=tile(seq.images), depth=tile(seq.depth), depth_conf=tile(seq.depth_conf),
                       cam_to_world=tile(seq.cam_to_world))
    picked = np.unique(np.linspace(0, n - 1, quality.ASSESSED_FRAMES).round().astype(int))
    assert len(picked) == quality.ASSESSED_FRAMES and picked[0] == 0 and picked[-1] == n - 1
    noise = np.random.default_rng(1).integers(0, 256, long.images.shape, dtype=np.uint8)
    skipped = np.setdiff1d(np.arange(n), picked)
    q = quality.assess_input(long)
    # frames between the picked ones do not enter the medians ...
    assert quality.assess_input(long.replace(images=np.where(np.isin(np.arange(n), skipped)[:, None, None, None],
                                                             noise, long.images))) == q
    grey = quality.grey_levels(np.asarray(long.images)[picked])
    assert q.neighbour_correlation == np.median(quality.neighbour_correlation(grey))
    assert q.textured_share == np.median(quality.textured_share(grey))
    # ... and noise in the picked ones is found
    bad = quality.assess_input(long.replace(images=noise))
    assert bad.degenerate and "random noise" in bad.problems[0] and not q.degenerate


def test_a_noise_sequence_stores_nothing_and_keeps_the_prior(tmp_path, empty_bank, capsys):
    seq = synthetic.generate(0, 0, 8, "moderate", WORLD)
    noise = seq.replace(images=np.random.default_rng(0).integers(0, 256, seq.images.shape, dtype=np.uint8))
    io.save_sequence(tmp_path / "noise.npz", noise)
    bank = tmp_path / "bank.cm3d"
    memory.save(with_map(empty_bank, 0), bank, CFG)
    before = bank.read_bytes()
    out = tmp_path / "out"
    assert cli.main(["run", str(tmp_path / "noise.npz"), "--out", str(out), "--memory", str(bank), "--quiet",
                     "--no-pictures"]) == 0
    text = capsys.readouterr().out
    assert "random noise" in text and "nothing stored" in text
    assert bank.read_bytes() == before  # nothing stored, not even a rewrite
    _, est = io.read_tum(out / "trajectory.txt")
    _, prior = io.read_tum(out / "trajectory_prior.txt")
    np.testing.assert_array_equal(est, prior)
    m = json.loads((out / "metrics.json").read_text())
    assert m["refinement_kept"] is False and "random noise" in m["warnings"][0]
    run = json.loads((out / "recall.json").read_text())["run"]
    assert not run["stored_in_memory"] and run["input"]["problems"] and run["photometric_check"] is None


def _holes(seq, share: float, seed: int):
    """``seq`` with sensor holes (depth 0, confidence 0) in smooth random blobs covering ``share``."""
    import cv2

    rng = np.random.default_rng(seed)
    S, h, w = seq.depth.shape
    m = np.zeros((S, h, w), bool)
    for t in range(S):
        field = cv2.GaussianBlur(rng.normal(size=(h, w)).astype(np.float32), (0, 0), 2.0)
        m[t] = field > np.quantile(field, 1 - share)
    return seq.replace(depth=np.where(m, 0, seq.depth).astype(np.float32),
                       depth_conf=np.where(m, 0, seq.depth_conf).astype(np.float32)), m


def test_hole_heavy_depth_refines():
    from cm3d import pipeline

    seq = synthetic.generate(5, 0, 8, "moderate", WORLD)
    holed, m = _holes(seq, 0.2, 5)
    assert 0.19 < m.mean() < 0.21
    # the memory program, each sequence with its own empty bank (nothing to recall: the memory-free poses,
    # tests/test_pipeline.py), which is the program the experiments' 48x64 smoke runs compile
    cfg = pipeline.small_config()
    (_, (clean,)), (_, (holes,)) = pipeline.run([seq], cfg), pipeline.run([holed], cfg)
    got = [outputs.sequence_metrics(r)["ate_reduction_pct"] for r in (clean, holes)]
    assert got[0] > 40 and got[1] > got[0] - 10, got  # within 10 points of the hole-free refinement
    assert holes.report.refinement_kept
    # the prior's holes are not scored as predictions
    assert outputs.sequence_metrics(holes)["depth_prior"]["abs_rel"] < 2 * outputs.sequence_metrics(clean)[
        "depth_prior"]["abs_rel"]


def test_the_photometric_check_refuses_poses_the_images_disagree_with():
    from cm3d.pipeline import check_refinement
    from cm3d.ops import se3

    seq = synthetic.generate(0, 0, 8, "none", WORLD)
    exact = np.asarray(seq.cam_to_world, np.float64)
    rng = np.random.default_rng(0)
    noisy = np.einsum("nij,njk->nik", exact, np.asarray(se3.exp(np.concatenate(
        [0.01 * rng.normal(size=(8, 3)), 0.03 * rng.normal(size=(8, 3))], 1)), np.float64))
    worse = check_refinement(seq, exact, noisy)
    better = check_refinement(seq, noisy, exact)
    assert not worse.kept and "worse" in worse.reason and worse.refined_error > worse.prior_error
    assert better.kept and better.refined_error < better.prior_error
    assert check_refinement(seq, exact, exact).kept  # unchanged poses: nothing to earn


def test_the_in_graph_warp_error_equals_the_host_check():
    """cm3d.ops.warp (the memory solution's photometric test, pure JAX) against the host check's numpy
    warp_errors: the same errors and paired pixels; jit / vmap invariant; frames outside ``valid`` skipped."""
    import jax
    import jax.numpy as jnp

    from cm3d.ops import se3, warp
    from cm3d.pipeline.photometric import warp_errors

    seq = synthetic.generate(0, 0, 7, "moderate", WORLD)
    dyn = np.asarray(seq.gt.dynamic_mask, bool)
    rng = np.random.default_rng(1)
    prior = np.asarray(seq.cam_to_world, np.float64)
    moved = np.einsum("nij,njk->nik", prior, np.asarray(se3.exp(np.concatenate(
        [0.01 * rng.normal(size=(7, 3)), 0.01 * rng.normal(size=(7, 3))], 1)), np.float64))
    H, W = seq.depth.shape[1:]
    step = warp.sample_step(H, W, 1000)
    args = (jnp.asarray(seq.images), jnp.asarray(seq.depth), jnp.asarray(seq.depth_conf), jnp.asarray(~dyn),
            jnp.asarray(seq.intrinsic, jnp.float32))
    trajs = jnp.asarray(np.stack([prior, moved]), jnp.float32)
    fn = jax.jit(warp.paired_warp_errors, static_argnames=("gaps", "step"))
    for valid in (np.ones(7, bool), np.arange(7) < 5):
        ref, n = warp_errors(types.SimpleNamespace(images=seq.images[valid], depth=seq.depth[valid],
                                                   depth_conf=seq.depth_conf[valid], intrinsic=seq.intrinsic[valid]),
                             [prior[valid], moved[valid]], dyn[valid], (1, 2, 4), 1000)
        got, m = fn(*args, trajs, jnp.asarray(valid), gaps=(1, 2, 4), step=step)
        assert int(m) == int(n.sum()) > 1000
        np.testing.assert_allclose(np.asarray(got), ref.mean(0), rtol=2e-4)
        assert got[1] > got[0]  # the perturbed poses disagree with the images
    # the memory solution's test (pipeline.memory_graph.photometric_test) on these frames as a window,
    # vmapped over (memory-free, memory) cases: memory moved the poses well off (refused), the other way round
    # (used: better on the mean and on more frame pairs than chance), a tie (the memory-free poses kept: the
    # memory must make the images agree better), and no static pixel at all (no evidence, no objection)
    from cm3d.pipeline.memory_graph import photometric_test

    def test(static, free, with_memory):
        win = types.SimpleNamespace(image=args[0], depth=args[1], conf=args[2], static=static, intrinsic=args[4],
                                    valid=jnp.ones(7, bool))
        return photometric_test(win, free, with_memory)

    a, none = trajs[0], jnp.zeros_like(args[3])
    b = jnp.asarray(np.einsum("nij,njk->nik", prior, np.asarray(se3.exp(np.concatenate(  # well off on every frame
        [0.05 * rng.normal(size=(7, 3)), 0.1 * rng.normal(size=(7, 3))], 1)), np.float64)), jnp.float32)
    ok, _, _, p = jax.jit(jax.vmap(test))(jnp.stack([args[3], args[3], args[3], none]), jnp.stack([a, b, a, a]),
                                          jnp.stack([b, a, a, b]))
    assert np.asarray(ok).tolist() == [False, True, False, True]
    assert float(p[1]) < 0.05  # the memory solution that is used wins on the frame pairs too


def test_photometric_decision_counts_frame_pairs_against_chance():
    """A memory solution whose mean grey error is lower only because the memory-free poses misplace one
    frame (4 of 24 frame pairs much worse), while it is the worse one on most other pairs, is refused:
    the sign test over the pairs (pipeline.memory_graph.photometric_decision); better on 20 of 24 is used;
    a window without paired pixels raises no objection."""
    import jax
    import jax.numpy as jnp

    from cm3d.pipeline.memory_graph import photometric_decision

    rng = np.random.default_rng(0)
    free = 6.0 + rng.uniform(0, 1, 24)
    one_frame = np.stack([free + np.where(np.arange(24) < 4, 3.0, 0.0), free * 1.01], 1)  # mean favours memory
    mostly = np.stack([free, free * np.where(np.arange(24) < 20, 0.97, 1.01)], 1)
    n = np.full(24, 500)
    ok, e_free, e_mem, p = jax.vmap(photometric_decision)(jnp.asarray(np.stack([one_frame, mostly, mostly])),
                                                          jnp.asarray(np.stack([n, n, 0 * n])))
    assert float(e_mem[0]) < float(e_free[0]) and float(p[0]) > 0.9
    assert np.asarray(ok).tolist() == [False, True, True] and float(p[1]) < 1e-3


def test_sign_test_against_scipy():
    """pipeline.memory_graph.sign_test: the binomial upper tail P(X >= k), X ~ Binomial(n, 1/2)."""
    from scipy.stats import binom

    from cm3d.pipeline.memory_graph import sign_test

    k = np.array([0, 1, 3, 10, 17, 30, 41, 60])
    n = np.array([0, 5, 3, 20, 20, 40, 60, 60])
    got = np.asarray(sign_test(k, n - k))
    want = np.where(k > 0, binom.sf(k - 1, n, 0.5), 1.0)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-7)


# ---------------------------------------------------------------------------------------------
# metrics that do not mislead
# ---------------------------------------------------------------------------------------------


def _result(gt_c2w, prior, refined, depth, gt_depth):
    S = len(gt_c2w)
    gt = types.SimpleNamespace(cam_to_world=gt_c2w, depth=gt_depth, dynamic_mask=None)
    seq = types.SimpleNamespace(gt=gt, timestamps=np.arange(S, dtype=np.float64), num_frames=S, depth=depth)
    return types.SimpleNamespace(sequence=seq, prior=prior, poses=refined, masks=None, report=None)


def _rotated(T, deg, rng):
    from cm3d.ops import se3

    w = np.radians(deg) * rng.normal(size=(len(T), 3)) / np.sqrt(3)
    return np.einsum("nij,njk->nik", T, np.asarray(se3.exp(np.concatenate([np.zeros_like(w), w], 1)), np.float64))


def test_the_tiny_motion_metric_is_flagged():
    rng = np.random.default_rng(0)
    S = 8
    gt = np.tile(np.eye(4), (S, 1, 1))
    gt[:, 0, 3] = 1e-6 * np.arange(S)  # a camera that barely moves
    prior, refined = _rotated(gt, 2.87, rng), _rotated(gt, 0.07, rng)
    prior[:, :3, 3] += 0.01 * rng.normal(size=(S, 3))
    refined[:, :3, 3] += 0.0005 * rng.normal(size=(S, 3))
    d = np.ones((S, 48, 64), np.float32)
    m = outputs.sequence_metrics(_result(gt, prior, refined, d, d))
    assert not m["ate_defined"] and not m["prior"]["ate_defined"] and not m["refined"]["ate_defined"]
    assert m["prior"]["ate"] < 1e-5  # the Sim(3) fit shrinks any estimate onto this trajectory
    assert 2.0 < m["prior"]["rot_rmse"] < 4.0 and m["refined"]["rot_rmse"] < 0.2  # what did improve
    line = outputs.headline(m)
    assert "%" not in line and "undefined" in line and "rotation" in line
    # a trajectory that moves well beyond its noise keeps a defined ATE and its percentage
    gt[:, 0, 3] = 0.1 * np.arange(S)
    prior, refined = gt.copy(), gt.copy()
    prior[:, :3, 3] += 0.01 * rng.normal(size=(S, 3))
    refined[:, :3, 3] += 0.001 * rng.normal(size=(S, 3))
    m = outputs.sequence_metrics(_result(gt, prior, refined, d, d))
    assert m["ate_defined"] and m["ate_reduction_pct"] > 50 and "%" in outputs.headline(m)
    # two frames: a Sim(3) fit is exact whatever the poses
    from cm3d.eval import metrics

    assert not metrics.ate_is_defined(0.0, 1.0, 2) and metrics.ate_is_defined(0.0, 1.0, 3)


def test_depth_metrics_skip_pixels_without_a_prediction():
    rng = np.random.default_rng(1)
    gt_depth = rng.uniform(1.0, 3.0, (8, 48, 64)).astype(np.float32)
    pred = gt_depth * (1 + 0.01 * rng.normal(size=gt_depth.shape)).astype(np.float32)
    holes = rng.random(gt_depth.shape) < 0.2
    gt_depth[0, 0, 0] = 0.0  # no ground truth there
    poses = np.tile(np.eye(4), (8, 1, 1))
    poses[:, 0, 3] = np.arange(8)
    full = outputs.sequence_metrics(_result(poses, poses, poses, pred, gt_depth))["depth_prior"]
    holed = outputs.sequence_metrics(_result(poses, poses, poses, np.where(holes, 0, pred), gt_depth))["depth_prior"]
    assert full["abs_rel"] < 0.02 and holed["abs_rel"] < 0.02 and holed["delta1"] == 1.0


# ---------------------------------------------------------------------------------------------
# fail early, say it clearly
# ---------------------------------------------------------------------------------------------


def test_unwritable_out_and_bank_fail_before_any_work(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    missing = str(tmp_path / "missing.npz")  # never read: the path checks come first
    assert cli.main(["run", missing, "--out", str(blocker / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--out" in err and "cannot write there" in err and "Errno" not in err
    assert cli.main(["run", missing, "--out", str(tmp_path / "o"), "--memory", str(blocker / "bank.cm3d")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--memory" in err and "is not a folder" in err


def test_a_held_bank_lock_is_a_one_line_error(tmp_path, empty_bank, capsys, monkeypatch):
    import functools

    from cm3d.data import atomic
    from cm3d.memory import transaction

    path = tmp_path / "bank.cm3d"
    memory.save(with_map(empty_bank, 0), path, CFG)
    monkeypatch.setattr(transaction, "locked", functools.partial(atomic.locked, timeout=0.2))
    with atomic.locked(path):  # another writer (a second open file: flock conflicts within one process too)
        assert cli.main(["memory", "rm", str(path), "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bank.cm3d.lock" in err and "another process" in err
    assert cli.main(["memory", "rm", str(path), "0"]) == 0  # released: the same command goes through


def test_eval_flags_an_undefined_ate(tmp_path, capsys):
    from cm3d.data.tum import write_tum

    rng = np.random.default_rng(0)
    gt = np.tile(np.eye(4), (8, 1, 1))
    gt[:, 0, 3] = 1e-6 * np.arange(8)
    est = _rotated(gt, 2.87, rng)
    est[:, :3, 3] += 0.01 * rng.normal(size=(8, 3))
    ts = np.arange(8) * 0.1
    write_tum(tmp_path / "gt.txt", ts, gt)
    write_tum(tmp_path / "est.txt", ts, est)
    args = ["eval", "--gt", str(tmp_path / "gt.txt"), "--est", str(tmp_path / "est.txt")]
    assert cli.main(args) == 0
    out = capsys.readouterr().out
    assert "ATE (Sim3) undefined" in out and "rotation" in out
    assert cli.main(args + ["--json"]) == 0
    m = json.loads(capsys.readouterr().out)
    assert m["ate_defined"] is False and 2.0 < m["rot_rmse"] < 4.0 and m["extent"] < 1e-5


def test_messages_name_the_file_and_the_problem(tmp_path, capsys):
    text = tmp_path / "notes.npz"
    text.write_text("these are my notes\n")
    with pytest.raises(io.SequenceFormatError, match="not an .npz archive") as e:
        io.load_sequence(text)
    assert "pickle" not in str(e.value)
    one = tmp_path / "one.npz"
    io.save_sequence(one, Sequence(images=np.zeros((1, 16, 16, 3), np.uint8), depth=np.ones((1, 16, 16), np.float32),
                                   depth_conf=np.ones((1, 16, 16), np.float32), intrinsic=np.eye(3)[None],
                                   cam_to_world=np.eye(4)[None], timestamps=np.zeros(1)))
    assert cli.main(["run", str(one), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert str(one) in err and "at least 2 frames" in err and err.count("\n") == 1


# ---------------------------------------------------------------------------------------------
# fuzz: random byte damage either loads identically or raises the documented error
# ---------------------------------------------------------------------------------------------

damage = st.one_of(
    st.tuples(st.just("flip"), st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(0, 7)),
                                        min_size=1, max_size=3), st.booleans()),
    st.tuples(st.just("cut"), st.floats(0, 1, exclude_max=True), st.just(False)))


def _damaged(data: bytes, how, head: int) -> bytes:
    """Bit flips at relative positions (``focus``: inside the first ``head`` bytes) or a truncation."""
    kind, where, focus = how
    if kind == "cut":
        return data[: int(where * len(data))]
    out = bytearray(data)
    for pos, bit in where:
        out[int(pos * (head if focus else len(data)))] ^= 1 << bit
    return bytes(out)


@pytest.fixture(scope="module")
def fuzz_files(tmp_path_factory, empty_bank):
    d = tmp_path_factory.mktemp("fuzz")
    bank = with_map(with_map(empty_bank, 0), 1)
    memory.save(bank, d / "bank.cm3d", CFG)
    rng = np.random.default_rng(0)
    S, H, W = 2, 6, 8
    seq = Sequence(images=rng.integers(0, 256, (S, H, W, 3), dtype=np.uint8),
                             depth=rng.uniform(1, 2, (S, H, W)).astype(np.float32),
                             depth_conf=np.ones((S, H, W), np.float32),
                             intrinsic=np.tile(np.array([[8.0, 0, 4], [0, 8, 3], [0, 0, 1]]), (S, 1, 1)),
                             cam_to_world=np.tile(np.eye(4), (S, 1, 1)), timestamps=np.arange(S, dtype=np.float64))
    io.save_sequence(d / "seq.npz", seq)
    io.save_sequence(d / "seqz.npz", seq, compress=True)
    return d, memory.load(d / "bank.cm3d"), io.load_sequence(d / "seq.npz")


@settings(max_examples=120, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(how=damage)
def test_fuzz_bank_load_on_byte_damage(fuzz_files, how):
    d, good, _ = fuzz_files
    data = (d / "bank.cm3d").read_bytes()
    head = data.index(b"[[") if b"[[" in data else 256  # the config part of the header
    path = d / "damaged.cm3d"
    path.write_bytes(_damaged(data, how, head))
    try:
        bank, cfg = memory.load(path)
    except memory.MemoryFileError:
        return
    assert cfg == good[1]
    for f in dataclasses.fields(bank):
        np.testing.assert_array_equal(getattr(bank, f.name), getattr(good[0], f.name))


@settings(max_examples=120, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(how=damage, compressed=st.booleans())
def test_fuzz_load_sequence_on_byte_damage(fuzz_files, how, compressed):
    d, _, good = fuzz_files
    data = (d / ("seqz.npz" if compressed else "seq.npz")).read_bytes()
    path = d / "damaged.npz"
    path.write_bytes(_damaged(data, how, 512))  # focus: the first member's zip and .npy headers
    try:
        got = io.load_sequence(path)
    except io.SequenceFormatError:
        return
    for key in ("images", "depth", "depth_conf", "intrinsic", "cam_to_world", "timestamps"):
        np.testing.assert_array_equal(getattr(got, key), getattr(good, key))
    assert got.meta == good.meta and got.gt is None
