"""Speed of the motion-cue kernels against their references, measured in the same run.

    .venv/bin/python experiments/bench_motion.py [--repeats 5] [--quick] [--json PATH]

On OpenCV DIS flow fields of the synthetic world at 384x512 (scene 0, visit 1, 4 movers; 96x128
with ``--quick``):

* GMM: ``cm3d.ops.gmm.fit_gmm`` (K=3, 50 EM iterations, tol=0, jitted, compiled beforehand) vs
  ``sklearn.mixture.GaussianMixture(3, covariance_type="full", max_iter=50, tol=0)`` started from
  the same initial parameters (ours: seeded k-means++): time ratio and adjusted Rand index of the
  labellings (also against scikit-learn with its own default k-means initialisation).
* Otsu: ``cm3d.ops.otsu.threshold_otsu`` vs ``skimage.filters.threshold_otsu`` on the flow
  magnitude (256 bins): equal thresholds and time ratio JAX / scikit-image.
* Batched: ``jit(vmap(f))`` over 8 frames vs a Python loop of ``jit(f)`` on single frames, for the
  GMM and for the whole ``motion_cues``.

Times are the best of ``--repeats`` runs. JSON keys: gmm_speedup_vs_sklearn, gmm_ari,
gmm_ari_sklearn_own_init, otsu_time_ratio, otsu_equal, vmap_speedup (GMM), vmap_speedup_cues.
"""

from __future__ import annotations

import argparse
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from cm3d import motion
from cm3d.data import synthetic
from cm3d.outputs import write_json
from cm3d.ops import flow as flow_ops
from cm3d.ops import gmm, keypoints, otsu


