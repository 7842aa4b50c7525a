"""ICP, voxel downsampling and global registration: cm3d (JAX, CPU) against Open3D and small_gicp.

    .venv/bin/python experiments/bench_icp.py [--sizes 5000 20000 100000] [--reps 3] [--median] [--quick] [--json PATH]

Room-like clouds (floor, ceiling, walls, boxes; source and target sampled independently), a
3 deg / 11 cm offset, max correspondence distance 0.3 m, same inputs for every method. For each size
and method (point-to-point, point-to-plane) it times: cm3d with the target index cached (as memory
entries keep it), cm3d including the index build, Open3D ``registration_icp`` and small_gicp
``align`` (target KD-tree and normals cached), each to convergence (100 iterations at most) and at a
fixed 30 iterations; then a batch of 8 pairs (vmap against a loop) and voxel downsampling. Prints
time ratios (cm3d / peer, < 1 means cm3d is faster), compile times separately, and the final
transform error ``max |T - T_gt|`` of each.

"Including the build" compares like with like: cm3d's index build (grid, 16-NN graph, PCA normals)
plus its ICP against Open3D's target normal estimation (``estimate_normals``, 16 nearest; point-to-
plane only, point-to-point needs none) plus ``registration_icp``, which builds its KD-tree inside
every call. ``time_ratio_with_build_20k`` is the worse of the two methods. small_gicp stops by its
own default criterion (1e-3 m / 0.1 deg steps), looser than Open3D's: see its error column.

``--gpu`` (the default when JAX runs on a GPU): cm3d on the accelerator, one pair and a vmapped
batch of 8 pairs against a Python loop at 20k and 100k points (Open3D, on the CPU, as a reference
column when it is installed; small_gicp is not needed); keys ``gpu_p2p_20k_ms``, ``gpu_p2l_20k_ms``,
``gpu_build_20k_ms``, ``gpu_batch8_speedup`` (loop / vmap, p2l 20k), the same at 100k, ...

Global registration (full run only): pairs of partially overlapping visits of the synthetic world,
the source moved by a random > 90 deg rotation (and, for Sim(3), scaled by 0.65-1.5); success =
global registration + ICP within 1 deg and 5 cm of the truth, for cm3d and for Open3D's FPFH +
``registration_ransac_based_on_feature_matching`` (its normals as they come, and oriented towards
the centroid as cm3d's are).

``--quick`` (the smoke test): 20k points, to convergence only, no batch, no global registration;
its ``*_100k`` voxel key then holds the 20k figure.
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from cm3d.data import synthetic
from cm3d.outputs import write_json
from cm3d.ops.neighbors import build_target_index
from cm3d.ops.voxel import voxel_downsample
from cm3d.solvers.icp import ICPOptions, icp, icp_batch, stack_indices

R = 0.3
o3d = reg = None  # Open3D, imported by _load_open3d (absent on the accelerator machine)


def _load_open3d():
    """Import Open3D into the module globals; False (with a note) when it is not installed."""
    global o3d, reg
    try:
        import open3d
    except ImportError:
        print("note: open3d is not installed: the Open3D columns are skipped")
        return False
    o3d, reg = open3d, open3d.pipelines.registration
    return True


def _load_small_gicp():
    try:
        import small_gicp
    except ImportError:  # a benchmark extra
        print("note: small_gicp is not installed: its columns are skipped")
        return None
    return small_gicp


def room(n, seed=0, size=(6.0, 5.0, 3.0), boxes=6):
    """Room-like cloud of n points with ``boxes`` random boxes (fixed layout), 3 mm noise."""
    L, W, _ = size
    brng = np.random.default_rng(1234)
    layout = []
    for _ in range(boxes):
        x, y, _ = brng.uniform([0.5, 0.5, 0], [L - 1.5, W - 1.5, 0])
        layout.append((x, y, *brng.uniform(0.3, 1.2, 3)))
    return synthetic.room_cloud(n, seed, size, layout)


def make_pair(n, seed):
    rng = np.random.default_rng(seed + 77)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) / np.sqrt(3) * np.deg2rad(3.0)).as_matrix()
    d = rng.normal(size=3)
    T[:3, 3] = d / np.linalg.norm(d) * 0.11
    tgt, src = room(n, 2 * seed), room(n, 2 * seed + 1)
    return ((src - T[:3, 3]) @ T[:3, :3]).astype(np.float32), tgt, T


STAT = min  # --median: the median of the repetitions instead of the best (a loaded machine)


def best_of(fn, reps):
    ts = []
    out = None
    for _ in range(reps):
        t0 = time.perf_counter()
        out = fn()
        jax.block_until_ready(out)
        ts.append(time.perf_counter() - t0)
    return float(STAT(ts)), out


def err(T, T_gt):
    return float(np.abs(np.asarray(T, np.float64) - T_gt).max())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[5000, 20000, 100000])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--quick", action="store_true", help="20k points, to convergence, 1 repetition, no batch")
    ap.add_argument("--global-trials", type=int, default=2, help="random poses per synthetic pair")
    ap.add_argument("--gpu", action="store_true", help="the accelerator section (default when JAX runs on a GPU)")
    ap.add_argument("--median", action="store_true", help="report the median of the repetitions, not the best")
    ap.add_argument("--json", default=None, metavar="PATH")
    args = ap.parse_args()
    global STAT
    STAT = np.median if args.median else min
    if args.gpu or jax.default_backend() == "gpu":
        figures = bench_gpu(args)
        if args.json:
            write_json(args.json, {k: (float(v) if not isinstance(v, bool) else v) for k, v in figures.items()})
        return
    if not _load_open3d():
        raise SystemExit("the CPU benchmark compares with Open3D: install open3d (or run the --gpu section)")
    sizes, reps, batch = ((20000,), 1, 2) if args.quick else (args.sizes, args.reps, args.batch)
    modes = (("conv", 100),) if args.quick else (("conv", 100), ("30it", 30))
    small_gicp = _load_small_gicp()

    build = jax.jit(build_target_index, static_argnames=("radius",))
    run = jax.jit(icp, static_argnames="options")
    figures = {}
    print(f"jax {jax.__version__} on {jax.devices()[0].platform}, open3d {o3d.__version__}, max corr {R} m, "
          f"times in ms ({'median' if args.median else 'best'} of {reps}), ratio = cm3d / peer; '+build': cm3d including its index build "
          f"(grid, 16-NN graph, PCA normals), 'o3d+n': Open3D including its target normals (p2l; its "
          f"KD-tree is built inside registration_icp), r_bld = +build / o3d+n")
    hdr = (f"{'n':>7} {'method':>6} {'mode':>6} | {'cm3d':>7} {'+build':>7} {'open3d':>7} {'o3d+n':>7} {'sgicp':>7} | "
           f"{'r_o3d':>5} {'r_sg':>5} {'r_bld':>5} | {'it':>3} | {'err_cm3d':>8} {'err_o3d':>8} {'err_sg':>8}")
    print(hdr)
    print("-" * len(hdr))
    err_diff = []
    for n in sizes:
        src, tgt, T_gt = make_pair(n, 0)
        t0 = time.perf_counter()
        index = build(jnp.asarray(tgt), radius=R)
        jax.block_until_ready(index)
        compile_build = time.perf_counter() - t0
        t_build, index = best_of(lambda: build(jnp.asarray(tgt), radius=R), reps)
        t_normals, pt = best_of(lambda: _o3d_target(tgt), reps)
        ps = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src.astype(np.float64)))
        if small_gicp is not None:
            sg_t = small_gicp.PointCloud(tgt.astype(np.float64))
            sg_tree = small_gicp.KdTree(sg_t, num_threads=2)
            small_gicp.estimate_normals_covariances(sg_t, sg_tree, num_neighbors=16, num_threads=2)
            sg_s = small_gicp.PointCloud(src.astype(np.float64))
        for method, short in (("point_to_point", "p2p"), ("point_to_plane", "p2l")):
            for mode, iters in modes:
                crit = dict(relative_fitness=1e-6, relative_rmse=1e-6) if mode == "conv" else dict(relative_fitness=0.0, relative_rmse=0.0)
                opts = ICPOptions(method=method, max_correspondence_distance=R, max_iterations=iters, **crit)
                t0 = time.perf_counter()
                jax.block_until_ready(run(jnp.asarray(src), index, options=opts))
                compile_icp = time.perf_counter() - t0
                t_c, res = best_of(lambda: run(jnp.asarray(src), index, options=opts), reps)
                est = reg.TransformationEstimationPointToPlane() if method == "point_to_plane" else reg.TransformationEstimationPointToPoint()
                oc = reg.ICPConvergenceCriteria(max_iteration=iters, **crit)
                t_o, ro = best_of(lambda: reg.registration_icp(ps, pt, R, np.eye(4), est, oc).transformation, reps)
                # Open3D's point-to-plane needs the target normals (its KD-tree is built in the call)
                t_on = t_o + (t_normals if short == "p2l" else 0.0)
                t_s, e_s = float("nan"), float("nan")
                if small_gicp is not None:
                    rt = "ICP" if method == "point_to_point" else "PLANE_ICP"
                    kw = dict(registration_type=rt, max_correspondence_distance=R, num_threads=2, max_iterations=iters)
                    t_s, rs = best_of(lambda: small_gicp.align(sg_t, sg_s, sg_tree, **kw), reps)
                    e_s = err(rs.T_target_source, T_gt)
                e_c, e_o = err(res.transform, T_gt), err(ro, T_gt)
                print(f"{n:>7} {short:>6} {mode:>6} | {t_c*1e3:7.1f} {(t_c+t_build)*1e3:7.1f} {t_o*1e3:7.1f} {t_on*1e3:7.1f} "
                      f"{t_s*1e3:7.1f} | {t_c/t_o:5.2f} {t_c/t_s:5.2f} {(t_c+t_build)/t_on:5.2f} | {int(res.iterations):>3} | "
                      f"{e_c:8.1e} {e_o:8.1e} {e_s:8.1e}   (compile icp {compile_icp:.1f} s)")
                k = f"{n // 1000}k"
                if mode == "conv":
                    err_diff.append(e_c - e_o)
                    figures[f"time_ratio_{short}_{k}"] = t_c / t_o
                    figures[f"time_ratio_vs_small_gicp_{short}_{k}"] = t_c / t_s
                    figures[f"time_ratio_with_build_{short}_{k}"] = (t_c + t_build) / t_on
                    figures[f"err_cm3d_{short}_{k}"] = e_c
                    figures[f"err_o3d_{short}_{k}"] = e_o
                    figures[f"iterations_cm3d_{short}_{k}"] = int(res.iterations)
        if f"time_ratio_with_build_p2l_{n // 1000}k" in figures:
            # the headline: the worse of the two methods
            figures[f"time_ratio_with_build_{n // 1000}k"] = max(figures[f"time_ratio_with_build_p2p_{n // 1000}k"],
                                                                 figures[f"time_ratio_with_build_p2l_{n // 1000}k"])
        print(f"{n:>7} index build {t_build*1e3:.1f} ms (compile {compile_build:.1f} s), Open3D normals "
              f"{t_normals*1e3:.1f} ms, truncated k-NN lists {int(index.truncated)}, overflow {int(index.overflow)}")

    # A batch of pairs: vmap against a loop (full run only: one more compilation).
    if not args.quick:
        n = 20000 if 20000 in sizes else sizes[0]
        pairs = [make_pair(n, s) for s in range(batch)]
        idx = [build(jnp.asarray(t), radius=R) for _, t, _ in pairs]
        srcs = jnp.asarray(np.stack([p[0] for p in pairs]))
        opts = ICPOptions(method="point_to_plane", max_correspondence_distance=R, max_iterations=100)
        bidx = stack_indices(idx)
        vb = jax.jit(icp_batch, static_argnames="options")
        jax.block_until_ready(vb(srcs, bidx, options=opts))
        t_v, rb = best_of(lambda: vb(srcs, bidx, options=opts), reps)
        t_l, rl = best_of(lambda: [run(srcs[b], idx[b], options=opts) for b in range(batch)], reps)
        t_ob, _ = best_of(lambda: [reg.registration_icp(
            o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p[0].astype(np.float64))), pt_b, R, np.eye(4),
            reg.TransformationEstimationPointToPlane(), reg.ICPConvergenceCriteria(max_iteration=100))
            for p, pt_b in zip(pairs, [_o3d_target(p[1]) for p in pairs])], 1)
        same = _batch_equals_loop(rb, rl)
        print(f"\nbatch of {batch} p2l pairs at {n}: vmap {t_v*1e3:.1f} ms, loop {t_l*1e3:.1f} ms (vmap/loop {t_v/t_l:.2f}), "
              f"open3d loop {t_ob*1e3:.1f} ms (incl. normals); vmap == loop: {same}")
        figures["batch_vmap_over_loop"] = t_v / t_l
        figures["batch_vmap_over_open3d_loop"] = t_v / t_ob
        figures["batch_vmap_equals_loop"] = bool(same)

    # Voxel downsampling.
    nv = max(sizes)
    cloud = room(nv, 5)
    vs = 0.02
    vd = jax.jit(lambda p: voxel_downsample(p, vs))
    jax.block_until_ready(vd(jnp.asarray(cloud)))
    t_vc, vout = best_of(lambda: vd(jnp.asarray(cloud)), reps)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud.astype(np.float64)))
    t_vo, dv = best_of(lambda: pc.voxel_down_sample(vs), reps)
    line = f"voxel downsample {nv} pts @ {vs} m: cm3d {t_vc*1e3:.1f} ms ({int(vout.count)} voxels), open3d {t_vo*1e3:.1f} ms ({len(dv.points)})"
    if small_gicp is not None:
        t_vs, _ = best_of(lambda: small_gicp.voxelgrid_sampling(cloud.astype(np.float64), vs, num_threads=2), reps)
        line += f", small_gicp {t_vs*1e3:.1f} ms (ratio {t_vc/t_vs:.2f})"
    print(line + f"; ratio cm3d/open3d {t_vc/t_vo:.2f}")
    figures[f"voxel_time_ratio_{nv // 1000}k"] = t_vc / t_vo
    figures.setdefault("voxel_time_ratio_100k", t_vc / t_vo)
    figures["err_diff_max"] = float(max(err_diff))
    for key in ("time_ratio_p2p_20k", "time_ratio_p2l_20k", "time_ratio_vs_small_gicp_p2p_20k",
                "time_ratio_vs_small_gicp_p2l_20k", "time_ratio_with_build_20k"):
        figures.setdefault(key, float("nan"))
    if not args.quick and args.global_trials > 0:
        figures.update(bench_global(args.global_trials))
    print("\nheadline:")
    for k in ("time_ratio_p2p_20k", "time_ratio_p2l_20k", "time_ratio_vs_small_gicp_p2p_20k",
              "time_ratio_vs_small_gicp_p2l_20k", "time_ratio_with_build_20k", "err_diff_max", "voxel_time_ratio_100k"):
        print(f"  {k:36s} {figures[k]:.3f}")
    if args.json:
        write_json(args.json, {k: (float(v) if not isinstance(v, bool) else v) for k, v in figures.items()})


def _batch_equals_loop(rb, rl):
    """A vmapped batch result equals the loop's: transforms up to float32 rounding (batched reductions
    sum in another order), same iterations and inlier counts."""
    return all(np.allclose(np.asarray(rb.transform[b]), np.asarray(r.transform), atol=1e-4)
               and int(rb.iterations[b]) == int(r.iterations) and int(rb.inlier_count[b]) == int(r.inlier_count)
               for b, r in enumerate(rl))


def bench_gpu(args):
    """cm3d on the accelerator: one pair and a vmapped batch of pairs against a Python loop, per size
    and method; Open3D (CPU, if installed) as a reference column. Keys ``gpu_{p2p,p2l}_{n}k_ms``,
    ``gpu_build_{n}k_ms``, ``gpu_batch{B}_speedup[_{n}k]`` (loop time / vmap time, p2l), ``gpu_err_diff_max``."""
    sizes, reps, batch = ((20000,), 1, 2) if args.quick else ((20000, 100000), args.reps, args.batch)
    have_o3d = _load_open3d()
    dev = jax.devices()[0]
    print(f"jax {jax.__version__} on {dev.platform} ({dev.device_kind}), max corr {R} m, times in ms (best of {reps}); "
          f"batch of {batch} pairs: vmap vs a Python loop of single calls"
          + ("" if have_o3d else "; Open3D columns skipped (not installed)"))
    build = jax.jit(build_target_index, static_argnames=("radius",))
    run = jax.jit(icp, static_argnames="options")
    vb = jax.jit(icp_batch, static_argnames="options")
    hdr = (f"{'n':>7} {'method':>6} | {'cm3d':>7} {'build':>7} {'vmap':>8} {'loop':>8} {'speedup':>7} | "
           f"{'o3d_cpu':>7} | {'it':>3} {'err_cm3d':>8} {'err_o3d':>8} | {'compile s':>9}")
    print(hdr)
    print("-" * len(hdr))
    figures, err_diff = {}, []
    for n in sizes:
        k = f"{n // 1000}k"
        pairs = [make_pair(n, s) for s in range(batch)]
        src, tgt, T_gt = pairs[0]
        t0 = time.perf_counter()
        jax.block_until_ready(build(jnp.asarray(tgt), radius=R))
        c_build = time.perf_counter() - t0
        t_build, _ = best_of(lambda: build(jnp.asarray(tgt), radius=R), reps)
        idx = [build(jnp.asarray(t), radius=R) for _, t, _ in pairs]
        bidx = stack_indices(idx)
        srcs = jnp.asarray(np.stack([p[0] for p in pairs]))
        figures[f"gpu_build_{k}_ms"] = t_build * 1e3
        for method, short in (("point_to_point", "p2p"), ("point_to_plane", "p2l")):
            opts = ICPOptions(method=method, max_correspondence_distance=R, max_iterations=100)
            t0 = time.perf_counter()
            jax.block_until_ready(run(srcs[0], idx[0], options=opts))
            jax.block_until_ready(vb(srcs, bidx, options=opts))
            c_icp = time.perf_counter() - t0
            t_c, res = best_of(lambda: run(srcs[0], idx[0], options=opts), reps)
            t_v, rb = best_of(lambda: vb(srcs, bidx, options=opts), reps)
            t_l, rl = best_of(lambda: [run(srcs[b], idx[b], options=opts) for b in range(batch)], reps)
            same = _batch_equals_loop(rb, rl)
            e_c, t_o, e_o = err(res.transform, T_gt), float("nan"), float("nan")
            if have_o3d:
                pt = _o3d_target(tgt)
                ps = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src.astype(np.float64)))
                est = reg.TransformationEstimationPointToPlane() if short == "p2l" else reg.TransformationEstimationPointToPoint()
                t_o, ro = best_of(lambda: reg.registration_icp(ps, pt, R, np.eye(4), est,
                                                               reg.ICPConvergenceCriteria(max_iteration=100)).transformation, reps)
                e_o = err(ro, T_gt)
                err_diff.append(e_c - e_o)
                figures[f"gpu_time_ratio_{short}_{k}"] = t_c / t_o
            print(f"{n:>7} {short:>6} | {t_c*1e3:7.1f} {t_build*1e3:7.1f} {t_v*1e3:8.1f} {t_l*1e3:8.1f} {t_l/t_v:7.2f} | "
                  f"{t_o*1e3:7.1f} | {int(res.iterations):>3} {e_c:8.1e} {e_o:8.1e} | {c_icp + c_build:9.1f}"
                  f"   vmap == loop: {same}")
            figures[f"gpu_{short}_{k}_ms"] = t_c * 1e3
            figures[f"gpu_err_cm3d_{short}_{k}"] = e_c
            figures[f"gpu_batch{batch}_vmap_ms_{short}_{k}"] = t_v * 1e3
            figures[f"gpu_batch{batch}_loop_ms_{short}_{k}"] = t_l * 1e3
            figures[f"gpu_batch{batch}_equals_loop_{short}_{k}"] = bool(same)
            if short == "p2l":
                figures[f"gpu_batch{batch}_speedup_{k}"] = t_l / t_v
                if n == sizes[0]:
                    figures[f"gpu_batch{batch}_speedup"] = t_l / t_v
    if err_diff:
        figures["gpu_err_diff_max"] = float(max(err_diff))
    print("\nheadline:")
    for key, v in figures.items():
        if key.endswith("_ms") and "batch" not in key or "speedup" in key:
            print(f"  {key:36s} {v:.3f}")
    return figures


GLOBAL_PAIRS = ((0, 0, 1), (0, 0, 2), (2, 1, 2), (3, 0, 1), (4, 1, 2), (5, 0, 1), (5, 0, 2), (5, 1, 2))


def _pose_err(T, G):
    """(rotation error deg, translation error) of a similarity T against G (inf if degenerate)."""
    T = np.asarray(T, np.float64)
    s, sg = np.cbrt(np.linalg.det(T[:3, :3])), np.cbrt(np.linalg.det(G[:3, :3]))
    if not (np.all(np.isfinite(T)) and s > 1e-6):
        return np.inf, np.inf
    dR = np.rad2deg(Rotation.from_matrix(T[:3, :3] / s @ (G[:3, :3] / sg).T).magnitude())
    return float(dR), float(np.linalg.norm(T[:3, 3] - G[:3, 3]))


def _o3d_global(src, tgt, voxel, orient, with_scaling):
    """Open3D's FPFH + RANSAC pipeline (its tutorial settings), then point-to-plane ICP."""
    def prep(p):
        d = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p.astype(np.float64))).voxel_down_sample(voxel)
        d.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        if orient:
            d.orient_normals_towards_camera_location(np.asarray(d.points).mean(0))
        return d, reg.compute_fpfh_feature(d, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))

    (ds, fs), (dt, ft) = prep(src), prep(tgt)
    r = reg.registration_ransac_based_on_feature_matching(
        ds, dt, fs, ft, True, 1.5 * voxel, reg.TransformationEstimationPointToPoint(with_scaling), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
        reg.RANSACConvergenceCriteria(100000, 0.999))
    ps = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src[:3000].astype(np.float64)))
    pt = _o3d_target(tgt[:3000])
    est = reg.TransformationEstimationPointToPoint(True) if with_scaling else reg.TransformationEstimationPointToPlane()
    return reg.registration_icp(ps, pt, R, r.transformation, est, reg.ICPConvergenceCriteria(max_iteration=100)).transformation


