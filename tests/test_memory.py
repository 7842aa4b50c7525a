"""Memory bank: pytree, capacity policy, hashed recall, persistence (atomic, checksummed)."""

import dataclasses
import functools
import hashlib
import json
import os
import signal
import struct
import subprocess
import sys
import textwrap
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cm3d import memory
from cm3d.ops import descriptors
from cm3d.solvers import ransac

CFG = memory.MemoryConfig(max_maps=4, max_points=64, max_keyframes=3)
# compiled once and shared: eager JAX compiles every primitive separately, which is what made this
# file slow
_insert = jax.jit(memory.insert_map)
_cloud_descriptor = jax.jit(descriptors.cloud_descriptor)


def _entry(seed, cfg=CFG):
    rng = np.random.default_rng(seed)
    kf = rng.normal(size=(cfg.max_keyframes, cfg.image_dim)).astype(np.float32)
    kf /= np.linalg.norm(kf, axis=1, keepdims=True)
    pts = rng.normal(size=(cfg.max_points, 3)).astype(np.float32)
    return memory.MapEntry(
        points=pts, normals=np.tile([0, 0, 1.0], (cfg.max_points, 1)), conf=np.ones(cfg.max_points),
        colors=rng.integers(0, 255, (cfg.max_points, 3)).astype(np.uint8),
        point_valid=np.arange(cfg.max_points) < 50, kf_desc=kf, kf_valid=np.array([True, True, False]),
        cloud_desc=np.asarray(_cloud_descriptor(pts)), voxel_size=np.float32(0.1))


def _bank(n):
    bank = memory.empty(CFG)
    for i in range(n):
        bank, _ = _insert(bank, _entry(i))
    return bank


def test_insert_fills_slots_and_full_bank_is_refused():
    bank = _bank(4)
    assert int(bank.num_maps) == 4 and list(np.asarray(bank.visits)) == [1, 1, 1, 1]
    same, map_id = _insert(bank, _entry(9))
    assert int(map_id) == -1
    jax.tree.map(np.testing.assert_array_equal, same, bank)
    with pytest.raises(memory.MemoryFullError, match="full"):
        memory.add_map(bank, _entry(9))
    freed = jax.jit(memory.remove_map)(bank, 2)
    assert list(np.asarray(freed.map_valid)) == [True, True, False, True]
    again, map_id = _insert(freed, _entry(9))
    assert int(map_id) == 2


def test_global_table_is_the_flat_view():
    bank = _bank(2)
    table, codes, valid, map_id = memory.global_table(bank)
    assert table.shape == (4 * 3, CFG.image_dim) and list(np.asarray(map_id[:6])) == [0, 0, 0, 1, 1, 1]
    assert list(np.asarray(valid[:7])) == [True, True, False, True, True, False, False]
    np.testing.assert_array_equal(codes[1], descriptors.hash_codes(bank.kf_desc[0, 1], bank.planes))


def test_recall_votes_for_the_map_with_similar_keyframes():
    bank = _bank(3)
    rng = np.random.default_rng(5)
    q = np.asarray(bank.kf_desc[1, :2]) + 0.03 * rng.normal(size=(2, CFG.image_dim))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q = np.concatenate([q, np.zeros((1, CFG.image_dim))]).astype(np.float32)
    r = jax.jit(memory.recall, static_argnums=4)(bank, q, np.array([True, True, False]),
                                                 bank.cloud_desc[1], CFG)
    assert int(r.candidates[0]) == 1 and float(r.votes[1]) == 2.0
    assert list(np.asarray(r.candidates[1:])) == [-1] * (CFG.top_k - 1)  # no votes: never a candidate
    # an unrelated query recalls nothing
    u = rng.normal(size=(3, CFG.image_dim)).astype(np.float32)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = memory.recall(bank, u, np.ones(3, bool), bank.cloud_desc[0], CFG)
    assert list(np.asarray(r.candidates)) == [-1] * CFG.top_k


def test_recall_vmaps_over_queries():
    bank = _bank(3)
    q = jnp.stack([bank.kf_desc[i] for i in range(3)])  # (3 queries, K, D)
    qv = jnp.ones((3, CFG.max_keyframes), bool)
    batched = jax.vmap(memory.recall, in_axes=(None, 0, 0, 0, None))(bank, q, qv, bank.cloud_desc[:3], CFG)
    for i in range(3):
        single = memory.recall(bank, q[i], qv[i], bank.cloud_desc[i], CFG)
        np.testing.assert_array_equal(batched.candidates[i], single.candidates)
    assert list(np.asarray(batched.candidates[:, 0])) == [0, 1, 2]


def test_identify_without_a_2d_candidate_skips_verification_and_reports_none():
    """No 2D candidate: the 3D stages do not run (a lax.cond) and the identification says so; under vmap
    (both branches run) each query gets what it gets alone."""
    bank = _bank(3)
    rng = np.random.default_rng(7)
    u = rng.normal(size=(CFG.max_keyframes, CFG.image_dim)).astype(np.float32)
    lost = _entry(11).replace(kf_desc=u / np.linalg.norm(u, axis=1, keepdims=True))  # unlike every stored keyframe
    known = _entry(1)  # map 1's own contents: a 2D candidate
    ident = jax.jit(memory.identify, static_argnums=2)
    key = jax.random.PRNGKey(0)
    none = ident(bank, lost, CFG, key)
    assert (np.asarray(none.recall.candidates) == -1).all() and int(none.map_id) == -1 and int(none.candidate) == -1
    assert (np.asarray(none.candidate_inliers) == -1).all() and int(none.verification.inlier_count) == 0
    np.testing.assert_array_equal(np.asarray(none.verification.transform), np.eye(4))
    assert not bool(none.verification.accepted) and np.isinf(float(none.placement_error))
    some = ident(bank, known, CFG, key)
    assert int(some.recall.candidates[0]) == 1 and int(some.candidate_inliers[0]) >= 0
    both = jax.tree.map(lambda *a: jnp.stack(a), lost, known)
    batched = jax.jit(jax.vmap(lambda e: memory.identify(bank, e, CFG, key)))(both)
    for i, single in enumerate((none, some)):
        jax.tree.map(lambda b, s: np.testing.assert_allclose(np.asarray(b)[i], np.asarray(s), rtol=1e-5, atol=1e-5),
                     batched, single)


