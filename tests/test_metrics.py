import copy
import logging

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from cm3d.data.tum import read_tum
from cm3d.eval.metrics import (
    align_depth_scale_shift,
    align_trajectory,
    associate,
    ate,
    depth_metrics,
    evaluate_trajectories,
    evaluate_trajectory_files,
    mask_metrics,
    pose_metrics,
    reconstruction_metrics,
    rpe,
    umeyama,
)

# (gt, est, poses, ATE Sim3, ATE SE3, RPE trans, RPE rot deg) from /work/shared/data/README.md.
PAIRS = [
    ("fr2_desk_groundtruth.txt", "fr2_desk_ORB.txt", 2174, 0.006123, 0.008119, 0.003485, 0.280519),
    (
        "freiburg1_xyz-groundtruth.txt",
        "freiburg1_xyz-rgbdslam.txt",
        785,
        0.013389,
        0.013470,
        0.005806,
        0.353613,
    ),
]


def _random_poses(n, seed, scale=1.0):
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    T[:, :3, 3] = scale * np.cumsum(rng.normal(size=(n, 3)), axis=0)
    return T


def _perturb(T, seed, rot_deg=2.0, trans=0.05):
    rng = np.random.default_rng(seed)
    n = len(T)
    dR = Rotation.from_rotvec(np.deg2rad(rot_deg) * rng.normal(size=(n, 3))).as_matrix()
    out = T.copy()
    out[:, :3, :3] = T[:, :3, :3] @ dR
    out[:, :3, 3] += trans * rng.normal(size=(n, 3))
    return out


def _sim3_apply(T, s, R, t):
    out = T.copy()
    out[..., :3, :3] = R @ T[..., :3, :3]
    out[..., :3, 3] = s * T[..., :3, 3] @ R.T + t
    return out


# ----------------------------------------------------------------------------------------------
# Real trajectories against evo
# ----------------------------------------------------------------------------------------------


def _evo_metrics(gt_path, est_path):
    from evo.core import metrics as em
    from evo.core import sync
    from evo.tools import file_interface

    ref = file_interface.read_tum_trajectory_file(str(gt_path))
    est = file_interface.read_tum_trajectory_file(str(est_path))
    ref, est = sync.associate_trajectories(ref, est, max_diff=0.01)
    out = {"pairs": ref.num_poses, "ref_ts": ref.timestamps, "est_ts": est.timestamps}
    for key, scale in (("ate", True), ("ate_se3", False)):
        e = copy.deepcopy(est)
        e.align(ref, correct_scale=scale)
        m = em.APE(em.PoseRelation.translation_part)
        m.process_data((ref, e))
        out[key] = m.get_statistic(em.StatisticsType.rmse)
    e = copy.deepcopy(est)
    e.align(ref, correct_scale=True)
    for key, rel in (
        ("rpe_trans", em.PoseRelation.translation_part),
        ("rpe_rot", em.PoseRelation.rotation_angle_deg),
    ):
        m = em.RPE(rel, delta=1, delta_unit=em.Unit.frames, all_pairs=True)
        m.process_data((ref, e))
        out[key] = m.get_statistic(em.StatisticsType.rmse)
    return out


@pytest.fixture(scope="module", params=PAIRS, ids=lambda p: p[1])
def pair(request, shared_data):
    gt_name, est_name, *ref = request.param
    d = shared_data / "evo_tum_traj"
    return d / gt_name, d / est_name, ref, _evo_metrics(d / gt_name, d / est_name)


def test_real_pairs_match_evo_and_readme(pair):
    gt_path, est_path, (n, ate_ref, ate_se3_ref, rpe_t_ref, rpe_r_ref), evo_out = pair
    ours = evaluate_trajectory_files(gt_path, est_path)
    assert list(ours) == ["ate", "ate_se3", "rpe_trans", "rpe_rot", "rot_rmse", "pairs", "extent", "ate_defined"]
    assert ours["pairs"] == evo_out["pairs"] == n
    for k in ("ate", "ate_se3", "rpe_trans", "rpe_rot"):
        assert isinstance(ours[k], float)
        assert abs(ours[k] - evo_out[k]) < 1e-6, (k, ours[k], evo_out[k])
    readme = dict(ate=ate_ref, ate_se3=ate_se3_ref, rpe_trans=rpe_t_ref, rpe_rot=rpe_r_ref)
    for k, v in readme.items():
        assert round(ours[k], 6) == pytest.approx(v, abs=1e-12), (k, ours[k], v)


