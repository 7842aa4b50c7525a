"""Evaluation metrics: trajectories (ATE/RPE as evo 1.38.1 computes them), depth, dynamic masks, reconstruction.

Pose, depth and mask metrics are jittable ``jax.numpy`` with fixed shapes (invalid frames/pixels are
masked); their dtype follows the inputs. ``associate``, ``evaluate_trajectories`` and
``reconstruction_metrics`` run on the host. Poses cam_to_world 4x4; metres and degrees.
Alignment is Umeyama on the positions (est -> gt); ATE is the RMSE of the aligned positions; RPE
uses all pairs ``(i, i + delta)`` with ``E = (G_i^-1 G_j)^-1 (P_i^-1 P_j)`` on the aligned estimate
(``evo_ape tum -a|-as``, ``evo_rpe -r trans_part|angle_deg -d 1 -u f -as --all_pairs``).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from cm3d.ops.robust import masked_median
from cm3d.ops.se3 import inverse
from cm3d.solvers.align import umeyama  # noqa: F401  (one implementation, re-exported)

_ALIGN_MODES = ("sim3", "se3", "none")


# Pose metrics (jnp)


def _safe_norm(x: jnp.ndarray, axis: int = -1) -> jnp.ndarray:
    """Euclidean norm with a finite (zero) gradient at the origin."""
    sq = jnp.sum(x * x, axis=axis)
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def _rotation_angle(R: jnp.ndarray) -> jnp.ndarray:
    """Rotation angle in radians of (..., 3, 3), atan2 form, finite gradient at the identity."""
    tr = jnp.trace(R, axis1=-2, axis2=-1)
    skew = jnp.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1
    )
    return jnp.arctan2(0.5 * _safe_norm(skew), 0.5 * (tr - 1.0))


def _weights(n: int, valid, dtype) -> jnp.ndarray:
    if valid is None:
        return jnp.ones((n,), dtype)
    return jnp.asarray(valid).astype(dtype)


def _sanitize(T: jnp.ndarray, w: jnp.ndarray) -> jnp.ndarray:
    """Replace the poses of zero-weight frames by the identity (keeps NaNs out of values and grads)."""
    eye = jnp.eye(4, dtype=T.dtype)
    return jnp.where((w > 0)[:, None, None], T, eye)


def _weighted_rmse(sq_err: jnp.ndarray, w: jnp.ndarray) -> jnp.ndarray:
    """sqrt(sum w e^2 / sum w); NaN when the total weight is 0."""
    tot = jnp.sum(w)
    ok = tot > 0
    mse = jnp.sum(w * sq_err) / jnp.where(ok, tot, 1.0)
    safe = mse > 0
    rmse = jnp.where(safe, jnp.sqrt(jnp.where(safe, mse, 1.0)), 0.0)
    return jnp.where(ok, rmse, jnp.nan)


def align_trajectory(est_c2w, gt_c2w, mode: str = "sim3", valid=None):
    """Align the estimate (N, 4, 4) to gt (N, 4, 4) by Umeyama on positions -> aligned estimate (N, 4, 4).

    mode: "sim3", "se3" or "none"; the result is rigid poses ``[R R_i, s R t_i + t]`` as evo's
    ``align``. valid: optional (N,) mask of the frames that enter the fit (all are transformed).
    """
    if mode not in _ALIGN_MODES:
        raise ValueError(f"align mode must be one of {_ALIGN_MODES}, got {mode!r}")
    est = jnp.asarray(est_c2w)
    if mode == "none":
        return est
    gt = jnp.asarray(gt_c2w, dtype=est.dtype)
    w = _weights(est.shape[0], valid, est.dtype)
    est_s, gt_s = _sanitize(est, w), _sanitize(gt, w)
    s, R, t = umeyama(est_s[:, :3, 3], gt_s[:, :3, 3], w, with_scale=(mode == "sim3"))
    Rn = jnp.einsum("ij,njk->nik", R, est[:, :3, :3])
    tn = s * jnp.einsum("ij,nj->ni", R, est[:, :3, 3]) + t
    top = jnp.concatenate([Rn, tn[:, :, None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0], est.dtype), (est.shape[0], 1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


def _ate_aligned(aligned, gt, w):
    d = aligned[:, :3, 3] - gt[:, :3, 3]
    return _weighted_rmse(jnp.sum(d * d, axis=-1), w)


def _rpe_aligned(aligned, gt, w, delta: int):
    n = aligned.shape[0]
    if not 1 <= delta < n:
        raise ValueError(f"rpe needs 1 <= delta < N, got delta={delta}, N={n}")
    P, G = _sanitize(aligned, w), _sanitize(gt, w)
    wp = w[:-delta] * w[delta:]
    rel_p = inverse(P[:-delta]) @ P[delta:]
    rel_g = inverse(G[:-delta]) @ G[delta:]
    E = inverse(rel_g) @ rel_p
    trans_sq = jnp.sum(E[:, :3, 3] ** 2, axis=-1)
    rot_deg = _rotation_angle(E[:, :3, :3]) * (180.0 / math.pi)
    return _weighted_rmse(trans_sq, wp), _weighted_rmse(rot_deg**2, wp)


def ate(est, gt, align: str = "sim3", valid=None):
    """Absolute trajectory error: RMSE (m) of translation differences after alignment (NaN if none valid).
    est, gt: cam_to_world (N, 4, 4), associated frame by frame; valid: optional (N,) mask."""
    est = jnp.asarray(est)
    gt = jnp.asarray(gt, dtype=est.dtype)
    w = _weights(est.shape[0], valid, est.dtype)
    aligned = align_trajectory(est, gt, align, w)
    return _ate_aligned(_sanitize(aligned, w), _sanitize(gt, w), w)


def rpe(est, gt, align: str = "sim3", delta: int = 1, valid=None):
    """Relative pose error over pairs (i, i + delta) -> (trans RMSE in metres, rot RMSE in degrees).

    est, gt: cam_to_world (N, 4, 4); ``E = (G_i^-1 G_j)^-1 (P_i^-1 P_j)`` on the aligned estimate.
    delta: static int frame step; valid: optional (N,) mask, a pair counts when both ends are valid.
    """
    est = jnp.asarray(est)
    gt = jnp.asarray(gt, dtype=est.dtype)
    w = _weights(est.shape[0], valid, est.dtype)
    aligned = align_trajectory(est, gt, align, w)
    return _rpe_aligned(aligned, gt, w, int(delta))


def pose_metrics(est, gt, valid=None) -> dict:
    """ATE (Sim3 and SE3 aligned, m) and Sim3-aligned RPE (m, deg) with delta 1 for (N, 4, 4) poses.

    Returns dict(ate, ate_se3, rpe_trans, rpe_rot) of scalars (``evo_ape -as``, ``evo_ape -a``,
    ``evo_rpe -as -d 1 --all_pairs``).
    """
    est = jnp.asarray(est)
    gt = jnp.asarray(gt, dtype=est.dtype)
    w = _weights(est.shape[0], valid, est.dtype)
    gt_s = _sanitize(gt, w)
    sim3 = align_trajectory(est, gt, "sim3", w)
    se3 = align_trajectory(est, gt, "se3", w)
    rpe_t, rpe_r = _rpe_aligned(sim3, gt, w, 1)
    return {
        "ate": _ate_aligned(_sanitize(sim3, w), gt_s, w),
        "ate_se3": _ate_aligned(_sanitize(se3, w), gt_s, w),
        "rpe_trans": rpe_t,
        "rpe_rot": rpe_r,
    }


_pose_metrics_jit = jax.jit(pose_metrics)


@jax.jit
def _trajectory_metrics_jit(est, gt) -> dict:
    """:func:`pose_metrics` and :func:`rotation_rmse` in one program (a stored one: :mod:`cm3d.programs`)."""
    return {**pose_metrics(est, gt), "rot_rmse": rotation_rmse(est, gt)}


def rotation_rmse(est, gt, valid=None):
    """Rotation error (degrees, RMS over frames) after the best global rotation, whatever the
    positions: ``R* = argmin sum |R_gt_i - R* R_est_i|_F`` (the SO(3) projection of
    ``sum R_gt_i R_est_i^T``), then the angle of ``R_gt_i^T R* R_est_i``. Unlike ATE it stays defined
    for a camera that barely moves. est, gt: cam_to_world (N, 4, 4); valid: optional (N,) mask."""
    est = jnp.asarray(est)
    gt = jnp.asarray(gt, dtype=est.dtype)
    w = _weights(est.shape[0], valid, est.dtype)
    Re, Rg = _sanitize(est, w)[:, :3, :3], _sanitize(gt, w)[:, :3, :3]
    M = jnp.einsum("n,nij,nkj->ik", w, Rg, Re)
    U, _, Vt = jnp.linalg.svd(M)
    D = jnp.diag(jnp.array([1.0, 1.0, jnp.sign(jnp.linalg.det(U @ Vt))], est.dtype))
    R = U @ D @ Vt
    E = jnp.einsum("nji,jk,nkl->nil", Rg, R, Re)
    deg = _rotation_angle(E) * (180.0 / math.pi)
    return _weighted_rmse(deg ** 2, w)


def trajectory_extent(c2w) -> float:
    """RMS distance (m) of the camera centres (N, 4, 4) from their centroid (host)."""
    c = np.asarray(c2w, np.float64)[:, :3, 3]
    return float(np.sqrt(np.mean(np.sum((c - c.mean(0)) ** 2, axis=-1)))) if len(c) else 0.0


ATE_DEFINED_RATIO = 1.0 / math.sqrt(2.0)


def ate_is_defined(ate_sim3: float, extent: float, pairs: int) -> bool:
    """Whether a Sim(3)-aligned ATE says anything: at least 3 poses, and the fit did not shrink the
    estimate to its centroid. A Sim(3) fit can always scale an estimate down, so ATE <= extent; an
    estimate whose noise ``σ`` swamps a trajectory of extent ``e`` gives ``ATE ≈ e σ / sqrt(e² + σ²)``,
    which passes ``e / sqrt(2)`` exactly when ``σ > e``: the extent is below the noise (undefined)."""
    return bool(pairs >= 3 and extent > 0 and np.isfinite(ate_sim3) and ate_sim3 <= ATE_DEFINED_RATIO * extent)


# Association and file-level evaluation (host)


def _match_sorted(short: np.ndarray, long: np.ndarray, max_diff: float):
    """evo's binary-search matching (long sorted), vectorised with its exact comparisons."""
    idx_s = np.arange(len(short))
    keep = ~((short < long[0] - max_diff) | (short > long[-1] + max_diff))
    ub_i = np.minimum(np.searchsorted(long, short, side="right"), len(long) - 1)
    diff_ub = long[ub_i] - short
    lb_i = ub_i - 1
    diff_lb = np.where(ub_i > 0, short - long[np.maximum(lb_i, 0)], np.inf)
    take_ub = (diff_ub <= max_diff) & (diff_ub < diff_lb)
    take_lb = ~take_ub & (diff_lb <= max_diff) & (diff_lb <= diff_ub)
    keep &= take_ub | take_lb
    best = np.where(take_ub, ub_i, lb_i)
    return idx_s[keep], best[keep]


