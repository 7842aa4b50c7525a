"""Recognition: which stored map does a query show, and where? 2D recall -> keypoint RANSAC per
candidate -> ICP validation of the best -> the acceptance model (pure, jittable, vmappable)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from cm3d.memory.acceptance import (acceptance_features, acceptance_score, accepts, chance_test, chance_tests,
                                    placement_error)
from cm3d.memory.bank import MemoryBank
from cm3d.memory.config import MemoryConfig
from cm3d.memory.entry import MapEntry
from cm3d.memory.recall import Recall, recall
from cm3d.memory.verify import Verification, decide, keypoint_poses, query_keypoints, refine_pose


@struct.dataclass
class Identification:
    """Recall + verification of one query: the recall, keypoint checks of each candidate
    (``candidate_inliers`` (top_k,)), the verification of the best candidate and ``map_id`` (the
    accepted map, -1 if none)."""

    recall: Recall
    candidate_inliers: jax.Array
    verification: Verification
    map_id: jax.Array
    candidate: jax.Array | None = None  # () the verified candidate (-1: none), accepted or not
    features: jax.Array | None = None  # (len(ACCEPTANCE_FEATURES),) its scores (acceptance_features)
    acceptance: jax.Array | None = None  # () the acceptance model's score (None without cfg.accept_weights)
    pose_inliers: jax.Array | None = None  # () scored keypoint matches within the RANSAC distance of the final pose
    chance_inliers: jax.Array | None = None  # () ... expected by chance (shuffled matches; chance_test)
    log_nfa: jax.Array | None = None  # () log10 of the chance test's number of false alarms (accept < max_log_nfa)
    placement_error: jax.Array | None = None  # () how precisely the final pose's keypoint inliers fix it


def identify(bank: MemoryBank, entry: MapEntry, cfg: MemoryConfig, key) -> Identification:
    """Which stored map does the query ``entry`` show, and where? (pure, jittable, vmappable)

    2D recall (:func:`recall`) proposes ``cfg.top_k`` candidates; each is checked by keypoint
    matching + Sim(3) RANSAC (triangle and upright-pair hypotheses); the candidate with most RANSAC
    inliers (ties: recall order) is refined from its pose with the most colour-consistent overlap
    and verified by ICP (:func:`verify`, per ``cfg.verification``); with ``cfg.accept_weights`` (the
    default) and ``"full"`` verification the acceptance model decides instead of the thresholds:
    :func:`acceptance_score` of :func:`acceptance_features` >= 0, plus the hard checks (a stored map, a
    finite transform, a scale in ``cfg.scale_range``). Every accepted candidate also passes the
    **chance test** (:func:`chance_test`: the final pose's keypoint inliers against the count its
    shuffled matches give, log10 NFA below ``cfg.max_log_nfa``), with keypoint verification or more;
    a candidate far beyond chance (log10 NFA below ``cfg.accept_log_nfa``) that passes the hard checks
    and whose keypoint inliers fix its pose (:func:`placement_error` at most
    ``cfg.alone_max_placement_error``) is accepted whatever the model or the thresholds say. With
    ``"full"`` verification an accepted candidate also overlaps the map: ICP fitness at least
    ``cfg.min_overlap``. (The decision is :func:`accepts` of the reported evidence.) A query without
    2D candidates skips the 3D stages (a ``lax.cond``; under ``vmap`` both branches run) and reports no
    candidate: inliers -1, zero ICP figures, identity transform, NaN acceptance score, infinite placement
    error.
    """
    r = recall(bank, entry.kf_desc, entry.kf_valid, entry.cloud_desc, cfg)
    cand = r.candidates
    if cfg.verification == "none":
        v = decide(bank, cand[0], jnp.eye(4), jnp.ones(()), jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32), None, cfg)
        return Identification(recall=r, candidate_inliers=jnp.zeros(cfg.top_k, jnp.int32), verification=v,
                              map_id=jnp.where(v.accepted, cand[0], -1))

    def candidates(_):
        qk, qf, cluster, frame, sep = query_keypoints(entry, cfg)
        keys = jax.random.split(key, cfg.top_k)
        Ts, scales, matches, inliers, scored = jax.vmap(
            lambda m, k: keypoint_poses(bank, jnp.maximum(m, 0), qk, qf, cluster, frame, sep, cfg, k))(cand, keys)
        best = jnp.where(cand >= 0, jnp.max(inliers, 1), -1)
        b = jnp.argmax(best)
        m = cand[b]
        v, screen, s_kp = refine_pose(bank, m, entry, Ts[b], scales[b], matches[b], inliers[b], cfg)
        feats = acceptance_features(bank, entry, r, best, b, inliers[b], screen, s_kp, v)
        score = acceptance_score(feats, cfg) if cfg.accept_weights and cfg.verification == "full" else None
        # the chance test (3D feature stage, under the final pose): an a-contrario bound on the keypoint inliers
        thr = cfg.ransac_distance * jnp.maximum(bank.voxel_size[jnp.maximum(m, 0)], 1e-12)
        k, lam, log_nfa = chance_test(scored[0][b], scored[1][b], scored[2][b], v.transform, thr, chance_tests(cfg))
        place = placement_error(scored[0][b], scored[1][b], scored[2][b], v.transform, thr)
        accepted = accepts(bank, m, v, score, log_nfa, place, cfg)
        v = v.replace(accepted=accepted)
        return Identification(recall=r, candidate_inliers=best, verification=v,
                              map_id=jnp.where(v.accepted, m, -1), candidate=m, features=feats, acceptance=score,
                              pose_inliers=k, chance_inliers=lam, log_nfa=log_nfa, placement_error=place)

    def no_candidate(_):  # nothing to verify: what the stages would report for no map, without running them
        z = jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), jax.eval_shape(candidates, None))
        none = lambda a: jnp.full_like(a, -1)  # noqa: E731
        v = z.verification.replace(transform=jnp.eye(4, dtype=z.verification.transform.dtype),
                                   scale=jnp.ones_like(z.verification.scale))
        return z.replace(recall=r, candidate_inliers=none(z.candidate_inliers), verification=v,
                         map_id=none(z.map_id), candidate=none(z.candidate),
                         acceptance=None if z.acceptance is None else jnp.full_like(z.acceptance, jnp.nan),
                         placement_error=jnp.full_like(z.placement_error, jnp.inf))

    # the expensive stages (3D keypoints, ICP) run only for a query the 2D recall found candidates for
    return jax.lax.cond(jnp.any(cand >= 0), candidates, no_candidate, None)