def test_real_pairs_association_matches_evo(pair):
    gt_path, est_path, _, evo_out = pair
    gt_ts, _ = read_tum(gt_path)
    est_ts, _ = read_tum(est_path)
    i_gt, i_est = associate(gt_ts, est_ts)
    np.testing.assert_array_equal(gt_ts[i_gt], evo_out["ref_ts"])
    np.testing.assert_array_equal(est_ts[i_est], evo_out["est_ts"])

    from evo.core.sync import matching_time_indices

    # Here the estimate is the shorter trajectory: evo searches each est stamp in the gt stamps.
    m_est, m_gt = matching_time_indices(est_ts, gt_ts, 0.01)
    np.testing.assert_array_equal(i_est, m_est)
    np.testing.assert_array_equal(i_gt, m_gt)


def _evo_associate_indices(ts_ref, ts_est, max_diff):
    """Indices evo's associate_trajectories keeps, recovered from positions that encode the index."""
    from evo.core import sync
    from evo.core.trajectory import PoseTrajectory3D

    def traj(ts):
        xyz = np.zeros((len(ts), 3))
        xyz[:, 0] = np.arange(len(ts))
        q = np.tile([1.0, 0, 0, 0], (len(ts), 1))
        return PoseTrajectory3D(xyz, q, np.array(ts, dtype=np.float64))

    try:
        a, b = sync.associate_trajectories(traj(ts_ref), traj(ts_est), max_diff=max_diff)
    except sync.SyncException:
        return np.zeros(0, int), np.zeros(0, int)
    return a.positions_xyz[:, 0].astype(int), b.positions_xyz[:, 0].astype(int)


_stamps = st.lists(st.integers(0, 12).map(lambda k: 0.005 * k), min_size=1, max_size=12)


@settings(max_examples=150, deadline=None)
@given(ref=_stamps, est=_stamps, sort_ref=st.booleans(), sort_est=st.booleans())
def test_associate_matches_evo_edge_cases(ref, est, sort_ref, sort_est):
    # Grid stamps give exact ties, duplicates, out-of-range stamps and unsorted inputs.
    ref = sorted(ref) if sort_ref else ref
    est = sorted(est) if sort_est else est
    logging.getLogger("evo").setLevel(logging.ERROR)
    exp_ref, exp_est = _evo_associate_indices(ref, est, 0.01)
    got_ref, got_est = associate(np.array(ref), np.array(est), 0.01)
    np.testing.assert_array_equal(got_ref, exp_ref)
    np.testing.assert_array_equal(got_est, exp_est)


def test_evaluate_by_index_when_timestamps_unrelated():
    gt = _random_poses(40, 0)
    est = _sim3_apply(_perturb(gt, 1, 0.5, 0.01), 0.5, Rotation.random(random_state=2).as_matrix(), np.ones(3))
    gt_ts = 1e9 + 0.03 * np.arange(40)
    est_ts = np.arange(40, dtype=np.float64)  # frame indices, as MonST3R writes them
    by_index = evaluate_trajectories(gt_ts, gt, est_ts, est)
    by_time = evaluate_trajectories(gt_ts, gt, gt_ts.copy(), est)
    assert by_index["pairs"] == by_time["pairs"] == 40
    for k in ("ate", "ate_se3", "rpe_trans", "rpe_rot"):
        assert by_index[k] == pytest.approx(by_time[k], rel=1e-12)
    with pytest.raises(ValueError, match="associated"):
        evaluate_trajectories(gt_ts, gt, est_ts[:30], est[:30])


# ----------------------------------------------------------------------------------------------
# Umeyama and pose metrics on synthetic data
# ----------------------------------------------------------------------------------------------


