"""The acceptance model: the verified candidate's weak signals as one feature vector
(:data:`~cm3d.memory.config.ACCEPTANCE_FEATURES`) and their linear score (a logistic regression
fitted on the tuning split of ``experiments/memory_recall.py``)."""

from __future__ import annotations

import jax.numpy as jnp

from cm3d.memory.bank import MemoryBank
from cm3d.memory.config import MemoryConfig
from cm3d.memory.entry import MapEntry
from cm3d.memory.recall import Recall
from cm3d.memory.verify import Verification


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


def model_accepts(bank, m, v: Verification, score, cfg: MemoryConfig):
    """The acceptance model's decision: score >= 0 and the hard checks (a stored map, a finite transform,
    a scale in ``cfg.scale_range``)."""
    return ((m >= 0) & bank.map_valid[jnp.maximum(m, 0)] & (score >= 0) & jnp.all(jnp.isfinite(v.transform))
            & (v.scale >= cfg.scale_range[0]) & (v.scale <= cfg.scale_range[1]))