def test_save_load_round_trip(tmp_path):
    bank = _bank(3)
    memory.save(bank, tmp_path / "bank.cm3d", CFG)
    back, cfg = memory.load(tmp_path / "bank.cm3d")
    assert cfg == CFG
    jax.tree.map(np.testing.assert_array_equal, back, bank)
    assert os.listdir(tmp_path) == ["bank.cm3d"]


def test_damaged_files_fail_clearly(tmp_path):
    path = tmp_path / "bank.cm3d"
    memory.save(_bank(2), path, CFG)
    data = path.read_bytes()
    path.write_bytes(data[:-100])
    with pytest.raises(memory.MemoryFileError, match="checksum"):
        memory.load(path)
    flipped = bytearray(data)
    flipped[-5] ^= 0xFF
    path.write_bytes(bytes(flipped))
    with pytest.raises(memory.MemoryFileError, match="checksum"):
        memory.load(path)
    path.write_bytes(b"PK\x03\x04 not a bank")
    with pytest.raises(memory.MemoryFileError, match="magic"):
        memory.load(path)
    with pytest.raises(memory.MemoryFileError, match="no such"):
        memory.load(tmp_path / "missing.cm3d")


def test_refuses_to_save_non_finite_bank(tmp_path):
    bank = _bank(1)
    bank = bank.replace(points=bank.points.at[0, 0, 0].set(jnp.nan))
    with pytest.raises(ValueError, match="non-finite"):
        memory.save(bank, tmp_path / "b.cm3d", CFG)
    assert not (tmp_path / "b.cm3d").exists()