def bench_global(trials):
    """Success of global registration + ICP on partial-overlap synthetic visits, cm3d vs Open3D."""
    from cm3d.solvers.align import GlobalOptions, global_registration, target_voxel_size

    world = synthetic.WorldConfig(height=48, width=64, fps=5.0)
    L, N = 16384, 3000
    cache = {}

    def visit(scene, v):
        if (scene, v) not in cache:
            p = synthetic.generate(scene, v, 20, "none", world).gt.static_points(1)
            cache[scene, v] = p[np.random.default_rng(v).permutation(len(p))[:L]].astype(np.float32)
        return cache[scene, v]

    g = jax.jit(global_registration, static_argnames="options")
    build = jax.jit(build_target_index, static_argnames=("radius",))
    run = jax.jit(icp, static_argnames="options")
    rng = np.random.default_rng(0)
    print(f"\nglobal registration + ICP, {len(GLOBAL_PAIRS)} synthetic visit pairs x {trials} poses (> 90 deg); "
          f"success = within 1 deg and 5 cm")
    hdr = (f"{'pair':>5} {'mode':>5} | {'cm3d':>14} {'o3d':>14} {'o3d+orient':>14} | {'t_cm3d':>6} {'t_o3d':>6}"
           f"   (deg / m errors; s)")
    print(hdr)
    print("-" * len(hdr))
    figures, wins = {}, {}
    times = {"se3": [], "sim3": []}
    for mode, opts in (("se3", GlobalOptions()), ("sim3", GlobalOptions.sim3())):
        icp_opts = ICPOptions(max_correspondence_distance=R, max_iterations=100, with_scale=mode == "sim3")
        for scene, a, b in GLOBAL_PAIRS:
            for _ in range(trials):
                G = np.eye(4)
                yaw = rng.uniform(95, 180) * rng.choice([-1, 1])
                G[:3, :3] = Rotation.from_euler("zyx", [yaw, *rng.uniform(-10, 10, 2)], degrees=True).as_matrix()
                G[:3, 3] = rng.uniform(-2, 2, 3)
                if mode == "sim3":
                    G[:3, :3] *= rng.uniform(0.65, 1.5)
                src = ((visit(scene, a) - G[:3, 3]) @ np.linalg.inv(G[:3, :3]).T).astype(np.float32)
                tgt = visit(scene, b)
                args = (jnp.asarray(src), jnp.asarray(tgt), jnp.ones(L, bool), jnp.ones(L, bool), jax.random.key(0))
                jax.block_until_ready(g(*args, options=opts))  # compile once per mode
                t0 = time.perf_counter()
                res = g(*args, options=opts)
                fine = run(jnp.asarray(src[:N]), build(jnp.asarray(tgt[:N]), jnp.ones(N, bool), radius=R),
                           res.transform, jnp.ones(N, bool), options=icp_opts)
                jax.block_until_ready(fine)
                times[mode].append(time.perf_counter() - t0)
                voxel = float(target_voxel_size(tgt, None, opts))
                t0 = time.perf_counter()
                o_plain = _o3d_global(src, tgt, voxel, False, mode == "sim3")
                t_o = time.perf_counter() - t0
                o_orient = _o3d_global(src, tgt, voxel, True, mode == "sim3")
                row = []
                for name, T in (("cm3d", fine.transform), ("o3d", o_plain), ("o3d_orient", o_orient)):
                    dR, dt = _pose_err(T, G)
                    ok = dR < 1.0 and dt < 0.05
                    wins[mode, name] = wins.get((mode, name), 0) + ok
                    row.append(f"{'ok' if ok else '--'} {min(dR, 999):5.1f}/{min(dt, 99):5.2f}")
                print(f"{scene}/{a}/{b} {mode:>5} | {row[0]:>14} {row[1]:>14} {row[2]:>14} | "
                      f"{times[mode][-1]:6.2f} {t_o:6.2f}")
        total = len(GLOBAL_PAIRS) * trials
        print(f"  {mode}: success cm3d {wins[mode, 'cm3d']}/{total}, Open3D {wins[mode, 'o3d']}/{total}, "
              f"Open3D with oriented normals {wins[mode, 'o3d_orient']}/{total}; cm3d median "
              f"{np.median(times[mode]):.2f} s per registration (compiled)")
        for name in ("cm3d", "o3d", "o3d_orient"):
            figures[f"global_success_{mode}_{name}"] = wins[mode, name] / total
        figures[f"global_time_{mode}_s"] = float(np.median(times[mode]))
    return figures


def _o3d_target(tgt):
    """Open3D target cloud with its normals (16 nearest, as cm3d's index)."""
    pt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt.astype(np.float64)))
    pt.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(16))
    return pt


if __name__ == "__main__":
    main()