def _match_linear(short: np.ndarray, long: np.ndarray, max_diff: float):
    """evo's fallback for unsorted stamps: first argmin of |long - s| per short stamp."""
    diffs = np.abs(long[None, :] - short[:, None])
    best = np.argmin(diffs, axis=1)
    keep = diffs[np.arange(len(short)), best] <= max_diff
    return np.flatnonzero(keep), best[keep]


def associate(ts_ref, ts_est, max_diff: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Match timestamps (s) as ``evo.core.sync.associate_trajectories`` (nearest time) -> (idx_ref, idx_est).

    Each stamp of the shorter trajectory is matched to its nearest stamp of the other within
    ``max_diff``, ties resolved as evo does. Returns int64 arrays (possibly empty).
    """
    ref = np.asarray(ts_ref, dtype=np.float64).ravel()
    est = np.asarray(ts_est, dtype=np.float64).ravel()
    if len(ref) == 0 or len(est) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    second_longer = len(est) > len(ref)
    short, long = (ref, est) if second_longer else (est, ref)
    match = _match_sorted if np.all(np.diff(long) >= 0) else _match_linear
    i_short, i_long = match(short, long, float(max_diff))
    i_short, i_long = i_short.astype(np.int64), i_long.astype(np.int64)
    return (i_short, i_long) if second_longer else (i_long, i_short)


def evaluate_trajectories(gt_ts, gt_c2w, est_ts, est_c2w, max_diff: float = 0.01) -> dict:
    """Associate, then ATE/RPE in float64 -> dict(ate, ate_se3, rpe_trans, rpe_rot, rot_rmse (deg,
    after the best global rotation: :func:`rotation_rmse`), extent (the ground truth's, :func:`trajectory_extent`):
    float, ate_defined (:func:`ate_is_defined`): bool, pairs: int).

    By timestamp as evo (:func:`associate`); when both have the same length and no stamp matches
    (e.g. MonST3R's frame-index stamps) frame i pairs with frame i. ``ValueError`` below 2 pairs.
    """
    gt_ts = np.asarray(gt_ts, np.float64)
    est_ts = np.asarray(est_ts, np.float64)
    gt_c2w = np.asarray(gt_c2w, np.float64)
    est_c2w = np.asarray(est_c2w, np.float64)
    i_gt, i_est = associate(gt_ts, est_ts, max_diff)
    if len(i_gt) == 0 and len(gt_ts) == len(est_ts):
        i_gt = i_est = np.arange(len(gt_ts))
    if len(i_gt) < 2:
        raise ValueError(
            f"only {len(i_gt)} associated poses (gt {len(gt_ts)}, est {len(est_ts)}, "
            f"max_diff {max_diff} s); need at least 2"
        )
    from cm3d import programs

    with jax.enable_x64(True):
        m = programs.call("trajectory_metrics", _trajectory_metrics_jit, {}, jnp.asarray(est_c2w[i_est]),
                          jnp.asarray(gt_c2w[i_gt]))
        out = {k: float(m[k]) for k in ("ate", "ate_se3", "rpe_trans", "rpe_rot", "rot_rmse")}
    out["pairs"] = int(len(i_gt))
    out["extent"] = trajectory_extent(gt_c2w[i_gt])
    out["ate_defined"] = ate_is_defined(out["ate"], out["extent"], out["pairs"])
    return out


def evaluate_trajectory_files(gt_path, est_path, max_diff: float = 0.01) -> dict:
    """:func:`evaluate_trajectories` on two TUM files (see :func:`cm3d.data.tum.read_tum`)."""
    from cm3d.data.tum import read_tum

    gt_ts, gt_c2w = read_tum(gt_path)
    est_ts, est_c2w = read_tum(est_path)
    return evaluate_trajectories(gt_ts, gt_c2w, est_ts, est_c2w, max_diff)


# Depth (jnp)


def _depth_mask(pred, gt, valid):
    m = (gt > 0) & jnp.isfinite(gt) & jnp.isfinite(pred)
    if valid is not None:
        m = m & jnp.asarray(valid).astype(bool)
    return m


def align_depth_scale_shift(pred, gt, valid=None):
    """Least-squares ``gt ≈ scale * pred + shift`` over all valid pixels of a sequence -> (scale, shift).
    Pixels count when valid, ``gt > 0`` and finite; constant ``pred`` gives scale 0; empty gives NaN."""
    pred = jnp.asarray(pred)
    gt = jnp.asarray(gt, dtype=pred.dtype)
    w = _depth_mask(pred, gt, valid).astype(pred.dtype)
    p = jnp.where(w > 0, pred, 0.0)
    g = jnp.where(w > 0, gt, 0.0)
    n = jnp.sum(w)
    ok = n > 0
    n_safe = jnp.where(ok, n, 1.0)
    mp = jnp.sum(w * p) / n_safe
    mg = jnp.sum(w * g) / n_safe
    dp = w * (p - mp)
    var = jnp.sum(dp * (p - mp))
    cov = jnp.sum(dp * (g - mg))
    pos = var > 0
    scale = jnp.where(pos, cov / jnp.where(pos, var, 1.0), 0.0)
    shift = mg - scale * mp
    return jnp.where(ok, scale, jnp.nan), jnp.where(ok, shift, jnp.nan)


def depth_metrics(pred, gt, valid=None, align: bool = True) -> dict:
    """Depth errors after per-sequence scale-and-shift alignment -> dict(abs_rel, delta1) scalars.

    pred, gt: (S, H, W) depths in metres; valid: optional bool mask (leave out pixels with no prediction,
    e.g. a sensor's holes, there). Pixels count when valid, ``gt > 0`` and finite. ``abs_rel = mean |a - g| / g``, ``delta1`` = fraction with ``max(a/g, g/a) < 1.25`` (an
    aligned ``a <= 0`` fails it), ``a = scale * pred + shift`` (``pred`` when not ``align``). NaN when empty.
    """
    pred = jnp.asarray(pred)
    gt = jnp.asarray(gt, dtype=pred.dtype)
    m = _depth_mask(pred, gt, valid)
    if align:
        scale, shift = align_depth_scale_shift(pred, gt, m)
        a = scale * pred + shift
    else:
        a = pred
    w = m.astype(pred.dtype)
    g = jnp.where(m, gt, 1.0)
    a = jnp.where(m, a, 1.0)
    n = jnp.sum(w)
    ok = n > 0
    n_safe = jnp.where(ok, n, 1.0)
    abs_rel = jnp.sum(w * jnp.abs(a - g) / g) / n_safe
    a_pos = a > 0
    ratio = jnp.maximum(a / g, g / jnp.where(a_pos, a, 1.0))
    good = a_pos & (ratio < 1.25)
    delta1 = jnp.sum(w * good.astype(pred.dtype)) / n_safe
    return {"abs_rel": jnp.where(ok, abs_rel, jnp.nan), "delta1": jnp.where(ok, delta1, jnp.nan)}


# Dynamic masks (jnp)


def mask_metrics(pred, gt, valid=None) -> dict:
    """Binary mask agreement pooled over all pixels -> dict(iou, precision, recall) scalars in [0, 1].

    pred, gt: masks of one shape; bool or thresholded at 0.5 (True = dynamic); valid: optional mask.
    Never NaN: an empty denominator gives 1 (sklearn's ``zero_division=1``).
    """
    pred = jnp.asarray(pred)
    gt = jnp.asarray(gt)
    p = pred if pred.dtype == jnp.bool_ else pred > 0.5
    g = gt if gt.dtype == jnp.bool_ else gt > 0.5
    if valid is not None:
        v = jnp.asarray(valid).astype(bool)
        p, g = p & v, g & v
    ftype = jnp.result_type(float)
    tp = jnp.sum(p & g).astype(ftype)
    fp = jnp.sum(p & ~g).astype(ftype)
    fn = jnp.sum(~p & g).astype(ftype)

    def ratio(num, den):
        pos = den > 0
        return jnp.where(pos, num / jnp.where(pos, den, 1.0), 1.0)

    return {"iou": ratio(tp, tp + fp + fn), "precision": ratio(tp, tp + fp), "recall": ratio(tp, tp + fn)}


# Reconstruction (host)


def cloud_overlap(cloud_a, cloud_b, radius: float = 0.05) -> float:
    """Share of ``cloud_b``'s points (M, 3) within ``radius`` (metres) of ``cloud_a``'s (N, 3): how much of
    a revisit's surface a first visit saw (0 when either cloud is empty)."""
    from scipy.spatial import cKDTree

    a, b = np.asarray(cloud_a, np.float64).reshape(-1, 3), np.asarray(cloud_b, np.float64).reshape(-1, 3)
    if len(a) == 0 or len(b) == 0:
        return 0.0
    d, _ = cKDTree(a).query(b, distance_upper_bound=radius)
    return float(np.mean(np.isfinite(d)))


def reconstruction_metrics(pred_pts, gt_pts, pred_normals=None, gt_normals=None) -> dict:
    """Point-cloud accuracy/completion (metres) and normal consistency, 7-Scenes / NICE-SLAM protocol.

    pred_pts (N, 3), gt_pts (M, 3), optional normals. accuracy: distance of predicted points to the
    nearest gt point (mean, median); completion: the reverse; normal_consistency (with both normals):
    mean ``|n_pred . n_gt(nearest)|`` both ways, averaged.
    """
    from scipy.spatial import cKDTree

    pred = np.asarray(pred_pts, np.float64).reshape(-1, 3)
    gt = np.asarray(gt_pts, np.float64).reshape(-1, 3)
    if len(pred) == 0 or len(gt) == 0:
        raise ValueError(f"reconstruction_metrics needs non-empty clouds, got {len(pred)} and {len(gt)}")
    d_acc, i_acc = cKDTree(gt).query(pred)
    d_comp, i_comp = cKDTree(pred).query(gt)
    out = {
        "accuracy": float(np.mean(d_acc)),
        "accuracy_median": float(np.median(d_acc)),
        "completion": float(np.mean(d_comp)),
        "completion_median": float(np.median(d_comp)),
    }
    if pred_normals is not None and gt_normals is not None:
        npred = np.asarray(pred_normals, np.float64).reshape(-1, 3)
        ngt = np.asarray(gt_normals, np.float64).reshape(-1, 3)
        if npred.shape != pred.shape or ngt.shape != gt.shape:
            raise ValueError("normals must have the shapes of their point clouds")
        npred = npred / np.maximum(np.linalg.norm(npred, axis=-1, keepdims=True), 1e-12)
        ngt = ngt / np.maximum(np.linalg.norm(ngt, axis=-1, keepdims=True), 1e-12)
        nc_acc = np.mean(np.abs(np.sum(npred * ngt[i_acc], axis=-1)))
        nc_comp = np.mean(np.abs(np.sum(ngt * npred[i_comp], axis=-1)))
        out["normal_consistency"] = float(0.5 * (nc_acc + nc_comp))
    return out


# Median-scaled depth and point-cloud normals (the paper tables)


def depth_metrics_median(pred, gt, valid=None) -> dict:
    """Depth errors after per-sequence median-scale alignment (Table 1) -> dict(abs_rel, delta1, scale).

    ``a = s * pred``, ``s = median(gt) / median(pred)`` over the pixels that count (valid, ``gt > 0``,
    finite, ``pred > 0``); abs_rel and delta1 as :func:`depth_metrics`. NaN when no pixel counts.
    """
    pred = jnp.asarray(pred)
    gt = jnp.asarray(gt, dtype=pred.dtype)
    m = _depth_mask(pred, gt, valid) & (pred > 0)
    scale = masked_median(gt.ravel(), m.ravel()) / masked_median(pred.ravel(), m.ravel())  # 0 / 0 = NaN when empty
    out = depth_metrics(scale * pred, gt, m, align=False)
    return {**out, "scale": scale}


def estimate_normals(points, k: int = 16) -> np.ndarray:
    """Unoriented PCA normals (N, 3) of a point cloud (N, 3) (host): the eigenvector of the smallest
    eigenvalue of the covariance of each point's ``k`` nearest neighbours (itself included), as
    Open3D's ``estimate_normals(KDTreeSearchParamKNN(k))`` up to sign."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if len(pts) < 3:
        raise ValueError(f"estimate_normals: needs at least 3 points, got {len(pts)}")
    k = int(min(max(k, 3), len(pts)))
    _, idx = cKDTree(pts).query(pts, k=k)
    nb = pts[idx]
    d = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", d, d) / k
    _, vecs = np.linalg.eigh(cov)
    return vecs[:, :, 0]