def test_killed_writer_leaves_previous_bank_loadable(tmp_path):
    path = tmp_path / "bank.cm3d"
    memory.save(_bank(2), path, CFG)
    before = path.read_bytes()
    # a writer that saves a large bank over and over; kill it mid-write
    script = textwrap.dedent(f"""
        import sys
        from cm3d import memory
        cfg = memory.MemoryConfig(max_maps=64, max_points=20000, max_keyframes=16)
        bank = memory.empty(cfg)
        print("ready", flush=True)
        while True:
            memory.save(bank, {str(path)!r}, cfg)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    # wait until a temporary file shows up (a save is in flight), then kill
    deadline, seen = time.monotonic() + 30, False
    while not seen and time.monotonic() < deadline:
        seen = any(n.endswith(".tmp") for n in os.listdir(tmp_path))
        time.sleep(0.0005)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert seen, "the writer never started a save"
    bank, cfg = memory.load(path)  # either the old bank or a complete new one, never a torn file
    assert cfg.max_maps in (CFG.max_maps, 64)
    if cfg == CFG:
        assert path.read_bytes() == before


def test_select_keyframes_spacing_and_capacity():
    # a 1-D walk in feature space: frame i sits at distance 0.1 * i from frame 0
    S, D = 30, 4
    desc = np.zeros((S, D), np.float32)
    desc[:, 0] = 0.1 * np.arange(S) + 1.0
    valid = np.ones(S, bool)
    select = jax.jit(memory.select_keyframes, static_argnums=(2, 3))
    idx, ok = select(desc, valid, 0.35, 16)
    idx = np.asarray(idx)[np.asarray(ok)]
    assert list(idx) == [0, 4, 8, 12, 16, 20, 24, 28]  # a new keyframe every 0.4 > 0.35
    idx, ok = select(desc, valid, 0.05, 5)
    assert bool(np.all(ok)) and list(np.asarray(idx)) == [0, 7, 14, 22, 29]  # over capacity: spread
    valid[:3] = False
    idx, ok = select(desc, valid, 0.35, 16)
    assert int(np.asarray(idx)[0]) == 3  # the first valid frame starts
    idx, ok = select(desc, np.zeros(S, bool), 0.35, 16)
    assert not bool(np.any(ok))


@functools.lru_cache(maxsize=1)
def _room_sequence():
    """One small render shared by the tests below (rendered once per session)."""
    from cm3d.data import synthetic

    return synthetic.generate(2, 0, 6, "slight", synthetic.WorldConfig(height=48, width=64))


SEQ_CFG = memory.MemoryConfig(max_maps=3, max_points=512, max_keyframes=4, pixel_stride=2)


@functools.partial(jax.jit, static_argnums=6)
def _cloud_and_entry(depth, conf, K, c2w, images, static, cfg):
    cloud = memory.sequence_cloud(depth, conf, K, c2w, images, static, cfg)
    d = jax.vmap(descriptors.image_descriptor)(images, static)
    idx, ok = memory.select_keyframes(d, jnp.ones(len(d), bool), 0.1, cfg.max_keyframes)
    return cloud, memory.build_entry(cloud, d[idx], ok, cfg)


@functools.lru_cache(maxsize=4)
def _entry_of(cfg=SEQ_CFG):
    """Static cloud and map entry of :func:`_room_sequence` (built once per config, jitted)."""
    seq = _room_sequence()
    return _cloud_and_entry(jnp.asarray(seq.depth), jnp.asarray(seq.depth_conf),
                            jnp.asarray(seq.intrinsic, jnp.float32), jnp.asarray(seq.cam_to_world, jnp.float32),
                            jnp.asarray(seq.images), jnp.asarray(~seq.gt.dynamic_mask), cfg)


def test_sequence_cloud_and_entry_from_a_render():
    seq = _room_sequence()
    cloud, entry = _entry_of()
    st = SEQ_CFG.pixel_stride
    assert cloud.points.shape == (6 * 24 * 32, 3)
    # static, confident pixels only; lifted points agree with the priors' own unprojection
    dyn = seq.gt.dynamic_mask[:, ::st, ::st].reshape(-1)
    assert not np.any(np.asarray(cloud.valid) & dyn)
    from cm3d.ops import camera

    full = np.asarray(jax.jit(camera.unproject)(seq.depth, seq.intrinsic, seq.cam_to_world))
    full = full[:, ::st, ::st].reshape(-1, 3)
    np.testing.assert_allclose(np.asarray(cloud.points), full, atol=1e-4)
    # downsampled to capacity, finite, with unit normals and a unit 3D descriptor
    n = int(entry.point_valid.sum())
    assert 100 < n <= SEQ_CFG.max_points
    assert np.all(np.isfinite(np.asarray(entry.points)))
    norms = np.linalg.norm(np.asarray(entry.normals)[np.asarray(entry.point_valid)], axis=1)
    assert np.mean(np.abs(norms - 1) < 1e-3) > 0.95
    assert abs(float(jnp.linalg.norm(entry.cloud_desc)) - 1) < 1e-5
    assert float(entry.voxel_size) > 0


def test_capacity_grows_the_voxel_instead_of_dropping_points():
    """The capacity policy of build_entry / update_map (downsample_to_capacity), on the render's cloud."""
    from cm3d.ops.voxel import adaptive_voxel_size

    cloud, _ = _entry_of()
    feats = jnp.concatenate([cloud.colors.astype(jnp.float32), cloud.conf[:, None]], axis=1)
    vs0 = adaptive_voxel_size(cloud.points, cloud.valid, 60.0)
    vox, vs = jax.jit(memory.downsample_to_capacity, static_argnums=4)(cloud.points, cloud.valid, feats, vs0, 64)
    assert 0 < int(vox.count) <= 64 and float(vs) > float(vs0)
    # the mean of all voxel points still covers the whole cloud (nothing was cut away)
    pts = np.asarray(cloud.points)[np.asarray(cloud.valid)]
    lo, hi = pts.min(0), pts.max(0)
    vox = np.asarray(vox.points)[np.asarray(vox.valid)]
    assert np.all(vox.min(0) < lo + 0.35 * (hi - lo)) and np.all(vox.max(0) > hi - 0.35 * (hi - lo))


def test_relocalize_applies_a_similarity_to_poses():
    from cm3d.ops import se3

    xi = np.concatenate([[[0.3, -0.2, 0.5, 0.1, 0.4, -0.2]], np.random.default_rng(0).normal(size=(4, 6)) * 0.3])
    poses = np.asarray(jax.jit(se3.exp)(jnp.asarray(xi, jnp.float32)))  # one compiled call, not eager ops
    T, cams = poses[0], poses[1:]
    S = T.copy()
    S[:3, :3] *= 2.0  # scale 2
    out = np.asarray(jax.jit(memory.relocalize)(jnp.asarray(S), jnp.asarray(cams)))
    np.testing.assert_allclose(out[:, :3, :3], T[:3, :3] @ cams[:, :3, :3], atol=1e-5)
    np.testing.assert_allclose(out[:, :3, 3], cams[:, :3, 3] @ S[:3, :3].T + S[:3, 3], atol=1e-5)


def test_update_map_merges_into_the_map_frame():
    _, entry = _entry_of()
    bank, m = _insert(memory.empty(SEQ_CFG), entry)
    # the same cloud, expressed in a frame 2x larger and shifted: moved back by the transform
    S = np.diag([2.0, 2.0, 2.0, 1.0])
    S[:3, 3] = [1.0, -2.0, 0.5]
    moved = entry.replace(points=entry.points * 2.0 + jnp.array([1.0, -2.0, 0.5]))
    Sinv = np.linalg.inv(S)
    merged = jax.jit(memory.update_map, static_argnums=4)(bank, m, moved, jnp.asarray(Sinv, jnp.float32), SEQ_CFG)
    assert int(merged.visits[m]) == 2
    a = np.asarray(bank.points[m])[np.asarray(bank.point_valid[m])]
    b = np.asarray(merged.points[m])[np.asarray(merged.point_valid[m])]
    from scipy.spatial import cKDTree

    d, _ = cKDTree(a).query(b)
    assert np.median(d) < 0.5 * float(bank.voxel_size[m])  # merged voxels lie on the old map
    assert int(merged.point_valid[m].sum()) <= SEQ_CFG.max_points
    assert int(merged.kf_valid[m].sum()) == min(SEQ_CFG.max_keyframes, 2 * int(entry.kf_valid.sum()))


def test_update_map_adds_only_new_surface_unless_told_to_pool():
    """A revisit placed a little off (0.4 voxel) leaves the stored surface as it was (the default new-surface
    merge of a recall), where pooling every voxel (``merge_new_surface_only=False``, or a query in the map's
    own frame: ``same_frame``) pulls the stored points towards it; surface the map does not hold (the same
    cloud 100 voxels away) is added either way."""
    from scipy.spatial import cKDTree

    _, entry = _entry_of()
    assert SEQ_CFG.merge_new_surface_only
    bank, m = _insert(memory.empty(SEQ_CFG), entry)
    vs = float(bank.voxel_size[m])
    ok = np.asarray(bank.point_valid[m])
    before = np.asarray(bank.points[m])[ok]
    eye = jnp.eye(4, dtype=jnp.float32)
    pool_cfg = dataclasses.replace(SEQ_CFG, merge_new_surface_only=False)
    update = jax.jit(memory.update_map, static_argnums=4)
    for cfg, same_frame, new_only in ((SEQ_CFG, False, True), (pool_cfg, False, False), (SEQ_CFG, True, False)):
        off = update(bank, m, entry.replace(points=entry.points + jnp.float32(0.4 * vs)), eye, cfg, same_frame)
        after = np.asarray(off.points[m])[np.asarray(off.point_valid[m])]
        moved = np.median(cKDTree(after).query(before)[0]) / vs  # how far the stored surface's points went
        if new_only:
            assert len(after) == len(before) and moved < 1e-3
        else:
            assert moved > 0.1
        far = update(bank, m, entry.replace(points=entry.points + jnp.float32(100 * vs)), eye, cfg, same_frame)
        got = np.asarray(far.points[m])[np.asarray(far.point_valid[m])]
        nearer_far = cKDTree(before + 100 * vs).query(got)[0] < cKDTree(before).query(got)[0]
        assert 0.25 < np.mean(nearer_far) < 0.75  # both copies held (over capacity: pooled, the voxel grown)
    # new surface that fits the capacity: added beside the stored points, which stay exactly as they were
    few = entry.replace(points=entry.points + jnp.float32(100 * vs),
                        point_valid=entry.point_valid & (jnp.arange(entry.points.shape[0]) < 12))
    out = update(bank, m, few, eye, SEQ_CFG, False)
    got = np.asarray(out.points[m])[np.asarray(out.point_valid[m])]
    assert len(before) < len(got) <= len(before) + 12 and float(out.voxel_size[m]) == vs
    assert np.max(cKDTree(got).query(before)[0]) < 1e-6


def test_verifying_icp_keeps_the_keypoint_scale_and_refines_the_rest():
    """The verifying ICP (``icp_scale=False``, the default) keeps the scale of its start (the keypoints'
    RANSAC pose) exactly and pulls rotation and translation back from a perturbed start. With
    ``icp_scale=True`` it fits the scale too, and on a query reaching past the map's edge (half of it
    here) it leaves the true scale even when it starts there: the edge's points pull the query inwards
    (docs/memory.md)."""
    from scipy.spatial.transform import Rotation

    from cm3d.memory.verify import icp_validation
    from cm3d.ops import sim3

    _, entry = _entry_of()
    pts, ok = np.asarray(entry.points), np.asarray(entry.point_valid)
    # the map holds half of the cloud; the query is all of it in a frame 2x larger, rotated and shifted
    half = entry.replace(point_valid=jnp.asarray(ok & (pts[:, 0] < np.median(pts[ok, 0]))))
    bank, m = _insert(memory.empty(SEQ_CFG), half)
    vs = float(bank.voxel_size[m])
    R = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    t = np.array([1.0, -2.0, 0.5])
    query = entry.replace(points=jnp.asarray(2.0 * pts @ R.T + t, jnp.float32))
    true = np.eye(4)
    true[:3, :3], true[:3, 3] = R.T / 2.0, -R.T @ t / 2.0  # query -> map
    off = np.eye(4)
    off[:3, :3] = Rotation.from_rotvec([0.0, 0.02, 0.0]).as_matrix()
    off[:3, 3] = [0.3 * vs, -0.3 * vs, 0.0]
    fit = jax.jit(icp_validation, static_argnums=4)
    scale = sim3.scale
    rot = lambda M: np.degrees(Rotation.from_matrix(sim3.rotation(M) @ R).magnitude())  # noqa: E731
    assert not SEQ_CFG.icp_scale
    for init in (true, off @ true):
        T = np.asarray(fit(bank, m, query, jnp.asarray(init, jnp.float32), SEQ_CFG)[0])
        assert abs(scale(T) / scale(init) - 1) < 1e-5
        assert rot(T) < 0.3 and np.linalg.norm(T[:3, 3] - true[:3, 3]) < 0.3 * vs  # from 1.15 degrees, 0.42 voxel
    T_sim = np.asarray(fit(bank, m, query, jnp.asarray(true, jnp.float32), dataclasses.replace(SEQ_CFG, icp_scale=True))[0])
    assert abs(scale(T_sim) / 0.5 - 1) > 0.01  # measured -2.2 %


# ----------------------------------------------------------------------------------------------
# 3D keypoints, Sim(3) RANSAC, grid neighbours, verification on real synthetic visits


def test_lift_keypoints_agrees_with_unprojection_and_round_robin():
    from cm3d.ops import camera, se3

    S, H, W, N = 3, 20, 30, 4
    rng = np.random.default_rng(0)
    depth = rng.uniform(1, 3, (S, H, W)).astype(np.float32)
    depth[1, 5, 7] = 0.0  # no depth: dropped
    K = np.tile(np.array([[20.0, 0, 14.5], [0, 20.0, 9.5], [0, 0, 1]], np.float32), (S, 1, 1))
    c2w = np.asarray(jax.jit(se3.exp)(jnp.asarray(rng.normal(size=(S, 6)) * 0.3, jnp.float32)))
    uv = rng.integers(0, [W, H], (S, N, 2)).astype(np.float32)
    uv[1, 0] = [7, 5]
    desc = rng.normal(size=(S, N, 8)).astype(np.float32)
    valid = np.ones((S, N), bool)
    valid[2, 3] = False
    kp = jax.jit(memory.lift_keypoints, static_argnums=6)(uv, desc, valid, depth, K, c2w, 16)
    full = np.asarray(jax.jit(camera.unproject)(depth, K, c2w))
    ok = valid & (depth[np.arange(S)[:, None], uv[..., 1].astype(int), uv[..., 0].astype(int)] > 0)
    assert int(kp.valid.sum()) == ok.sum() == 10
    # round robin: the first keypoints come one per frame, each frame's strongest first
    np.testing.assert_allclose(np.asarray(kp.desc[:3]), desc[[0, 1, 2], [0, 1, 0]])
    for p, d in zip(np.asarray(kp.points)[np.asarray(kp.valid)], np.asarray(kp.desc)[np.asarray(kp.valid)]):
        s, n = np.argwhere(np.all(desc == d, -1))[0]
        np.testing.assert_allclose(p, full[s, int(uv[s, n, 1]), int(uv[s, n, 0])], atol=1e-4)
    assert not np.any(np.asarray(kp.points)[~np.asarray(kp.valid)])  # padding is zero


def test_lift_keypoints_of_a_larger_detection_starts_with_the_smaller_lift():
    """The round robin makes capacities nested: a lift at capacity ``c`` is the first ``c`` of a lift at
    a larger capacity; and when every frame's ``n`` strongest keypoints have depth, lifting them equals the
    first ``S * n`` of a lift of more per frame (what lets experiments/memory_recall.py cache every lifted
    keypoint once and sweep capacities by a cut)."""
    S, H, W, N = 3, 20, 30, 6
    rng = np.random.default_rng(5)
    depth = rng.uniform(1, 3, (S, H, W)).astype(np.float32)
    K = np.tile(np.array([[20.0, 0, 14.5], [0, 20.0, 9.5], [0, 0, 1]], np.float32), (S, 1, 1))
    c2w = np.tile(np.eye(4, dtype=np.float32), (S, 1, 1))
    uv = rng.integers(0, [W, H], (S, N, 2)).astype(np.float32)
    desc = rng.normal(size=(S, N, 8)).astype(np.float32)
    valid = np.ones((S, N), bool)
    valid[2, 4:] = False  # a frame with fewer keypoints than the larger detection's capacity
    lift = jax.jit(memory.lift_keypoints, static_argnums=6)

    def same(small, big, c):
        np.testing.assert_array_equal(np.asarray(small.valid), np.asarray(big.valid)[:c])
        np.testing.assert_array_equal(np.asarray(small.desc), np.asarray(big.desc)[:c])
        np.testing.assert_allclose(np.asarray(small.points), np.asarray(big.points)[:c], atol=1e-5)  # (ulps)

    big = lift(uv, desc, valid, depth, K, c2w, S * N)
    for n, c in ((2, S * 2), (4, S * 4 - 1)):
        same(lift(uv[:, :n], desc[:, :n], valid[:, :n], depth, K, c2w, c), big, c)
    hole = depth.copy()
    hole[0, int(uv[0, 1, 1]), int(uv[0, 1, 0])] = 0.0  # a keypoint without depth: same detection, any capacity
    big = lift(uv, desc, valid, hole, K, c2w, S * N)
    same(lift(uv, desc, valid, hole, K, c2w, 7), big, 7)
    assert not np.asarray(big.valid)[S * N - 2:].any()  # the hole and the invalid ones: padding at the end


def test_keypoint_clusters_and_distinct_count_match_a_loop():
    rng = np.random.default_rng(3)
    centres = rng.uniform(-5, 5, (12, 3))
    pts = (centres[rng.integers(0, 12, 60)] + rng.normal(scale=0.02, size=(60, 3))).astype(np.float32)
    valid = rng.random(60) < 0.9
    cid = np.asarray(jax.jit(memory.keypoint_clusters)(pts, valid, 0.2))
    for i in range(60):  # reference: the first valid keypoint within the separation (itself at worst)
        close = [j for j in range(60) if valid[j] and np.linalg.norm(pts[i] - pts[j]) < 0.2]
        assert cid[i] == (close[0] if valid[i] else i)
    masks = rng.random((4, 60)) < 0.5
    counts = np.asarray(ransac.distinct_count(jnp.asarray(masks), jnp.asarray(cid)))
    assert list(counts) == [len(set(cid[m])) for m in masks]
    # views of one 3D point are one cluster: 12 centres at most, each valid point in one
    assert len(set(cid[valid])) <= 12


def test_even_subsample_takes_evenly_spaced_valid_points():
    rng = np.random.default_rng(2)
    f = jax.jit(memory.even_subsample, static_argnums=2)
    for size, n, share in [(8192, 64, 0.5), (8192, 256, 0.01), (300, 256, 0.95), (50, 8, 0.0)]:
        pts = rng.random((size, 3)).astype(np.float32)
        valid = rng.random(size) < share
        kept = np.flatnonzero(valid)
        want = kept[(np.arange(n) * len(kept)) // n] if len(kept) > n else kept
        sub, ok, idx = (np.asarray(a) for a in f(pts, valid, n))
        assert ok.sum() == len(want) and np.array_equal(idx[ok], want) and np.array_equal(sub[ok], pts[want])
        if len(kept) < size:  # the padding slots hold invalid points
            assert not np.any(valid[idx[~ok]])


def test_match_keypoints_equals_a_brute_force_loop():
    """Mutual nearest descriptors with the 3D-aware ratio test, against a plain numpy loop: views of one
    3D point (repeated descriptors nearby in 3D) do not fail the ratio test; invalid keypoints never match."""
    from cm3d.memory.matching import nearest_descriptors

    rng = np.random.default_rng(5)
    unit = lambda a: (a / np.linalg.norm(a, axis=-1, keepdims=True)).astype(np.float32)  # noqa: E731
    m_desc = unit(rng.random((80, 16)))
    m_pts = rng.uniform(-2, 2, (80, 3)).astype(np.float32)
    m_desc[40:60] = unit(m_desc[:20] + 0.05 * rng.random((20, 16)))  # a second view of 20 points ...
    m_pts[40:60] = m_pts[:20] + 0.01  # ... at the same place
    m_valid = rng.random(80) < 0.9
    q_desc = unit(m_desc[rng.integers(0, 80, 50)] + 0.2 * rng.random((50, 16)))
    q_valid = rng.random(50) < 0.9
    q = memory.Keypoints(np.zeros((50, 3), np.float32), q_desc, q_valid)
    ratio, sep = 0.85, 0.1
    m = memory.Keypoints(m_pts, m_desc, m_valid)
    j, best, mutual, ratio_ok = jax.jit(nearest_descriptors, static_argnums=2)(q, m, ratio, sep)
    d2 = np.where(q_valid[:, None] & m_valid[None], 2 - 2 * q_desc.astype(np.float64) @ m_desc.T, np.inf)
    ok = 0
    for i in range(50):
        if not q_valid[i]:
            assert best[i] == np.inf and not mutual[i] and not ratio_ok[i]
            continue
        ji = int(np.argmin(d2[i]))
        far = m_valid & (np.linalg.norm(m_pts - m_pts[ji], axis=1) > sep)
        assert j[i] == ji and np.isclose(best[i], d2[i, ji], atol=1e-5)
        assert mutual[i] == (np.argmin(d2[:, ji]) == i)
        assert ratio_ok[i] == (d2[i, ji] <= ratio**2 * np.min(d2[i, far]))
        ok += bool(mutual[i] & ratio_ok[i])
    assert ok >= 10  # the test sees matches that pass, and (the noise) ones that do not
    assert ok < np.sum(q_valid)
    _, best, mutual, ratio_ok = nearest_descriptors(q, memory.Keypoints(m_pts, m_desc, np.zeros(80, bool)), ratio, sep)
    assert np.all(np.isinf(best)) and not np.any(mutual) and not np.any(ratio_ok)  # a map without keypoints


def test_entry_keypoints_are_padded_and_never_nan():
    cfg = memory.MemoryConfig(max_maps=2, max_points=64, max_keyframes=3, max_keypoints=8, keypoint_dim=4)
    e = _entry(0, cfg)
    kp = memory.Keypoints(np.ones((5, 3), np.float32), np.ones((5, 4), np.float32) / 2, np.ones(5, bool))
    bank, m = _insert(memory.empty(cfg), e.replace(keypoints=kp))
    assert bank.kp_points.shape == (2, 8, 3) and int(bank.kp_valid[m].sum()) == 5
    bad = memory.Keypoints(kp.points.copy(), kp.desc, kp.valid)
    bad.points[1, 0] = np.nan
    cloud = memory.SequenceCloud(points=jnp.asarray(np.random.default_rng(0).normal(size=(100, 3)), jnp.float32),
                                 colors=jnp.zeros((100, 3), jnp.uint8), conf=jnp.ones(100), valid=jnp.ones(100, bool))
    entry = jax.jit(memory.build_entry, static_argnums=3)(cloud, e.kf_desc, e.kf_valid, cfg, bad)
    assert list(np.asarray(entry.keypoints.valid)) == [True, False, True, True, True]
    assert np.all(np.isfinite(np.asarray(entry.keypoints.points)))
    with pytest.raises(ValueError, match="dimension"):
        memory.add_map(memory.empty(cfg), e.replace(keypoints=memory.Keypoints(kp.points, np.ones((5, 3)), kp.valid)))


VISIT_CFG = memory.MemoryConfig(max_maps=4, max_points=1024, max_keyframes=8, max_keypoints=256,
                                voxel_resolution=40.0, top_k=2)
VISIT_FRAMES = 16  # every visit (stored or query) has this many frames: one render and one preparation compile


@jax.jit
def _prepare_visit(depth, conf, K, c2w, images, static, frame_ok, uv, kdesc, kvalid):
    cfg = VISIT_CFG
    d = jax.vmap(descriptors.image_descriptor)(images, static)
    idx, ok = memory.select_keyframes(d, frame_ok, 0.1, cfg.max_keyframes)
    cloud = memory.sequence_cloud(depth, conf, K, c2w, images, static, cfg)
    kp = memory.lift_keypoints(uv, kdesc, kvalid, depth, K, c2w, cfg.max_keypoints)
    return memory.build_entry(cloud, d[idx], ok, cfg, kp)


@functools.lru_cache(maxsize=None)
def _visit_sequence(seed, visit):
    """One rendered visit with priors (rendered once per process: the fixture and the floor test share it)."""
    from cm3d.data import synthetic

    world = synthetic.WorldConfig(height=120, width=160, supersample=1, fps=1.0)
    return synthetic.generate(seed, visit, VISIT_FRAMES, "slight", world)


def _visit_entry(seed, visit):
    from cm3d.ops import keypoints

    seq = _visit_sequence(seed, visit)
    static = ~seq.gt.dynamic_mask
    f = keypoints.detect_sequence(seq.images, static, 48, contrast_threshold=0.01)
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    entry = _prepare_visit(f32(seq.depth), f32(seq.depth_conf), f32(seq.intrinsic), f32(seq.cam_to_world),
                           jnp.asarray(seq.images), jnp.asarray(static), jnp.ones(VISIT_FRAMES, bool),
                           f32(f.uv), f32(f.desc), jnp.asarray(f.valid))
    s = seq.meta["prior_scale"]
    prior_from_world = np.diag([s, s, s, 1.0]) @ np.linalg.inv(seq.gt.cam_to_world[0])
    return entry, prior_from_world


@pytest.fixture(scope="module")
def visits():
    """Two stored rooms (look-around visits), a revisit of room 1 and a room never stored, and
    :func:`memory.remember` of the last two, jitted and vmapped as a batch (one compilation shared by
    the tests below)."""
    maps = [_visit_entry(s, 0) for s in (1, 2)]
    revisit = _visit_entry(2, 1)
    unseen = _visit_entry(10_001, 1)
    bank = memory.empty(VISIT_CFG)
    for e, _ in maps:
        bank, _ = _insert(bank, e)
    queries = jax.tree.map(lambda a, b: jnp.stack([a, b]), revisit[0], unseen[0])
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    banks, rep = jax.jit(jax.vmap(lambda e, k: memory.remember(bank, e, VISIT_CFG, k)))(queries, keys)
    return bank, maps, revisit, unseen, banks, rep


def test_revisit_is_recalled_verified_and_relocalised_and_new_room_rejected(visits):
    """remember (recall, verification by the acceptance model, update or insert), jitted and vmapped
    over a batch of two queries: the revisit updates map 1 with a correct Sim(3), the new room becomes
    map 2."""
    bank, maps, (rev, rev_pfw), (new, _), banks, rep = visits
    out = rep.identification
    assert list(np.asarray(out.map_id)) == [1, -1]
    v = jax.tree.map(lambda a: a[0], out.verification)
    assert float(out.acceptance[0]) >= 0 > float(out.acceptance[1])
    assert int(v.keypoint_inliers) >= VISIT_CFG.min_keypoint_inliers and float(v.fitness) >= VISIT_CFG.min_fitness
    gt = maps[1][1] @ np.linalg.inv(rev_pfw)  # query prior frame -> map prior frame
    T = np.asarray(v.transform)
    s, s_gt = np.cbrt(np.linalg.det(T[:3, :3])), np.cbrt(np.linalg.det(gt[:3, :3]))
    np.testing.assert_allclose(s, s_gt, rtol=0.05)
    dR = (T[:3, :3] / s) @ (gt[:3, :3] / s_gt).T
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 3.0
    # the revisit updated map 1 in place (moved by the verified transform) ...
    b0 = jax.tree.map(lambda a: a[0], banks)
    assert list(np.asarray(rep.map_id)) == [1, 2] and list(np.asarray(rep.created)) == [False, True]
    assert int(b0.visits[1]) == 2 and int(b0.num_maps) == 2
    assert np.all(np.isfinite(np.asarray(b0.points))) and np.all(np.isfinite(np.asarray(b0.kp_points)))
    np.testing.assert_allclose(np.asarray(rep.transform[0]), T, atol=1e-6)
    # ... the new room became map 2 with the identity transform, map 1 untouched
    b1 = jax.tree.map(lambda a: a[1], banks)
    assert int(rep.recalled[1]) == -1 and int(b1.num_maps) == 3 and int(b1.visits[1]) == 1
    np.testing.assert_allclose(np.asarray(rep.transform[1]), np.eye(4), atol=0)
    np.testing.assert_array_equal(np.asarray(b1.points[1]), np.asarray(bank.points[1]))
    np.testing.assert_allclose(np.asarray(b1.points[2]), np.asarray(_insert(bank, new)[0].points[2]),
                               atol=1e-6)


def test_acceptance_model_in_identify_equals_sklearn_on_its_features(visits):
    """The score identify computes (jitted, vmapped) is scikit-learn's logistic-regression decision function
    on the same features (a StandardScaler + LogisticRegression holding the config's numbers), shifted by the
    folded-in threshold, and float64 NumPy agrees; the features are the verification's own scores; the
    decision is score >= 0 (and the hard checks), not the thresholds."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.preprocessing import StandardScaler

    bank, maps, _, _, _, rep = visits
    out = rep.identification
    F = np.asarray(out.features, np.float64)
    cfg = VISIT_CFG
    sc = StandardScaler()
    sc.mean_, sc.scale_ = np.asarray(cfg.accept_mean), np.asarray(cfg.accept_scale)
    sc.var_, sc.n_features_in_ = sc.scale_**2, F.shape[1]
    lr = LogisticRegression()
    lr.coef_, lr.intercept_ = np.asarray(cfg.accept_weights)[None], np.array([cfg.accept_bias])
    lr.classes_ = np.array([False, True])
    ref = lr.decision_function(sc.transform(F))
    np.testing.assert_allclose(np.asarray(out.acceptance), ref, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(
        ref, (F - np.asarray(cfg.accept_mean)) / np.asarray(cfg.accept_scale) @ np.asarray(cfg.accept_weights)
        + cfg.accept_bias, atol=1e-9)
    # the features are the verification's scores (the revisit's: the keypoint path accepted it)
    names = memory.ACCEPTANCE_FEATURES
    v = jax.tree.map(lambda a: np.asarray(a)[0], out.verification)
    vs = float(bank.voxel_size[int(out.candidate[0])])
    np.testing.assert_allclose(F[0, names.index("fitness")], v.fitness, rtol=1e-6)
    np.testing.assert_allclose(F[0, names.index("colour_agreement")], v.colour_agreement, rtol=1e-6)
    np.testing.assert_allclose(F[0, names.index("rmse_voxels")], v.inlier_rmse / vs, rtol=1e-5)
    np.testing.assert_allclose(F[0, names.index("log_icp_inliers")], np.log1p(v.inlier_count), rtol=1e-6)
    np.testing.assert_allclose(F[0, names.index("log_pose_inliers")], np.log1p(v.keypoint_inliers), rtol=1e-6)
    share = float(out.recall.votes[0, 1]) / int(np.sum(np.asarray(visits[2][0].kf_valid)))
    np.testing.assert_allclose(F[0, names.index("vote_share")], share, rtol=1e-6)
    assert int(out.candidate[0]) == 1 and list(np.asarray(out.map_id)) == [1, -1]
    assert list(np.asarray(out.map_id) >= 0) == list(np.asarray(out.acceptance) >= 0)
    with pytest.raises(ValueError, match="accept_weights"):
        memory.MemoryConfig(accept_weights=(1.0, 2.0))
    with pytest.raises(ValueError, match="min_overlap"):
        memory.MemoryConfig(min_overlap=1.5)
    with pytest.raises(ValueError, match="accept_log_nfa"):
        memory.MemoryConfig(accept_log_nfa=0.5)


def _floor_keypoints(rng, n, dim=128):
    d = np.abs(rng.normal(size=(n, dim))).astype(np.float32)
    return memory.Keypoints(rng.normal(size=(n, 3)).astype(np.float32), d / np.linalg.norm(d, axis=1, keepdims=True),
                            np.arange(n) < n - 2)


def test_floor_keypoints_round_trip_and_version_2_files_with_legacy_options_load(tmp_path):
    cfg = dataclasses.replace(CFG, max_floor_keypoints=6)
    rng = np.random.default_rng(0)
    bank, m = _insert(memory.empty(cfg), _entry(0).replace(floor_keypoints=_floor_keypoints(rng, 9)))
    assert bank.floor_kp_points.shape == (4, 6, 3) and int(bank.floor_kp_valid[m].sum()) == 6  # cut to capacity
    memory.save(bank, tmp_path / "bank.cm3d", cfg)
    back, cfg2 = memory.load(tmp_path / "bank.cm3d")
    assert cfg2 == cfg
    jax.tree.map(np.testing.assert_array_equal, back, bank)
    # a version-2 file (before floor keypoints): loads with none
    old = memory.empty(CFG)
    arrays = {k: v for k, v in memory.io._fields(old).items() if not k.startswith("floor_kp_")}
    payload = b"".join(np.ascontiguousarray(a).tobytes() for a in arrays.values())
    conf = {k: v for k, v in dataclasses.asdict(CFG).items() if k != "max_floor_keypoints"}
    conf.update(fallback_yaws=0, fallback_grid=64, pose_candidates=1)  # options since removed: ignored on load
    header = json.dumps({"version": 2, "config": conf, "arrays": [[k, list(a.shape), a.dtype.str] for k, a in arrays.items()],
                         "sha256": hashlib.sha256(payload).hexdigest()}).encode()
    (tmp_path / "v2.cm3d").write_bytes(memory.MAGIC + struct.pack("<Q", len(header)) + header + payload)
    b2, c2 = memory.load(tmp_path / "v2.cm3d")
    assert c2 == CFG and b2.floor_kp_points.shape == (4, 0, 3)
    jax.tree.map(np.testing.assert_array_equal, b2, old)


def test_floor_keypoints_match_only_floor_keypoints():
    """The same descriptors at the same points are matched as floor keypoints, never across kinds."""
    cfg = dataclasses.replace(CFG, max_keypoints=8, max_floor_keypoints=8, min_keypoint_inliers=1)
    rng = np.random.default_rng(1)
    floor = _floor_keypoints(rng, 8)
    query = _entry(0).replace(keypoints=None, floor_keypoints=floor)
    as_floor = _insert(memory.empty(cfg), _entry(0).replace(floor_keypoints=floor))[0]
    as_image = _insert(memory.empty(cfg), _entry(0).replace(keypoints=floor))[0]
    key = jax.random.PRNGKey(0)
    kcfg = dataclasses.replace(cfg, verification="keypoints")
    verify = jax.jit(lambda b: memory.verify(b, 0, query, kcfg, key))  # one compilation for both banks
    assert int(verify(as_floor).matches) == 6
    assert int(verify(as_image).matches) == 0
    # update_map moves the query's floor keypoints into the map and merges them
    T = np.diag([2.0, 2.0, 2.0, 1.0])
    up = jax.jit(lambda b, t: memory.update_map(b, 0, query, t, cfg))(as_image, jnp.asarray(T, jnp.float32))
    np.testing.assert_allclose(np.asarray(up.floor_kp_points[0][:6]), 2 * floor.points[:6], atol=1e-6)


def test_floor_keypoints_alone_recall_a_revisit_with_the_right_pose():
    """A revisit's floor orthophoto keypoints (no image keypoints) against the stored room's: the RANSAC
    pose is the ground-truth similarity between the two visits' prior frames."""
    from cm3d.ops import keypoints

    cfg = dataclasses.replace(VISIT_CFG, max_floor_keypoints=256, verification="keypoints")
    entries, pfws = [], []
    for visit in (0, 1):
        entry, pfw = _visit_entry(2, visit)
        seq = _visit_sequence(2, visit)
        f = keypoints.floor_features(seq.images, seq.depth, seq.intrinsic, seq.cam_to_world, ~seq.gt.dynamic_mask, 256)
        entries.append(entry.replace(keypoints=None, floor_keypoints=memory.Keypoints(f.points, f.desc, f.valid)))
        pfws.append(pfw)
    bank, m = _insert(memory.empty(cfg), entries[0])
    v = jax.jit(lambda b, e, k: memory.verify(b, 0, e, cfg, k))(bank, entries[1], jax.random.PRNGKey(0))
    assert bool(v.accepted) and int(v.keypoint_inliers) >= 10
    gt = pfws[0] @ np.linalg.inv(pfws[1])
    T = np.asarray(v.transform)
    s, s_gt = np.cbrt(np.linalg.det(T[:3, :3])), np.cbrt(np.linalg.det(gt[:3, :3]))
    np.testing.assert_allclose(s, s_gt, rtol=0.05)
    dR = (T[:3, :3] / s) @ (gt[:3, :3] / s_gt).T
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 3.0