def test_umeyama_recovers_sim3_and_matches_evo():
    from evo.core.geometry import umeyama_alignment

    rng = np.random.default_rng(0)
    B, N = 6, 25
    src = rng.normal(size=(B, N, 3))
    R = Rotation.random(B, random_state=1).as_matrix()
    s = rng.uniform(0.2, 5.0, B)
    t = rng.normal(size=(B, 3))
    dst = s[:, None, None] * np.einsum("bij,bnj->bni", R, src) + t[:, None]
    with jax.enable_x64(True):
        f = jax.jit(jax.vmap(lambda a, b: umeyama(a, b, with_scale=True)))
        s_, R_, t_ = f(jnp.asarray(src), jnp.asarray(dst))
        np.testing.assert_allclose(s_, s, rtol=1e-10)
        np.testing.assert_allclose(R_, R, atol=1e-10)
        np.testing.assert_allclose(t_, t, atol=1e-10)
        # Noisy, masked and reflected data against evo on the kept points.
        noisy = dst[0] + 0.3 * rng.normal(size=(N, 3))
        noisy[:, 2] *= -1.0  # a mirrored target: the best proper rotation needs the sign fix
        mask = rng.random(N) > 0.3
        src_bad = src[0].copy()
        for ws in (True, False):
            r_e, t_e, c_e = umeyama_alignment(src[0][mask].T, noisy[mask].T, ws)
            c, r, tt = umeyama(jnp.asarray(src_bad), jnp.asarray(noisy), jnp.asarray(mask), ws)
            assert np.linalg.det(np.asarray(r)) == pytest.approx(1.0)
            np.testing.assert_allclose(r, r_e, atol=1e-10)
            np.testing.assert_allclose(tt, t_e, atol=1e-10)
            assert float(c) == pytest.approx(c_e, rel=1e-10)
    # NumPy inputs (host code) take the NumPy path: NumPy float64 out, no JAX, the same fit as evo's
    for ws in (True, False):
        r_e, t_e, c_e = umeyama_alignment(src[0][mask].T, noisy[mask].T, ws)
        c, r, tt = umeyama(src_bad, noisy, mask, ws)
        assert all(isinstance(v, np.ndarray) and v.dtype == np.float64 for v in (c, r, tt))
        np.testing.assert_allclose(r, r_e, atol=1e-10)
        np.testing.assert_allclose(tt, t_e, atol=1e-10)
        assert float(c) == pytest.approx(c_e, rel=1e-10)
    c, r, tt = umeyama(src[1].astype(np.float32), dst[1].astype(np.float32))  # float32 stays float32
    assert r.dtype == np.float32 and float(c) == pytest.approx(s[1], rel=1e-4)


def _evo_synthetic(gt, est):
    """evo's ATE Sim3/SE3 and Sim3 RPE on already associated synthetic poses (stamps = index)."""
    from evo.core import metrics as em
    from evo.core.trajectory import PoseTrajectory3D

    ts = np.arange(len(gt), dtype=np.float64)
    ref = PoseTrajectory3D(poses_se3=list(gt), timestamps=ts)
    out = {}
    for key, scale in (("ate", True), ("ate_se3", False)):
        e = PoseTrajectory3D(poses_se3=list(est), timestamps=ts)
        e.align(ref, correct_scale=scale)
        m = em.APE(em.PoseRelation.translation_part)
        m.process_data((ref, e))
        out[key] = m.get_statistic(em.StatisticsType.rmse)
        if scale:
            for k2, rel in (
                ("rpe_trans", em.PoseRelation.translation_part),
                ("rpe_rot", em.PoseRelation.rotation_angle_deg),
            ):
                m = em.RPE(rel, delta=1, delta_unit=em.Unit.frames, all_pairs=True)
                m.process_data((ref, e))
                out[k2] = m.get_statistic(em.StatisticsType.rmse)
    return out


