"""3D keypoint matching for verification: mutual nearest descriptors with a 3D-aware ratio test,
clusters of keypoints that are one 3D point, and a cloud's up axis (for upright RANSAC pairs)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from cm3d.memory.entry import Keypoints


def nearest_descriptors(q: Keypoints, m: Keypoints, ratio: float, min_separation):
    """Each query keypoint's nearest map keypoint in descriptor space (unit descriptors, squared L2):
    the map index j (Nq,) (the first on ties), its squared distance (Nq,) (inf for an invalid query
    keypoint or a map without valid ones), whether the match is mutual (the query keypoint is as close to
    map keypoint j as any other query keypoint is) and whether it passes the 3D-aware ratio test (Nq,)
    (see :func:`match_keypoints`).

    Computed on the similarities ``q.desc @ m.desc.T`` (squared distance ``2 - 2 sim``) in four passes
    over the (Nq, Nm) matrix: the row maximum, its first index, the best map keypoint farther than
    ``min_separation`` in 3D (squared 3D distances expanded as |a|^2 + |b|^2 - 2 a.b: one small matrix
    product instead of an (Nq, Nm, 3) difference) and the column maximum for the mutual check (a
    column maximum, not a column argmin: 1.6x faster at 256 x 1024, the same matches but on exact ties)."""
    sim = jnp.where(q.valid[:, None] & m.valid[None, :], q.desc @ m.desc.T, -jnp.inf)
    top = jnp.max(sim, axis=1)
    iota = jnp.arange(sim.shape[1], dtype=jnp.int32)
    j = jnp.min(jnp.where(sim == top[:, None], iota[None, :], sim.shape[1] - 1), axis=1)
    pj = m.points[j]
    sq = jnp.sum(m.points**2, -1)
    far = sq[None, :] + sq[j][:, None] - 2.0 * (pj @ m.points.T) > min_separation**2
    top_far = jnp.max(jnp.where(far, sim, -jnp.inf), axis=1)
    found = jnp.isfinite(top)
    best = jnp.where(found, 2.0 - 2.0 * top, jnp.inf)
    second = jnp.where(jnp.isfinite(top_far), 2.0 - 2.0 * top_far, jnp.inf)
    mutual = found & (top >= jnp.max(sim, axis=0)[j])
    return j, best, mutual, found & (best <= ratio**2 * second)


def match_keypoints(q: Keypoints, m: Keypoints, ratio: float, min_separation):
    """Mutual nearest neighbours in descriptor space with a 3D-aware ratio test.

    The second-best match is searched among map keypoints farther than ``min_separation`` (map
    units) from the best one, so repeated views of one 3D point do not fail the ratio test.
    Returns (j (Nq,) map index per query keypoint, ok (Nq,) bool).
    """
    q = jax.tree.map(jnp.asarray, q)
    m = jax.tree.map(jnp.asarray, m)
    j, _, mutual, ratio_ok = nearest_descriptors(q, m, ratio, min_separation)
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
