"""The acceptance tests of the verified candidate:

* the **chance test** (:func:`chance_test`, an a-contrario bound that means the same on any data):
  the recovered pose's keypoint inliers against the count expected by chance at that match count,
  measured on the query's own matches with their map ends shuffled; accept when the number of
  false alarms (tests x Poisson tail) is below ``10 ** cfg.max_log_nfa``;
* the **acceptance model**: the candidate's weak signals as one feature vector
  (:data:`~cm3d.memory.config.ACCEPTANCE_FEATURES`) and their linear score (a logistic regression
  fitted on the tuning split of ``experiments/memory_recall.py``)."""

from __future__ import annotations

import jax.numpy as jnp
from jax.scipy.special import gammainc

from cm3d.memory.bank import MemoryBank
from cm3d.memory.config import MemoryConfig
from cm3d.memory.entry import MapEntry
from cm3d.memory.recall import Recall
from cm3d.memory.verify import Verification
from cm3d.ops import sim3

SHUFFLES = 8  # cyclic shifts of the matches' map ends that measure the chance inlier count
MINIMAL_SAMPLE = 3  # matches a hypothesis fits exactly (inliers by construction, not evidence)


def chance_test(src, dst, valid, T, threshold, tests, shuffles: int = SHUFFLES):
    """The a-contrario test of a pose ``T`` (4, 4) fitted to the matches ``src[i] -> dst[i]`` (N, 3)
    (where ``valid``): (inliers k within ``threshold``, chance inliers λ, log10 NFA).

    λ is the inlier count of the same pose on the same matches with their map ends shuffled (``shuffles``
    cyclic shifts among the valid matches; their mean, plus half an inlier so that a clean background
    is not taken for an impossible one): what chance gives at this match count, this map's keypoint
    density and this threshold. ``NFA = tests · P(Poisson(λ) >= k - 3)`` (3: the minimal sample, inliers
    of any hypothesis; ``tests``: the hypotheses tried). NFA < 1 (log10 < 0): fewer than one pose this
    good expected by chance among all tried. Pure, fixed shape."""
    src, dst = jnp.asarray(src, jnp.float32), jnp.asarray(dst, jnp.float32)
    valid = jnp.asarray(valid, bool)
    order = jnp.argsort(~valid, stable=True)
    src, dst, valid = src[order], dst[order], valid[order]
    n = jnp.sum(valid)
    T = jnp.asarray(T, jnp.float32)
    pred = sim3.apply(T, src)
    thr2 = jnp.float32(threshold) ** 2
    k = jnp.sum(valid & (jnp.sum((pred - dst) ** 2, -1) < thr2))
    i = jnp.arange(src.shape[0])
    nn = jnp.maximum(n, 1)

    def shifted(j):
        off = 1 + (j * jnp.maximum(n - 1, 0)) // shuffles  # in [1, n - 1]: no match keeps its own end
        d = dst[(i + off) % nn]
        return jnp.sum(valid & (jnp.sum((pred - d) ** 2, -1) < thr2))

    chance = sum(shifted(j) for j in range(shuffles))
    lam = (chance.astype(jnp.float32) + 0.5) / shuffles
    excess = jnp.maximum(k - MINIMAL_SAMPLE, 0).astype(jnp.float32)
    tail = jnp.where(excess > 0, gammainc(jnp.maximum(excess, 1.0), lam), 1.0)  # P(Poisson(lam) >= excess)
    log_nfa = jnp.log10(jnp.float32(tests)) + jnp.log10(jnp.maximum(tail, 1e-30))
    ok = jnp.all(jnp.isfinite(T))
    return k.astype(jnp.int32), lam, jnp.where(ok, log_nfa, jnp.float32(jnp.log10(tests)))


def placement_error(src, dst, valid, T, threshold):
    """How precisely the keypoint inliers of a pose ``T`` fix it: ``σ / (S √(2k))`` with ``k`` the
    matches ``src[i] -> dst[i]`` (where ``valid``) within ``threshold`` under ``T``, ``S`` the RMS distance
    of their map ends from their centroid and ``σ = threshold / 2`` the RMS of their 3D noise: to first
    order, the standard error of a similarity fitted to them in its rotation about each axis (radians)
    and in its log scale, for inliers spread evenly about their centroid. Dimensionless, so it means the
    same on any data; large when few inliers sit close together (they fix the place, not the orientation
    and scale). Pure, fixed shape (inf without inliers)."""
    src, dst = jnp.asarray(src, jnp.float32), jnp.asarray(dst, jnp.float32)
    pred = sim3.apply(jnp.asarray(T, jnp.float32), src)
    inl = jnp.asarray(valid, bool) & (jnp.sum((pred - dst) ** 2, -1) < jnp.float32(threshold) ** 2)
    k = jnp.sum(inl)
    w = inl.astype(jnp.float32)
    c = jnp.sum(dst * w[:, None], 0) / jnp.maximum(k, 1)
    spread = jnp.sqrt(jnp.sum(w * jnp.sum((dst - c) ** 2, -1)) / jnp.maximum(k, 1))
    err = 0.5 * jnp.float32(threshold) / (spread * jnp.sqrt(2.0 * k.astype(jnp.float32)))
    return jnp.where((k > 0) & (spread > 0) & jnp.all(jnp.isfinite(T)), err, jnp.inf)