def test_pose_metrics_synthetic_match_evo_and_masks():
    gt = _random_poses(30, 5)
    est = _sim3_apply(_perturb(gt, 6), 2.5, Rotation.random(random_state=7).as_matrix(), np.array([1.0, -2, 3]))
    ref = _evo_synthetic(gt, est)
    valid = np.ones(30, bool)
    valid[[0, 7, 8, 20]] = False
    ref_masked = _evo_synthetic(gt[valid], est[valid])
    est_bad = est.copy()
    est_bad[~valid] = np.nan  # invalid frames may hold garbage
    with jax.enable_x64(True):
        m = jax.jit(pose_metrics)(jnp.asarray(est), jnp.asarray(gt))
        for k, v in ref.items():
            assert float(m[k]) == pytest.approx(v, abs=1e-9), k
        assert float(ate(est, gt, "sim3")) == pytest.approx(ref["ate"], abs=1e-9)
        assert float(ate(est, gt, "se3")) == pytest.approx(ref["ate_se3"], abs=1e-9)
        # Masking: ATE equals evo on the kept frames; RPE keeps only pairs with both ends valid.
        mm = pose_metrics(jnp.asarray(est_bad), jnp.asarray(gt), valid=jnp.asarray(valid))
        assert all(np.isfinite(float(v)) for v in mm.values())
        assert float(mm["ate"]) == pytest.approx(ref_masked["ate"], abs=1e-9)
        assert float(mm["ate_se3"]) == pytest.approx(ref_masked["ate_se3"], abs=1e-9)
        aligned = align_trajectory(jnp.asarray(est), jnp.asarray(gt), "sim3", jnp.asarray(valid))
        pair_ok = valid[:-1] & valid[1:]
        rel = lambda T: np.linalg.inv(T[:-1]) @ T[1:]  # noqa: E731
        E = np.linalg.inv(rel(gt)) @ rel(np.asarray(aligned))
        t_ref = np.sqrt(np.mean(np.sum(E[pair_ok, :3, 3] ** 2, -1)))
        r_ref = np.sqrt(np.mean(Rotation.from_matrix(E[pair_ok, :3, :3]).magnitude() ** 2)) * 180 / np.pi
        assert float(mm["rpe_trans"]) == pytest.approx(t_ref, abs=1e-9)
        assert float(mm["rpe_rot"]) == pytest.approx(r_ref, abs=1e-9)
        # delta > 1 and no alignment, against the same formula.
        rt, rr = rpe(jnp.asarray(est), jnp.asarray(gt), align="none", delta=3)
        rel3 = lambda T: np.linalg.inv(T[:-3]) @ T[3:]  # noqa: E731
        E3 = np.linalg.inv(rel3(gt)) @ rel3(est)
        assert float(rt) == pytest.approx(np.sqrt(np.mean(np.sum(E3[:, :3, 3] ** 2, -1))), abs=1e-9)
        r3 = np.sqrt(np.mean(Rotation.from_matrix(E3[:, :3, :3]).magnitude() ** 2)) * 180 / np.pi
        assert float(rr) == pytest.approx(r3, abs=1e-9)
        assert np.isnan(float(ate(est, gt, valid=np.zeros(30, bool))))
    with pytest.raises(ValueError):
        align_trajectory(est, gt, mode="sim2")


def test_jit_vmap_invariance_float32():
    B, N = 3, 20
    gts = np.stack([_random_poses(N, 10 + b) for b in range(B)])
    ests = np.stack([_perturb(g, 20 + b) for b, g in enumerate(gts)])
    gts32, ests32 = jnp.asarray(gts, jnp.float32), jnp.asarray(ests, jnp.float32)
    single = jax.jit(pose_metrics)
    loop = [single(ests32[b], gts32[b]) for b in range(B)]
    vm = jax.jit(jax.vmap(pose_metrics))(ests32, gts32)
    for k in loop[0]:
        assert vm[k].dtype == jnp.float32
        np.testing.assert_allclose(vm[k], [float(x[k]) for x in loop], rtol=2e-4, atol=1e-6)
    # Eager (op by op) against jit, for ate and rpe with delta 2.
    a_eager = ate(ests32[0], gts32[0], "se3")
    a_jit = jax.jit(lambda e, g: ate(e, g, "se3"))(ests32[0], gts32[0])
    np.testing.assert_allclose(a_jit, a_eager, rtol=2e-4)
    r_jit = jax.jit(lambda e, g: rpe(e, g, "sim3", 2))(ests32[0], gts32[0])
    r_eager = rpe(ests32[0], gts32[0], "sim3", 2)
    np.testing.assert_allclose(r_jit, r_eager, rtol=2e-4)


