"""The 7-Scenes colour camera, fitted: its intrinsics and its pose on the depth camera.

    .venv/bin/python experiments/sevenscenes_calibration.py [--data DIR] [--pairs 60] [--quick] [--json PATH]

7-Scenes gives one K (``camera-intrinsics.txt``: f = 585 px, the Kinect's *depth* camera, which
KinectFusion used for the poses), and its depth is not registered to the colour frames. This script
fits the colour camera, fx = fy = f and the centre (cx, cy) (placed at the depth camera, see
:func:`camera`), by robust least squares (``scipy.optimize.least_squares``,
soft-L1 at 1 px) of the reprojection error of SIFT matches between colour frames: a colour keypoint
of frame i is lifted with frame i's sensor depth (read where the depth camera sees the colour ray:
:func:`cm3d.data.sevenscenes.lift_colour_pixels`), moved by the files' depth-camera poses into frame
j and projected with the colour camera; both directions of every match count.

Fitted on frame pairs of ``TUNE`` (frames 100-398), reported on pairs of ``REPORT`` (460-938), never
fitted on: median reprojection error and the share of matches within 2 px for the folder's K (the
two cameras taken as one), the Kinect colour camera's published intrinsics (f = 525, centre
(319.5, 239.5)) at the depth camera and 2.5 cm (the Kinect's baseline) either way along its x axis,
and the fit: the published camera explains the colour frames far better than the folder's K, the
baseline's sign is told apart (-2.5 cm, what :data:`cm3d.data.sevenscenes.KINECT_COLOUR` holds), and
the fit is barely better than the published camera (the floor, ~1.8 px, is the ground truth's own
error and the colour and depth frames' time offset).

A second table asks how far the colour frames and the depth frames each turn between the report pairs,
against the files' poses, with estimators that know nothing of those poses: the colour frames by PnP (the
pair's SIFT matches, frame i's keypoints lifted with its sensor depth into the Kinect colour camera,
OpenCV's RANSAC then Levenberg-Marquardt), the depth frames by point-to-plane ICP of the two sensor
clouds (Open3D, the folder's K: the camera and K that KinectFusion tracked for the files' poses). Per pair:
the estimated rotation angle over the files' (pairs where the files turn by at least 1 degree), the angle
between the two rotation axes, and over all pairs the least-squares slope of the estimated rotation
vectors on the files' (the colour frames also with the folder's K, as the benchmarks see them). The depth
frames turn nearly as the files say (0.97-0.98); the colour frames turn less (0.92-0.96; 0.86-0.91 with
the folder's K), with motions that reproject their matches far better than the files' poses do: the
under-rotation that cm3d's windows show on the kitchen (docs/pipeline.md, stop 58). A last table says what
such a bias alone costs: the folder's trajectory with every step turned by that ratio and nothing else
changed, its ATE as 40-frame chunks stitched on their overlaps and as one chain (the two agree: a chunk's
overlap steps are the chunk before's, so its overlap places it exactly).

JSON keys: f, cx, cy (the fit), report_median_px_X and report_within2_X for X in folder, published,
published_plus, published_minus, fit; matches_tune, matches_report; rotation_ratio_colour,
rotation_slope_colour, rotation_axis_deg_colour, pnp_median_px_colour, files_median_px_colour, rotation_ratio_depth,
rotation_slope_depth, rotation_axis_deg_depth, rotation_pairs; turned_ate_stitched and turned_ate_chain
(the whole folder's ATE when every step turns by the report pairs' colour slope, stitched as 40-frame
chunks and as one chain); rotation_slope_folder_k and turned_ate_folder_k (the same PnP with the folder's
K for the colour frames, what the benchmarks feed cm3d, and the chain at its slope).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from cm3d.data import sevenscenes
from cm3d.data.sevenscenes import ColourCamera, lift_colour_pixels
from cm3d.outputs import write_json

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "sevenscenes_redkitchen"
TUNE, REPORT = (100, 400), (460, 940)
GAPS = (2, 4, 8)  # listed frames apart (every 2nd sequence frame is listed: 4-16 frames of the sequence)


def matches(g0, g1):
    """SIFT matches (ratio 0.75, mutual, fundamental-matrix RANSAC at 2 px): (uv0 (N, 2), uv1 (N, 2))."""
    import cv2

    sift = cv2.SIFT_create(nfeatures=2000)
    (k0, d0), (k1, d1) = sift.detectAndCompute(g0, None), sift.detectAndCompute(g1, None)
    if d0 is None or d1 is None or len(k0) < 8 or len(k1) < 8:
        return np.zeros((0, 2)), np.zeros((0, 2))
    bf = cv2.BFMatcher()
    fwd = [m for m, n in bf.knnMatch(d0, d1, k=2) if m.distance < 0.75 * n.distance]
    back = {m.queryIdx: m.trainIdx for m in bf.match(d1, d0)}
    fwd = [m for m in fwd if back.get(m.trainIdx) == m.queryIdx]
    if len(fwd) < 8:
        return np.zeros((0, 2)), np.zeros((0, 2))
    p0 = np.float64([k0[m.queryIdx].pt for m in fwd])
    p1 = np.float64([k1[m.trainIdx].pt for m in fwd])
    _, inl = cv2.findFundamentalMat(p0, p1, cv2.FM_RANSAC, 2.0, 0.999)
    keep = np.zeros(len(p0), bool) if inl is None else inl.ravel().astype(bool)
    return p0[keep], p1[keep]


def camera(x) -> ColourCamera:
    """(f, cx, cy) -> a colour camera at the depth camera's place. Its offset on the depth camera (a
    Kinect: ~2.5 cm) is left out: fitted as well (with or without a rotation), it took implausible
    values (4 cm, 3 cm, -3 cm) that the report pairs reprojected no better (1.78 px against 1.84 px): the
    matches cannot tell it from the focal length and the centre at these depths."""
    f, cx, cy = (float(v) for v in x)
    return ColourCamera(f=f, cx=cx, cy=cy)


def residuals(cam: ColourCamera, data, Kd) -> np.ndarray:
    """Reprojection errors (px) of every match, both directions (NaN where a keypoint has no depth)."""
    Kc, T_cd = cam.K(), cam.depth_to_colour()
    out = []
    for (d0, d1, P0, P1, uv0, uv1) in data:
        for (da, Pa, uva, Pb, uvb) in ((d0, P0, uv0, P1, uv1), (d1, P1, uv1, P0, uv0)):
            X, ok = lift_colour_pixels(uva, da, Kd, cam)  # colour camera a
            # colour a -> depth a -> world -> depth b -> colour b
            T = T_cd @ np.linalg.inv(Pb) @ Pa @ np.linalg.inv(T_cd)
            Y = X @ T[:3, :3].T + T[:3, 3]
            uv = (Y @ Kc.T)[:, :2] / np.maximum(Y[:, 2:], 1e-6)
            r = uv - uvb
            r[~ok | (Y[:, 2] <= 0)] = np.nan
            out.append(r)
    return np.concatenate(out)


def gather(folder, span, n_pairs, rng):
    """``n_pairs`` frame pairs of the frames in ``span`` (a gap from GAPS each), with their matches, depth
    and depth-camera poses."""
    import cv2

    nums = [n for n in sevenscenes.frame_numbers(folder) if span[0] <= n < span[1]]
    data = []
    starts = rng.choice(len(nums) - max(GAPS), size=n_pairs, replace=len(nums) - max(GAPS) < n_pairs)
    for k, i in enumerate(starts):
        a, b = nums[i], nums[i + GAPS[k % len(GAPS)]]
        frames = [sevenscenes.load_sevenscenes(folder, f"{n}:{n + 1}") for n in (a, b)]
        g = [cv2.cvtColor(s.images[0], cv2.COLOR_RGB2GRAY) for s in frames]
        uv0, uv1 = matches(*g)
        data.append((frames[0].depth[0], frames[1].depth[0], frames[0].gt.cam_to_world[0],
                     frames[1].gt.cam_to_world[0], uv0, uv1))
    return data


def colour_rotations(data, cam: ColourCamera, Kd):
    """Per pair: (files' rotation vector, PnP rotation vector, median reprojection px of PnP's inliers under
    its pose and under the files' poses) in the colour camera (from frame a to frame b); pairs with fewer
    than 12 lifted matches or PnP inliers are left out."""
    import cv2

    Kc, T_cd = cam.K(), cam.depth_to_colour()
    out = []
    for (d0, _d1, P0, P1, uv0, uv1) in data:
        X, ok = lift_colour_pixels(uv0, d0, Kd, cam)
        if ok.sum() < 12:
            continue
        X, uv = X[ok], uv1[ok]
        found, rv, tv, inl = cv2.solvePnPRansac(X, uv, Kc, None, reprojectionError=2.0, iterationsCount=1000,
                                                flags=cv2.SOLVEPNP_EPNP)
        if not found or inl is None or len(inl) < 12:
            continue
        rv, tv = cv2.solvePnPRefineLM(X[inl[:, 0]], uv[inl[:, 0]], Kc, None, rv, tv)
        proj = cv2.projectPoints(X[inl[:, 0]], rv, tv, Kc, None)[0][:, 0]
        T = T_cd @ np.linalg.inv(P1) @ P0 @ np.linalg.inv(T_cd)  # colour a -> colour b, the files' poses
        Y = X[inl[:, 0]] @ T[:3, :3].T + T[:3, 3]
        files = (Y @ Kc.T)[:, :2] / Y[:, 2:]
        err = [float(np.median(np.linalg.norm(q - uv[inl[:, 0]], axis=1))) for q in (proj, files)]
        out.append((rotvec(T[:3, :3]), rv.ravel(), *err))
    return out


def depth_rotations(data, Kd, voxels=(0.04, 0.02, 0.01)):
    """Per pair: (files' rotation vector, ICP rotation vector) of the depth camera, by Open3D point-to-plane
    ICP of the two sensor clouds, coarse to fine (``voxels`` m, each level within 3 voxels), started at the
    identity."""
    import open3d as o3d

    def cloud(d, voxel):
        v, u = np.nonzero(d > 0)
        z = d[v, u].astype(np.float64)
        X = np.c_[(u - Kd[0, 2]) / Kd[0, 0] * z, (v - Kd[1, 2]) / Kd[1, 1] * z, z]
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(X)).voxel_down_sample(voxel)
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=30))
        return pc

    reg = o3d.pipelines.registration
    out = []
    for (d0, d1, P0, P1, _uv0, _uv1) in data:
        T_est = np.eye(4)
        for voxel in voxels:
            T_est = reg.registration_icp(cloud(d0, voxel), cloud(d1, voxel), 3 * voxel, T_est,
                                         reg.TransformationEstimationPointToPlane(),
                                         reg.ICPConvergenceCriteria(max_iteration=60)).transformation
        T = np.linalg.inv(P1) @ P0
        out.append((rotvec(T[:3, :3]), rotvec(np.asarray(T_est)[:3, :3])))
    return out


def rotvec(R) -> np.ndarray:
    return Rotation.from_matrix(R).as_rotvec()


def rotation_summary(pairs, min_deg: float = 1.0) -> tuple[float, float, float, int]:
    """(median angle ratio estimated / files', least-squares slope of the estimated rotation vectors on the
    files', median axis angle in degrees, pairs in the ratio) over ``pairs`` of (files', estimated, ...)."""
    g = np.array([p[0] for p in pairs])
    e = np.array([p[1] for p in pairs])
    ng, ne = np.linalg.norm(g, axis=1), np.linalg.norm(e, axis=1)
    big = ng >= np.radians(min_deg)
    axis = np.degrees(np.arccos(np.clip(np.sum(e * g, 1) / np.maximum(ng * ne, 1e-12), -1, 1)))
    slope = float(np.sum(e * g) / np.sum(g * g))
    return float(np.median(ne[big] / ng[big])), slope, float(np.median(axis[big])), int(big.sum())


def turned_by(poses: np.ndarray, ratio: float) -> np.ndarray:
    """The trajectory whose every step (camera i -> i + 1, in camera i's frame) keeps its translation and
    turns ``ratio`` times as far about the same axis (first pose at the identity)."""
    out = [np.eye(4)]
    for a, b in zip(poses[:-1], poses[1:]):
        T = np.linalg.inv(a) @ b
        T[:3, :3] = Rotation.from_rotvec(ratio * rotvec(T[:3, :3])).as_matrix()
        out.append(out[-1] @ T)
    return np.array(out)


def stitched(poses: np.ndarray, ratio: float, length: int = 40, overlap: int = 10) -> np.ndarray:
    """:func:`turned_by` on chunks of ``length`` frames overlapping by ``overlap``, each placed on the frames
    stitched before it by the rigid fit of its overlap (rotation: the chordal mean; translation: the
    centres' mean): what chunks that under-rotate by ``ratio``, and are right otherwise, stitch to."""
    n = len(poses)
    out = np.zeros_like(poses)
    for k, a in enumerate(range(0, n - overlap, length - overlap)):
        b = min(a + length, n)
        C = turned_by(poses[a:b], ratio)
        if k == 0:
            out[a:b] = C
            continue
        A, B = out[a:a + overlap], C[:overlap]
        U, _, Vt = np.linalg.svd(np.einsum("nij,nkj->ik", A[:, :3, :3], B[:, :3, :3]))
        W = np.eye(4)
        W[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        W[:3, 3] = A[:, :3, 3].mean(0) - (B[:, :3, 3] @ W[:3, :3].T).mean(0)
        out[a + overlap:b] = (W @ C)[overlap:]
    return out


def summary(r) -> tuple[float, float]:
    e = np.linalg.norm(r, axis=1)
    e = e[np.isfinite(e)]
    return float(np.median(e)), float(np.mean(e < 2.0))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(DEFAULT_DATA))
    ap.add_argument("--pairs", type=int, default=60, help="frame pairs to fit on (and as many to report on)")
    ap.add_argument("--quick", action="store_true", help="6 pairs each, a few solver steps")
    ap.add_argument("--json", default=None, metavar="PATH")
    args = ap.parse_args()
    t0 = time.perf_counter()
    folder = Path(args.data)
    n = 6 if args.quick else args.pairs
    rng = np.random.default_rng(0)
    tune, report = gather(folder, TUNE, n, rng), gather(folder, REPORT, n, rng)
    Kd = sevenscenes.read_intrinsics(folder)
    folder_cam = ColourCamera(f=float(Kd[0, 0]), cx=float(Kd[0, 2]), cy=float(Kd[1, 2]))
    published = ColourCamera(f=525.0, cx=319.5, cy=239.5)
    baseline = [("published, +2.5 cm", dataclasses.replace(published, translation=(0.025, 0.0, 0.0))),
                ("published, -2.5 cm", dataclasses.replace(published, translation=(-0.025, 0.0, 0.0)))]
    x0 = np.array([published.f, published.cx, published.cy], float)

    def fun(x):
        r = residuals(camera(x), tune, Kd)
        return np.nan_to_num(r, nan=0.0).ravel()  # (a keypoint without depth contributes nothing)

    sol = least_squares(fun, x0, loss="soft_l1", f_scale=1.0, x_scale=[10, 5, 5],
                        max_nfev=8 if args.quick else 200)
    fit = camera(sol.x)
    n_tune = int(np.sum(np.isfinite(residuals(fit, tune, Kd)[:, 0])))
    rows, figures = [], {}
    for name, cam in (("folder", folder_cam), ("published", published), *baseline, ("fit", fit)):
        mt, wt = summary(residuals(cam, tune, Kd))
        mr, wr = summary(residuals(cam, report, Kd))
        rows.append((name, cam, mt, wt, mr, wr))
        key = {"published, +2.5 cm": "published_plus", "published, -2.5 cm": "published_minus"}.get(name, name)
        figures[f"report_median_px_{key}"], figures[f"report_within2_{key}"] = mr, wr
    print(f"{folder.name}: {n} frame pairs to fit (frames {TUNE[0]}-{TUNE[1] - 2}), {n} to report on (frames "
          f"{REPORT[0]}-{REPORT[1] - 2}), gaps {GAPS} listed frames; {n_tune} tuning residuals\n")
    print(f"{'colour camera':>18} {'f':>7} {'cx':>7} {'cy':>7} | {'tune med px':>11} "
          f"{'<2px':>5} | {'report med px':>13} {'<2px':>5}")
    for name, cam, mt, wt, mr, wr in rows:
        print(f"{name:>18} {cam.f:7.1f} {cam.cx:7.1f} {cam.cy:7.1f} | {mt:11.2f} {100 * wt:4.0f}% | "
              f"{mr:13.2f} {100 * wr:4.0f}%")
    print(f"\nfitted: ColourCamera(f={fit.f:.1f}, cx={fit.cx:.1f}, cy={fit.cy:.1f})")
    print(f"\nhow far the frames turn between frame pairs, against the files' poses (pairs turning >= 1 deg)")
    print(f"{'frames':>9} {'(estimator)':>28} | {'angle ratio':>11} {'slope':>6} {'axis deg':>8} {'pairs':>5} "
          f"{'PnP px':>6} {'files px':>8}")
    rot = {}  # span -> the summaries of rotation_summary (colour, folder_k, depth) and the colour pairs' px
    for span, data in ((TUNE, tune), (REPORT, report)):
        colour = colour_rotations(data, sevenscenes.KINECT_COLOUR, Kd)
        r = rot[span] = {"colour": rotation_summary(colour),
                         "folder_k": rotation_summary(colour_rotations(data, folder_cam, Kd)),
                         "depth": rotation_summary(depth_rotations(data, Kd)),
                         "pnp_px": float(np.median([p[2] for p in colour])),
                         "files_px": float(np.median([p[3] for p in colour]))}
        for name, key in (("colour (SIFT + depth, PnP)", "colour"), ("... with the folder's K", "folder_k"),
                          ("depth (point-to-plane ICP)", "depth")):
            ratio, slope, axis, k = r[key]
            px = f"{r['pnp_px']:6.2f} {r['files_px']:8.2f}" if key == "colour" else ""
            print(f"{span[0]:>4}-{span[1] - 2:<4} {name:>28} | {ratio:11.3f} {slope:6.3f} {axis:8.1f} {k:5d} {px:>6}")
    rc, rd, rf = rot[REPORT]["colour"], rot[REPORT]["depth"], rot[REPORT]["folder_k"]
    pnp_px, files_px = rot[REPORT]["pnp_px"], rot[REPORT]["files_px"]
    print("(px: median reprojection of PnP's inliers under PnP's pose and under the files' poses)")
    from cm3d.eval import metrics

    nums = sevenscenes.frame_numbers(folder)
    poses = np.array([sevenscenes.read_pose(folder / f"frame-{n:06d}.pose.txt") for n in nums])
    ratios = (rc[1], rot[TUNE]["colour"][1], rf[1], rot[TUNE]["folder_k"][1])
    drift = {r: (float(metrics.ate(stitched(poses, r).astype(np.float32), poses.astype(np.float32))),
                 float(metrics.ate(turned_by(poses, r).astype(np.float32), poses.astype(np.float32))))
             for r in ratios}
    print(f"\nthe files' {len(nums)} frames, every step turned by a ratio and nothing else changed: ATE (Sim(3), m)")
    print(f"{'ratio':>6} | {'40-frame chunks, overlap 10, stitched':>37} | {'one chain':>9}")
    for r, (a, b) in drift.items():
        print(f"{r:6.3f} | {a:37.4f} | {b:9.4f}")
    print(f"wall {time.perf_counter() - t0:.0f} s")
    figures |= {"f": fit.f, "cx": fit.cx, "cy": fit.cy, "matches_tune": int(sum(len(d[4]) for d in tune)),
                "matches_report": int(sum(len(d[4]) for d in report)),
                "rotation_ratio_colour": rc[0], "rotation_slope_colour": rc[1], "rotation_axis_deg_colour": rc[2],
                "pnp_median_px_colour": pnp_px, "files_median_px_colour": files_px,
                "rotation_ratio_depth": rd[0], "rotation_slope_depth": rd[1],
                "rotation_axis_deg_depth": rd[2], "rotation_pairs": rc[3],
                "turned_ate_stitched": drift[rc[1]][0], "turned_ate_chain": drift[rc[1]][1],
                "rotation_slope_folder_k": rf[1], "turned_ate_folder_k": drift[rf[1]][1]}
    if args.json:
        write_json(args.json, figures)


if __name__ == "__main__":
    main()