def chance_tests(cfg: MemoryConfig) -> int:
    """Poses tried per query: every candidate's triangle and upright-pair hypotheses."""
    return cfg.top_k * (cfg.ransac_hypotheses + cfg.upright_hypotheses)


def acceptance_features(bank: MemoryBank, entry: MapEntry, r: Recall, candidate_inliers, b, inliers, screen,
                        ransac_scale, v: Verification):
    """The scores of the verified candidate ``r.candidates[b]`` as one vector, in the order of
    :data:`ACCEPTANCE_FEATURES`: the acceptance model's inputs (:func:`acceptance_score`).
    ``candidate_inliers`` (top_k,): each candidate's best keypoint inliers (-1: none); ``inliers`` (G,):
    the candidate's per generator (triangle, upright pairs); ``screen``: the chosen pose's screening
    overlap (share); ``ransac_scale``: its RANSAC scale; ``v``: its verification (ICP scores). Pure, fixed
    shape; 0 where not finite or without a candidate."""
    cand = r.candidates
    m = cand[b]
    mm = jnp.maximum(m, 0)
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    share = r.votes[mm] / jnp.maximum(jnp.sum(entry.kf_valid), 1)
    finite = lambda x: jnp.where(jnp.isfinite(x), x, 0.0)  # noqa: E731
    other = (jnp.arange(cand.shape[0]) != b) & (cand >= 0)
    margin = finite(r.candidate_scores[b]) - jnp.max(jnp.where(other, finite(r.candidate_scores), 0.0))
    sim = bank.cloud_desc[mm] @ jnp.asarray(entry.cloud_desc, jnp.float32)
    log1p = lambda n: jnp.log1p(jnp.maximum(f32(n), 0.0))  # noqa: E731
    runner = jnp.max(jnp.where(other, candidate_inliers, 0))
    vs = jnp.maximum(bank.voxel_size[mm], 1e-12)
    scale = jnp.maximum(v.scale, 1e-12)
    feats = jnp.stack([
        f32(share), f32(margin), f32(sim), log1p(v.matches), log1p(inliers[0]), log1p(inliers[-1]),
        log1p(v.keypoint_inliers),
        log1p(candidate_inliers[b]) - log1p(runner), f32(screen), log1p(v.inlier_count), f32(v.fitness),
        f32(v.inlier_rmse) / vs, f32(v.colour_agreement),
        jnp.minimum(jnp.abs(jnp.log(scale / jnp.maximum(ransac_scale, 1e-12))), 2.0),
        jnp.minimum(jnp.abs(jnp.log(scale)), 2.0)])
    present = (m >= 0) & bank.map_valid[mm]
    return jnp.where(present & jnp.isfinite(feats), feats, 0.0)


def acceptance_score(features, cfg: MemoryConfig):
    """The acceptance model's score of :func:`acceptance_features` (accept when >= 0): a dot product of
    the standardised features with ``cfg.accept_weights`` plus ``cfg.accept_bias``."""
    w = jnp.asarray(cfg.accept_weights, jnp.float32)
    mu = jnp.asarray(cfg.accept_mean, jnp.float32)
    sd = jnp.asarray(cfg.accept_scale, jnp.float32)
    return jnp.sum(w * (features - mu) / sd) + jnp.float32(cfg.accept_bias)


def hard_checks(bank, m, v: Verification, cfg: MemoryConfig):
    """A stored map, a finite transform, a scale in ``cfg.scale_range``."""
    return ((m >= 0) & bank.map_valid[jnp.maximum(m, 0)] & jnp.all(jnp.isfinite(v.transform))
            & (v.scale >= cfg.scale_range[0]) & (v.scale <= cfg.scale_range[1]))


def model_accepts(bank, m, v: Verification, score, cfg: MemoryConfig):
    """The acceptance model's decision: score >= 0 and the :func:`hard_checks`."""
    return hard_checks(bank, m, v, cfg) & (score >= 0)


def accepts(bank, m, v: Verification, score, log_nfa, place, cfg: MemoryConfig):
    """The final decision on the verified candidate ``m`` (what :func:`identify` reports as
    ``verification.accepted``), from its evidence alone, so a changed threshold needs no new
    verification: the acceptance model (``score``, :func:`acceptance_score`; None: ``v.accepted``,
    the verification's thresholds) and the chance test (``log_nfa`` below ``cfg.max_log_nfa``), or far
    beyond chance (below ``cfg.accept_log_nfa``) with the :func:`hard_checks` and a pose its inliers fix
    (``place``, :func:`placement_error`, at most ``cfg.alone_max_placement_error``); with ``"full"``
    verification also an overlap with the map (ICP fitness at least ``cfg.min_overlap``). Pure."""
    base = v.accepted if score is None else model_accepts(bank, m, v, score, cfg)
    alone = hard_checks(bank, m, v, cfg) & (log_nfa < cfg.accept_log_nfa) & (place <= cfg.alone_max_placement_error)
    accepted = (base & (log_nfa < cfg.max_log_nfa)) | alone
    if cfg.verification == "full":  # the window must share a part of its surface with the map, not touch it
        accepted = accepted & (v.fitness >= cfg.min_overlap)
    return accepted