def best_time(f, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(f())
        ts.append(time.perf_counter() - t)
    return min(ts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="smoke run: 96x128 flows, 3 frames tiled to 8, one repeat")
    ap.add_argument("--json", default=None, metavar="PATH")
    args = ap.parse_args()
    from sklearn.metrics import adjusted_rand_score
    from sklearn.mixture import GaussianMixture
    from skimage.filters import threshold_otsu

    reps = 1 if args.quick else args.repeats
    wcfg = synthetic.WorldConfig(num_moving=4)
    if args.quick:
        wcfg = synthetic.WorldConfig(height=96, width=128, num_moving=4)
    n_render = 3 if args.quick else 9
    seq = synthetic.generate(scene_seed=0, visit=1, num_frames=n_render, level="moderate", cfg=wcfg)
    flows = flow_ops.sequence_flow(seq.images)
    H, W = flows.shape[1:3]
    idx = np.arange(8) % len(flows)
    flows8 = flows[idx]
    print(f"flow fields: {H}x{W} ({H * W} vectors), OpenCV DIS; best of {reps}; jax {jax.__version__} on "
          f"{jax.devices()[0].platform}")
    figures = {}

    # --- GMM ---------------------------------------------------------------------------------
    cfg = gmm.GMMConfig(num_components=3, max_iters=50, tol=0.0)
    x = flows[0].reshape(-1, 2)
    fit = jax.jit(gmm.fit_gmm, static_argnums=1)
    res = jax.block_until_ready(fit(x, cfg))
    t_jax = best_time(lambda: fit(x, cfg), max(reps, 3))
    w0, m0, c0 = (np.asarray(a, np.float64) for a in gmm.initial_parameters(x, cfg))
    x64 = x.astype(np.float64)

    def sk_fit():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # tol=0 never "converges"
            g = GaussianMixture(3, covariance_type="full", max_iter=50, tol=0.0, init_params="random_from_data",
                                weights_init=w0 / w0.sum(), means_init=m0, precisions_init=np.linalg.inv(c0),
                                random_state=0)
            return g.fit(x64).predict(x64)

    labels_sk = sk_fit()
    t_sk = best_time(sk_fit, reps)
    ari = adjusted_rand_score(labels_sk, np.asarray(res.labels))
    ari_own = float("nan")
    if not args.quick:  # scikit-learn's default k-means initialisation: a different start
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            own = GaussianMixture(3, covariance_type="full", max_iter=50, tol=0.0, random_state=0).fit(x64).predict(x64)
        ari_own = adjusted_rand_score(own, np.asarray(res.labels))
    figures.update(gmm_speedup_vs_sklearn=t_sk / t_jax, gmm_ari=ari,
                   gmm_ari_sklearn_own_init=None if args.quick else ari_own,
                   gmm_ms_jax=1e3 * t_jax, gmm_ms_sklearn=1e3 * t_sk)

    # --- Otsu --------------------------------------------------------------------------------
    mag = np.linalg.norm(flows[0], axis=-1).astype(np.float32)
    th = jax.jit(otsu.threshold_otsu, static_argnums=1)
    t_j = float(th(mag, 256))
    t_s = float(threshold_otsu(mag, nbins=256))
    equal = all(float(th(np.linalg.norm(f, axis=-1).astype(np.float32), 256))
                == float(threshold_otsu(np.linalg.norm(f, axis=-1).astype(np.float32), nbins=256)) for f in flows8)
    o_reps = 10 * max(reps, 3)
    to_j = best_time(lambda: th(mag, 256), o_reps)
    to_s = best_time(lambda: threshold_otsu(mag, nbins=256), o_reps)
    figures.update(otsu_time_ratio=to_j / to_s, otsu_equal=bool(equal and t_j == t_s),
                   otsu_ms_jax=1e3 * to_j, otsu_ms_skimage=1e3 * to_s)

    # --- batched ----------------------------------------------------------------------------
    X8 = jnp.asarray(flows8.reshape(8, -1, 2))
    fit8 = jax.jit(jax.vmap(gmm.fit_gmm, in_axes=(0, None)), static_argnums=1)
    jax.block_until_ready(fit8(X8, cfg))
    t_vmap = best_time(lambda: fit8(X8, cfg), reps)
    t_loop = best_time(lambda: [fit(X8[i], cfg) for i in range(8)], reps)
    figures.update(vmap_speedup=t_loop / t_vmap)

    priors = motion.FramePrior.from_sequence(seq)
    a = jax.tree.map(lambda v: v[idx], priors)
    b = jax.tree.map(lambda v: v[idx + 1], priors)
    m = keypoints.sequence_matches(seq.images)
    m8 = jax.tree.map(lambda v: jnp.asarray(v[idx]), m)
    mcfg = motion.MotionConfig()
    cues8 = jax.jit(jax.vmap(motion.motion_cues, in_axes=(0, 0, 0, 0, None)), static_argnums=4)
    jf8 = jnp.asarray(flows8)
    jax.block_until_ready(cues8(a, b, jf8, m8, mcfg))
    sl = [jax.tree.map(lambda v: v[i], (a, b, jf8, m8)) for i in range(8)]
    jax.block_until_ready(motion.motion_cues_jit(*sl[0], mcfg))
    t_cv = best_time(lambda: cues8(a, b, jf8, m8, mcfg), reps)
    t_cl = best_time(lambda: [motion.motion_cues_jit(*s, mcfg) for s in sl], reps)
    figures.update(vmap_speedup_cues=t_cl / t_cv, cues_ms_per_frame_vmap=1e3 * t_cv / 8)

    rows = [
        ("GMM K=3, 50 EM its: JAX", f"{1e3 * t_jax:9.1f} ms", ""),
        ("  sklearn GaussianMixture", f"{1e3 * t_sk:9.1f} ms", f"speedup {t_sk / t_jax:6.1f}x   ARI {ari:.4f} "
                                                               f"(vs sklearn's own init: {ari_own:.4f})"),
        ("Otsu 256 bins: JAX", f"{1e3 * to_j:9.3f} ms", ""),
        ("  skimage threshold_otsu", f"{1e3 * to_s:9.3f} ms", f"ratio JAX/skimage {to_j / to_s:5.2f}   "
                                                                f"equal: {figures['otsu_equal']}"),
        ("GMM x8 frames: vmap", f"{1e3 * t_vmap:9.1f} ms", ""),
        ("  Python loop of jit", f"{1e3 * t_loop:9.1f} ms", f"vmap speedup {t_loop / t_vmap:5.2f}x"),
        ("motion_cues x8: vmap", f"{1e3 * t_cv:9.1f} ms", ""),
        ("  Python loop of jit", f"{1e3 * t_cl:9.1f} ms", f"vmap speedup {t_cl / t_cv:5.2f}x"),
    ]
    print()
    for name, t, note in rows:
        print(f"{name:28s} {t:>13s}   {note}")
    if args.json:
        write_json(args.json, figures)


if __name__ == "__main__":
    main()