def test_gradients_finite_and_correct():
    from jax.test_util import check_grads

    gt = _random_poses(10, 30)
    est = _sim3_apply(_perturb(gt, 31, 1.0, 0.05), 1.7, Rotation.random(random_state=32).as_matrix(), np.ones(3))
    valid = np.ones(10, bool)
    valid[4] = False
    with jax.enable_x64(True):
        e, g = jnp.asarray(est), jnp.asarray(gt)
        for mode in ("sim3", "se3"):
            f = jax.jit(lambda x, mode=mode: ate(x, g, mode, valid=valid))
            check_grads(f, (e,), order=1, modes=["rev"], eps=1e-6)
        # Finite even at zero error (est == gt), through every metric.
        total = jax.jit(jax.grad(lambda x: sum(jax.tree_util.tree_leaves(pose_metrics(x, g, valid)))))
        for x in (e, g):
            assert np.all(np.isfinite(np.asarray(total(x))))
        gr = jax.jit(jax.grad(lambda x: rpe(x, g)[1]))(e)
        assert np.all(np.isfinite(np.asarray(gr))) and np.any(np.asarray(gr) != 0)


# ----------------------------------------------------------------------------------------------
# Depth, masks, reconstruction
# ----------------------------------------------------------------------------------------------


def _depth_reference(pred, gt, valid):
    m = valid & (gt > 0)
    A = np.stack([pred[m], np.ones(m.sum())], axis=1)
    (s, b), *_ = np.linalg.lstsq(A, gt[m], rcond=None)
    a, g = s * pred[m] + b, gt[m]
    abs_rel = np.mean(np.abs(a - g) / g)
    with np.errstate(divide="ignore", invalid="ignore"):
        d1 = np.mean((a > 0) & (np.maximum(a / g, g / a) < 1.25))
    return s, b, abs_rel, d1


def test_depth_metrics_against_numpy():
    rng = np.random.default_rng(0)
    S, H, W = 2, 8, 10
    gt = rng.uniform(0.5, 5.0, (S, H, W))
    gt[0, 0, :3] = 0.0  # missing depth
    pred = (gt - 0.3) / 2.0 + 0.2 * rng.normal(size=gt.shape)
    pred[1, 2, :4] = -3.0  # aligned depth becomes negative there: delta1 failures
    valid = rng.random(gt.shape) > 0.2
    s, b, abs_rel, d1 = _depth_reference(pred, gt, valid)
    with jax.enable_x64(True):
        s_, b_ = jax.jit(align_depth_scale_shift)(pred, gt, valid)
        assert float(s_) == pytest.approx(s, rel=1e-10) and float(b_) == pytest.approx(b, rel=1e-10)
        m = jax.jit(depth_metrics)(pred, gt, valid)
        assert float(m["abs_rel"]) == pytest.approx(abs_rel, rel=1e-10)
        assert float(m["delta1"]) == pytest.approx(d1, rel=1e-12)
        assert 0.0 < float(m["delta1"]) < 1.0
        # Without alignment; all-invalid gives NaN.
        m0 = depth_metrics(gt * 1.1, gt, valid, align=False)
        assert float(m0["abs_rel"]) == pytest.approx(0.1, rel=1e-9)
        assert float(m0["delta1"]) == 1.0
        assert np.isnan(float(depth_metrics(pred, gt, np.zeros_like(valid))["abs_rel"]))
    m32 = depth_metrics(jnp.asarray(pred, jnp.float32), jnp.asarray(gt, jnp.float32), valid)
    assert m32["abs_rel"].dtype == jnp.float32
    assert float(m32["abs_rel"]) == pytest.approx(abs_rel, rel=1e-4)


def test_mask_metrics_against_sklearn():
    from sklearn.metrics import jaccard_score, precision_score, recall_score

    rng = np.random.default_rng(1)
    f = jax.jit(mask_metrics)
    cases = []
    for _ in range(4):
        cases.append((rng.random((3, 6, 7)) > 0.6, rng.random((3, 6, 7)) > 0.5, rng.random((3, 6, 7)) > 0.3))
    z = np.zeros((3, 6, 7), bool)
    cases += [(z, z, None), (z, ~z, None), (~z, z, None), (cases[0][0], z, None)]
    for pred, gt, valid in cases:
        keep = np.ones_like(pred) if valid is None else valid
        p, g = pred[keep], gt[keep]
        exp = dict(
            iou=jaccard_score(g, p, zero_division=1.0),
            precision=precision_score(g, p, zero_division=1.0),
            recall=recall_score(g, p, zero_division=1.0),
        )
        got = f(pred, gt, valid) if valid is not None else f(pred, gt)
        for k, v in exp.items():
            assert float(got[k]) == pytest.approx(v, abs=1e-6), k
    # Soft predictions are thresholded at 0.5.
    probs = np.where(cases[0][0], 0.9, 0.1).astype(np.float32)
    got = mask_metrics(probs, cases[0][1])
    ref = mask_metrics(cases[0][0], cases[0][1])
    assert all(float(got[k]) == float(ref[k]) for k in ref)


