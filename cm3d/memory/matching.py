"""3D keypoint matching for verification: mutual nearest descriptors with a 3D-aware ratio test,
clusters of keypoints that are one 3D point, and a cloud's up axis (for upright RANSAC pairs)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from cm3d.memory.entry import Keypoints
from cm3d.ops.grid import first_argmin


def nearest_descriptors(d2, m_points, ratio: float, min_separation):
    """From squared descriptor distances d2 (Nq, Nm) (inf for invalid pairs): the nearest map keypoint j
    (Nq,), its distance (Nq,), whether the match is mutual (Nq,) and whether it passes the 3D-aware ratio
    test (Nq,) (see :func:`match_keypoints`). Squared 3D distances to the best match's point are expanded
    as |a|^2 + |b|^2 - 2 a.b (one small matrix product instead of an (Nq, Nm, 3) difference)."""
    j = first_argmin(d2, 1)
    best = jnp.min(d2, axis=1)
    pj = m_points[j]
    sq = jnp.sum(m_points**2, -1)
    far = sq[None, :] + sq[j][:, None] - 2.0 * (pj @ m_points.T) > min_separation**2
    second = jnp.min(jnp.where(far, d2, jnp.inf), axis=1)
    mutual = first_argmin(d2, 0)[j] == jnp.arange(d2.shape[0])
    return j, best, mutual, jnp.isfinite(best) & (best <= ratio**2 * second)


def descriptor_d2(q: Keypoints, m: Keypoints):
    """(Nq, Nm) squared L2 distances of unit descriptors, inf for pairs with an invalid keypoint."""
    return jnp.where(q.valid[:, None] & m.valid[None, :], 2.0 - 2.0 * (q.desc @ m.desc.T), jnp.inf)


def match_keypoints(q: Keypoints, m: Keypoints, ratio: float, min_separation):
    """Mutual nearest neighbours in descriptor space with a 3D-aware ratio test.

    The second-best match is searched among map keypoints farther than ``min_separation`` (map
    units) from the best one, so repeated views of one 3D point do not fail the ratio test.
    Returns (j (Nq,) map index per query keypoint, ok (Nq,) bool).
    """
    q = jax.tree.map(jnp.asarray, q)
    m = jax.tree.map(jnp.asarray, m)
    j, _, mutual, ratio_ok = nearest_descriptors(descriptor_d2(q, m), m.points, ratio, min_separation)
    return j, q.valid & mutual & ratio_ok


def keypoint_clusters(points, valid, separation):
    """Cluster id (N,) int32 of each keypoint: the index of the first valid keypoint closer than
    ``separation`` (itself when none is earlier). Keypoints of one 3D point seen in several frames
    share an id, so counting distinct ids counts 3D points, not views
    (:func:`cm3d.solvers.ransac.distinct_count`)."""
    points, valid = jnp.asarray(points), jnp.asarray(valid, bool)
    near = (jnp.sum((points[:, None] - points[None]) ** 2, -1) < separation**2) & valid[None, :] & valid[:, None]
    first = jnp.argmax(near, axis=1)  # the earliest close keypoint (itself at worst)
    return jnp.where(valid, first, jnp.arange(points.shape[0])).astype(jnp.int32)


def up_axis(normals, valid, prior=(0.0, -1.0, 0.0), max_angle: float = 35.0):
    """The up (gravity) axis (3,) of a cloud in its own frame, from its normals (N, 3): the principal
    direction of the unit normals within ``max_angle`` degrees of ``prior`` (up or down: floor, ceiling,
    table tops), signed like ``prior``; ``prior`` (normalised) when fewer than 3 normals qualify.
    A camera held roughly upright (the first camera defines a visit's frame) makes the prior good to a
    few tens of degrees; the floor and ceiling make the estimate good to about a degree."""
    normals = jnp.asarray(normals, jnp.float32)
    prior = jnp.asarray(prior, jnp.float32)
    prior = prior / jnp.linalg.norm(prior)
    unit = jnp.abs(jnp.sum(normals**2, -1) - 1.0) < 0.1
    near = jnp.abs(normals @ prior) > np.cos(np.radians(max_angle))
    w = (jnp.asarray(valid, bool) & unit & near).astype(jnp.float32)
    _, vecs = jnp.linalg.eigh(jnp.einsum("n,ni,nj->ij", w, normals, normals))
    u = vecs[:, -1]
    u = jnp.where(u @ prior < 0, -u, u)
    return jnp.where(jnp.sum(w) >= 3, u, prior)
