"""One consistent trajectory from the windows (host side around a compiled chain solve, issue 26).

Each window refines its poses against its own tracks and hands its last pose to the next window as
the anchor, so the refined trajectory is a chain of window-local motions: right inside a window,
but nothing ties it to the prior beyond the first frame, and the windows' small errors add up over
a long sequence. :func:`global_refine` solves one pose graph over every frame instead:

* a prior factor per frame at its prior pose (the VGGT-like input: jitter and drift, no chaining);
* a motion factor per consecutive frame pair at the window-refined relative pose (every pair
  belongs to exactly one window: a window's anchor is the previous window's last frame);
* noise levels (translation / rotation, prior and motion) by robust variance component estimation
  (median of ``r² / (1 − h)`` against χ²₁'s median, ``h`` the leverage), so nothing is tuned to a
  data set's units;
* the graph runs only when the windows disagree with the priors beyond chance
  (:func:`chain_consistency`): the chain is placed on the priors by one Sim(3); each window's mean
  position residual, whitened by the priors' frame-to-frame jitter, is a χ² statistic. Where the
  windows agree (the usual case over a few windows: the chain is then more accurate than the priors
  can tell), the priors could only pull their own jitter into the result, so the chain is kept;
* a window whose refined shape is further from the priors than the priors' own noise explains
  loses its motion factors: there the result is the prior. The statistic (:func:`window_residuals`:
  the window's poses rigidly placed on its frames' priors) is the median whitened squared residual
  of its frames, a robust variance of the window's misfit; its unit is the median window's (at
  least χ²₆'s median when the priors' sigma is right; χ²₆'s median alone with fewer than 3
  windows), since the priors' noise is not white within a window (drift). The typical window's
  misfit is mostly the priors' noise, so a window above ``max_misfit_ratio`` = 2 units is one whose
  own error is larger than the priors' there: the prior alone is the better estimate. Single
  motion factors above ``χ²₆(outlier_quantile)``, in the solve or against the priors' own relative
  motion (independent of the solve, which spreads a gross error over its neighbours), are dropped
  too, and split their window: each run of frames still joined by motion factors is judged on its
  own, so one broken link (a jump in the video) does not condemn the rest of its window.

The chain is block-tridiagonal (:func:`cm3d.solvers.chain_pose_graph.solve_chain`, padded to a
multiple of ``pad_frames`` frames: one compiled program for many lengths). Whether the result is
kept is decided by evidence the graph never saw: :func:`cm3d.pipeline.run` compares the images
under the prior and the final poses (:func:`cm3d.pipeline.photometric.check_refinement`).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from cm3d.long_video.frame_graph import _pad
from cm3d.ops import robust, se3
from cm3d.solvers import factors
from cm3d.solvers.chain_pose_graph import solve_chain
from cm3d.solvers.factors import FactorGraph, MotionFactors, PriorFactors, ProjectionFactors

_CHI2_6_MEDIAN = 5.348120627447122  # median of χ²_6
_MAD_EFFICIENCY = 0.37  # the MAD's asymptotic efficiency as a scale estimate at the normal (0.367)


@dataclasses.dataclass(frozen=True)
class GlobalGraphConfig:
    """Options of :func:`global_refine`: ``enabled``; consistency_p: the graph runs when the chained
    windows' agreement with the priors has a p-value below this (:func:`chain_consistency`; 1: always);
    vce_iterations: variance-estimation rounds;
    outlier_quantile: single motion factors above ``χ²₆(q)`` are dropped; max_misfit_ratio: a window
    (or a run of it) whose misfit to the priors is above this many typical windows' keeps the prior
    (module docstring: 2 is where its own error variance passes the priors');
    iterations: LM steps per solve; pad_frames: the graph is padded to a multiple of this many frames."""

    enabled: bool = True
    consistency_p: float = 0.01
    vce_iterations: int = 4
    outlier_quantile: float = 0.999
    max_misfit_ratio: float = 2.0
    iterations: int = 8
    pad_frames: int = 64

    def __post_init__(self):
        if self.vce_iterations < 1 or self.iterations < 1 or self.pad_frames < 1:
            raise ValueError(f"GlobalGraphConfig: vce_iterations, iterations, pad_frames >= 1 required, got {self}")
        if not (0 < self.outlier_quantile < 1 and 0 < self.consistency_p <= 1 and self.max_misfit_ratio > 1):
            raise ValueError(f"GlobalGraphConfig: quantiles in (0, 1) and max_misfit_ratio > 1 required, got {self}")


def chain_graph(prior, measured, sigma_prior, sigma_motion, weight) -> FactorGraph:
    """The landmark-free chain: a prior per frame at ``prior`` (N, 4, 4), a motion factor
    ``(i, i + 1)`` per row of ``measured`` (N − 1, 4, 4) with ``weight`` (N − 1,); sigmas (6,)."""
    P = jnp.asarray(prior)
    N = P.shape[0]
    f = lambda a: jnp.asarray(a, P.dtype)  # noqa: E731
    Q = N - 1
    return FactorGraph(
        intrinsics=jnp.tile(jnp.eye(3, dtype=P.dtype), (N, 1, 1)),
        projection=ProjectionFactors(pose_idx=jnp.zeros(1, jnp.int32), point_idx=jnp.zeros(1, jnp.int32),
                                     z=jnp.zeros((1, 2), P.dtype), sigma=jnp.ones(1, P.dtype),
                                     weight=jnp.zeros(1, P.dtype), memory=jnp.zeros(1, bool)),
        prior=PriorFactors(pose_idx=jnp.arange(N, dtype=jnp.int32), target=P,
                           sigma=jnp.broadcast_to(f(sigma_prior), (N, 6)), weight=jnp.ones(N, P.dtype)),
        motion=MotionFactors(idx_a=jnp.arange(Q, dtype=jnp.int32), idx_b=jnp.arange(1, Q + 1, dtype=jnp.int32),
                             measured=f(measured), sigma=jnp.broadcast_to(f(sigma_motion), (Q, 6)), weight=f(weight)),
        huber_k=jnp.asarray(np.inf, P.dtype), memory_alpha=jnp.asarray(0.5, P.dtype), pose_fixed=jnp.zeros(N, bool))


def pair_windows(num_frames: int, windows) -> np.ndarray:
    """(S − 1,) the window of each consecutive pair ``(i, i + 1)`` (-1: no window): the window whose
    frames ``(first, last)`` hold ``first < i + 1 <= last``."""
    out = -np.ones(max(num_frames - 1, 0), np.int64)
    for k, (a, b) in enumerate(windows):
        out[max(a, 0):max(min(b, num_frames - 1), 0)] = k
    return out


def _linked_runs(link, a: int, b: int):
    """Maximal runs ``(first, last)`` of frames in ``[a, b]`` joined by consecutive ``link`` (S − 1,)
    pairs (pair ``i`` joins frames ``i`` and ``i + 1``), two frames or more."""
    out, i = [], a
    while i < b:
        if not link[i]:
            i += 1
            continue
        j = i
        while j < b and link[j]:
            j += 1
        out.append((i, j))
        i = j
    return out


@jax.jit
def window_residuals(prior, poses, valid, sigma):
    """How far one window's refined shape is from the prior's over the same frames: the rigid motion
    ``T`` that best places the window's poses (n, 4, 4) on the priors (Gauss-Newton on
    ``Σ |log(P_i^{-1} T X_i) / σ|²`` over ``valid`` (n,) frames, from the first frame's), then each
    frame's whitened squared residual (n,). Independent of the global solution."""
    Xi = se3.inverse(poses)
    T = prior[0] @ Xi[0]
    for _ in range(4):
        r = se3.log(se3.inverse(prior) @ T @ poses) / sigma
        A = factors.adjoint(Xi) / sigma[:, None]  # d r / d δ for T exp(δ), first order
        H = jnp.einsum("n,nki,nkj->ij", valid, A, A)
        g = jnp.einsum("n,nki,nk->i", valid, A, r)
        d = -jnp.linalg.solve(H + 1e-9 * jnp.eye(6, dtype=H.dtype), g)
        T = T @ se3.exp(jnp.where(jnp.isfinite(d), d, 0.0))
    r = se3.log(se3.inverse(prior) @ T @ poses) / sigma
    return jnp.sum(r * r, -1)


def chain_consistency(prior, poses, windows) -> dict:
    """Do the chained windows ``poses`` (S, 4, 4) agree with the ``prior`` (S, 4, 4) beyond chance?

    The chain is placed on the priors by the Sim(3) of their camera centres (Umeyama); ``r_i`` the
    residual centre per frame. The priors' per-frame jitter ``σ`` (per axis) is the robust spread of
    ``r_{i+1} − r_i`` over ``√2`` (differences cancel slow drift and the windows' offsets); each window
    (its frames after the shared anchor, ``n`` of them) contributes ``n |mean r / σ|²``, χ²₃ when the
    chain is right up to the placement. ``σ`` is itself estimated, from few differences on a short
    sequence, so the statistic over its dof is tested as F(dof, ν) rather than χ²(dof) / dof: ``ν`` the
    effective dof of ``σ²``, the MAD's efficiency at the normal (0.37) times the independent
    differences (3 axes, half the ``S − 1`` differences: neighbours share a frame). Returns ``statistic``,
    ``dof`` (3 per window less 3 for the placement, at least 1), ``nu``, ``p`` (F survival) and
    ``sigma`` (3,).

    A prior's slow drift (VGGT's, or the random walk of :func:`cm3d.data.priors.pose_errors`) offsets
    whole windows too, so over many windows the test also rejects an exact chain when the priors
    drift (seeded orbits of 100 frames, 5 windows, half the error as drift: p < 0.01 in 4 of 8); the
    graph then follows the priors' drift, and its result stays below the priors' ATE."""
    from scipy.special import fdtrc  # F survival (scipy.stats takes ~1 s to import)

    from cm3d.solvers.umeyama import umeyama

    P, X = np.asarray(prior, np.float64), np.asarray(poses, np.float64)
    s, R, t = umeyama(X[:, :3, 3], P[:, :3, 3])  # NumPy, float64: no JAX dispatch on the host
    r = P[:, :3, 3] - (s * X[:, :3, 3] @ R.T + t)
    dz = np.diff(r, axis=0)
    sig = np.maximum(1.4826 * np.median(np.abs(dz - np.median(dz, 0)), 0) / np.sqrt(2.0), 1e-12)
    stat, dof = 0.0, 0
    for k, (a, b) in enumerate(windows):
        f = np.arange(a if k == 0 else a + 1, min(b, len(P) - 1) + 1)
        if f.size:
            stat += f.size * float(np.sum((r[f].mean(0) / sig) ** 2))
            dof += 3
    dof = max(dof - 3, 1)
    nu = max(_MAD_EFFICIENCY * 3 * (len(P) - 1) / 2, 1.0)
    return {"statistic": stat, "dof": dof, "nu": nu, "p": float(fdtrc(dof, nu, stat / dof)), "sigma": sig}


def global_refine(prior, poses, windows, cfg: GlobalGraphConfig = GlobalGraphConfig()):
    """The global pose graph over a sequence (module docstring). prior, poses (S, 4, 4) cam_to_world
    (the input and the windows' chained result); windows: ``(first, last)`` frames per window.
    Returns (poses (S, 4, 4), facts dict: ``ran``, sigmas, motion factors used, windows kept /
    dropped (``window_kept`` per window, ``window_misfit_ratio``: its worst run's misfit in typical
    windows'), costs)."""
    P0 = np.asarray(prior, np.float64)
    X = np.asarray(poses, np.float64)
    if P0.shape != X.shape or P0.ndim != 3 or P0.shape[1:] != (4, 4):
        raise ValueError(f"global_refine: prior and poses must both be (S, 4, 4), got {P0.shape}, {X.shape}")
    S = P0.shape[0]
    facts = {"ran": False, "windows": len(windows)}
    if not cfg.enabled or S < 3 or not np.all(np.isfinite(X)) or not np.all(np.isfinite(P0)):
        return X.copy(), {**facts, "reason": "disabled" if not cfg.enabled else "fewer than 3 frames or non-finite poses"}
    cons = chain_consistency(P0, X, windows)
    facts.update({"consistency_statistic": round(cons["statistic"], 2), "consistency_dof": cons["dof"],
                  "consistency_nu": round(cons["nu"], 1), "consistency_p": cons["p"]})
    if cons["p"] >= cfg.consistency_p and cfg.consistency_p < 1:
        return X.copy(), {**facts, "reason": f"the windows agree with the priors (p = {cons['p']:.3g})"}
    meas = np.linalg.inv(X[:-1]) @ X[1:]
    local = np.asarray(se3.log(jnp.asarray(np.linalg.inv(meas) @ np.linalg.inv(P0[:-1]) @ P0[1:])), np.float64)
    N = -(-S // cfg.pad_frames) * cfg.pad_frames
    Pp, Mp = _pad(P0, N, "last"), _pad(meas, N - 1, "last")
    real = np.arange(N - 1) < S - 1
    w = real.astype(np.float64)
    # start: centre noise from the prior's own step length, 1 degree; the motion 10x tighter
    step = np.linalg.norm(np.diff(P0[:, :3, 3], axis=0), axis=1)
    scale = float(np.median(step)) if np.any(step > 0) else 1.0
    sp = np.array([max(scale, 1e-9)] * 3 + [np.deg2rad(1.0)] * 3)
    sm = sp / 10.0
    lim1 = float(robust.chi2_quantile(cfg.outlier_quantile, 6))
    nwin = len(windows)
    dropped = np.zeros(nwin, bool)
    misfit = np.zeros(nwin)
    frame_real = np.arange(N) < S
    for rnd in range(cfg.vce_iterations + 1):
        sol = solve_chain(chain_graph(Pp, Mp, sp, sm, w), jnp.asarray(Pp), iterations=cfg.iterations)
        if rnd == cfg.vce_iterations:
            break
        rp, hp, rm, hm = (np.asarray(x, np.float64) for x in (sol.e_prior, sol.h_prior, sol.e_motion, sol.h_motion))
        sp_new = robust.variance_components(rp, hp, frame_real, sp)
        sm_new = robust.variance_components(rm, hm, w > 0, sm)
        e2 = np.sum((rm * sm / sm_new) ** 2, 1)  # whitened by the updated sigmas
        sp, sm = sp_new, sm_new
        # usable motion factors: within χ²₆ in the solve and against the priors' own relative motion
        # ``|log(M_i⁻¹ P_i⁻¹ P_{i+1})|`` whitened by ``√(2 σ_p² + σ_m²)`` (independent of the solve,
        # which spreads a gross error over its neighbours). A dropped factor (e.g. a jump in the
        # video) splits its window; each run of linked frames whose shape the priors reject keeps
        # the prior.
        link = real & (w > 0) & (e2 <= lim1) & (_pad(np.sum((local / np.sqrt(2 * sp ** 2 + sm ** 2)) ** 2, 1),
                                                     N - 1, "last") <= lim1)
        runs = [(k, a, b) for k, (a0, b0) in enumerate(windows) for a, b in _linked_runs(link, a0, min(b0, S - 1))]
        mis = np.zeros(len(runs))
        for m, (k, a, b) in enumerate(runs):
            n = b - a + 1
            pad = -(-n // 8) * 8
            sel = np.minimum(np.arange(a, a + pad), S - 1)
            e = window_residuals(jnp.asarray(P0[sel]), jnp.asarray(X[sel]),
                                 jnp.asarray((np.arange(pad) < n).astype(P0.dtype)), jnp.asarray(sp))
            mis[m] = float(np.median(np.asarray(e)[:n]))
        # the typical run sets the unit (the priors' noise is not white within a window: drift)
        unit = max(_CHI2_6_MEDIAN, float(np.median(mis))) if len(runs) >= 3 else _CHI2_6_MEDIAN
        misfit = np.zeros(nwin)
        for m, (k, a, b) in enumerate(runs):
            misfit[k] = max(misfit[k], mis[m] / unit)
            if mis[m] > cfg.max_misfit_ratio * unit:
                link[a:b] = False
                dropped[k] = True
        w = np.where(link, w, 0.0)
    out = np.asarray(sol.poses, np.float64)[:S]
    if not np.all(np.isfinite(out)):
        return X.copy(), {**facts, "reason": "non-finite solution"}
    facts.update({"ran": True, "sigma_prior_trans": float(sp[0]), "sigma_prior_rot_deg": float(np.rad2deg(sp[3])),
                  "sigma_motion_trans": float(sm[0]), "sigma_motion_rot_deg": float(np.rad2deg(sm[3])),
                  "motion_factors": S - 1, "motion_factors_used": int(np.sum(w[: S - 1] > 0)),
                  "windows_dropped": int(dropped.sum()), "window_kept": [bool(not d) for d in dropped],
                  "window_misfit_ratio": [round(float(m), 2) for m in misfit],
                  "cost_initial": float(sol.cost_initial), "cost": float(sol.cost)})
    return out, facts