def test_reconstruction_metrics_against_brute_force():
    rng = np.random.default_rng(2)
    pred = rng.normal(size=(60, 3))
    gt = rng.normal(size=(45, 3))
    pn, gn = rng.normal(size=(60, 3)), rng.normal(size=(45, 3))
    D = np.linalg.norm(pred[:, None] - gt[None], axis=-1)
    acc_i, comp_i = D.argmin(1), D.argmin(0)
    acc, comp = D.min(1), D.min(0)
    unit = lambda v: v / np.linalg.norm(v, axis=-1, keepdims=True)  # noqa: E731
    nc = 0.5 * (
        np.mean(np.abs(np.sum(unit(pn) * unit(gn)[acc_i], -1)))
        + np.mean(np.abs(np.sum(unit(gn) * unit(pn)[comp_i], -1)))
    )
    out = reconstruction_metrics(pred, gt, pn, gn)
    assert out["accuracy"] == pytest.approx(acc.mean(), rel=1e-12)
    assert out["accuracy_median"] == pytest.approx(np.median(acc), rel=1e-12)
    assert out["completion"] == pytest.approx(comp.mean(), rel=1e-12)
    assert out["completion_median"] == pytest.approx(np.median(comp), rel=1e-12)
    assert out["normal_consistency"] == pytest.approx(nc, rel=1e-12)
    assert "normal_consistency" not in reconstruction_metrics(pred, gt)
    same = reconstruction_metrics(gt, gt, gn, gn)
    assert same["accuracy"] == 0.0 and same["normal_consistency"] == pytest.approx(1.0)


def test_import_does_not_load_heavy_modules():
    import subprocess
    import sys

    code = (
        "import sys, cm3d, cm3d.eval, cm3d.data.tum; "
        "bad = [m for m in ('scipy', 'open3d', 'cv2', 'matplotlib', 'sklearn') if m in sys.modules]; "
        "assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_depth_metrics_median_against_numpy():
    from cm3d.eval.metrics import depth_metrics_median

    rng = np.random.default_rng(5)
    gt = rng.uniform(0.5, 5.0, (3, 8, 9))
    gt[0, 0, :4] = 0.0  # no ground truth there
    pred = 0.37 * gt * np.exp(rng.normal(0, 0.15, gt.shape))
    pred[1, 2, 3] = -1.0  # a non-positive prediction does not count
    valid = rng.random(gt.shape) > 0.2
    m = valid & (gt > 0) & (pred > 0)
    s = np.median(gt[m]) / np.median(pred[m])
    a, g = s * pred[m], gt[m]
    got = jax.jit(depth_metrics_median)(pred, gt, valid)
    assert float(got["scale"]) == pytest.approx(s, rel=1e-6)
    assert float(got["abs_rel"]) == pytest.approx(np.mean(np.abs(a - g) / g), rel=1e-5)
    assert float(got["delta1"]) == pytest.approx(np.mean(np.maximum(a / g, g / a) < 1.25), abs=1e-6)
    exact = depth_metrics_median(3.0 * gt, gt)  # a pure scale is removed exactly
    assert float(exact["abs_rel"]) == pytest.approx(0.0, abs=1e-6) and float(exact["delta1"]) == 1.0


def test_estimate_normals_match_open3d():
    import open3d as o3d

    from cm3d.eval.metrics import estimate_normals

    rng = np.random.default_rng(6)
    # a curved, noisy surface patch: normals vary from point to point
    xy = rng.uniform(-1, 1, (600, 2))
    pts = np.c_[xy, 0.3 * np.sin(2 * xy[:, 0]) + 0.2 * xy[:, 1] ** 2 + rng.normal(0, 0.003, 600)]
    got = estimate_normals(pts, k=16)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(16))
    ref = np.asarray(pc.normals)
    cos = np.abs(np.sum(got * ref, -1))
    assert np.allclose(np.linalg.norm(got, axis=-1), 1.0)
    assert np.median(cos) > 0.9999 and np.mean(cos > 0.999) > 0.98
