"""2D recall: hashed keyframe-descriptor votes for stored maps, re-ranked by the 3D descriptor, and
keyframe selection."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from cm3d.memory.bank import MemoryBank, global_table
from cm3d.memory.config import MemoryConfig
from cm3d.memory.entry import evenly_spread
from cm3d.ops import descriptors
from cm3d.ops.grid import first_argmin


@struct.dataclass
class Recall:
    """Recall of one query sequence: ``votes`` (M,) per map, ``scores`` (M,) after 3D re-ranking,
    ``candidates`` (top_k,) map ids best first (-1 = none), ``candidate_scores`` (top_k,)."""

    votes: jax.Array
    scores: jax.Array
    candidates: jax.Array
    candidate_scores: jax.Array


def recall(bank: MemoryBank, query_desc, query_valid, query_cloud_desc, cfg: MemoryConfig) -> Recall:
    """Vote for stored maps with a sequence's keyframe descriptors (Q, D2) and re-rank by 3D.

    Each valid query keyframe looks up the table rows whose hash code is within
    ``cfg.hash_radius`` bits (approximate), re-checks them by exact L2 (< ``cfg.match_radius``)
    and votes for the map of its nearest surviving row. Scores are the fraction of query keyframes
    voting for a map plus ``cfg.w_cloud`` times the cosine similarity of the 3D descriptors; maps
    without votes are never candidates.
    """
    table, codes, valid, map_id = global_table(bank)
    qcodes = descriptors.hash_codes(query_desc, bank.planes)
    near = descriptors.hamming(qcodes[:, None, :], codes[None, :, :]) <= cfg.hash_radius
    d2 = jnp.sum((query_desc[:, None, :] - table[None]) ** 2, -1)
    ok = near & valid[None] & query_valid[:, None] & (d2 < cfg.match_radius**2)
    best = first_argmin(jnp.where(ok, d2, jnp.inf), 1)
    has = jnp.any(ok, axis=1)
    M = bank.map_valid.shape[0]
    votes = jnp.zeros(M).at[map_id[best]].add(has.astype(jnp.float32))
    frac = votes / jnp.maximum(jnp.sum(query_valid), 1)
    sim3d = bank.cloud_desc @ query_cloud_desc
    scores = jnp.where((votes > 0) & bank.map_valid, frac + cfg.w_cloud * sim3d, -jnp.inf)
    top_scores, top = jax.lax.top_k(scores, min(cfg.top_k, M))
    if cfg.top_k > M:  # fewer maps than candidates: pad with "none"
        top_scores = jnp.concatenate([top_scores, jnp.full((cfg.top_k - M,), -jnp.inf, top_scores.dtype)])
        top = jnp.concatenate([top, jnp.zeros((cfg.top_k - M,), top.dtype)])
    return Recall(votes=votes, scores=scores, candidates=jnp.where(jnp.isfinite(top_scores), top, -1),
                  candidate_scores=top_scores)


def select_keyframes(desc, valid, threshold: float, max_keyframes: int):
    """Keyframes spaced evenly in feature space: frame 0 (the first valid one), then every frame
    whose descriptor is farther than ``threshold`` (L2) from the last keyframe's.

    desc (S, D), valid (S,) -> (indices (max_keyframes,) int32, kf_valid (max_keyframes,) bool).
    When more frames qualify than the capacity holds, an evenly spaced subset of them is kept
    (first and last included), so coverage of the sequence is preserved.
    """

    def body(last, x):
        d, ok = x
        far = jnp.sum((d - last) ** 2) > threshold**2
        first = jnp.all(last == 0)
        take = ok & (far | first)
        return jnp.where(take, d, last), take

    _, take = jax.lax.scan(body, jnp.zeros(desc.shape[1], desc.dtype), (desc, valid))
    idx, kf_valid = evenly_spread(take, max_keyframes)
    return jnp.where(kf_valid, idx, 0).astype(jnp.int32), kf_valid
