"""Occlusion-aware motion cues (cm3d.motion.occlusion) on a hand-built two-plane scene.

A background wall at depth 4 and a near static strip at depth 1, seen by a camera that slides
sideways: the strip's parallax (8 px) is four times the wall's (2 px). The "observed" flow is what a
patch-based estimator returns: the true flow box-averaged over 5x5 pixels (mixing both sides of the
depth edge), and on the wall pixels the strip covers in the next frame (the disoccluded band, seen
from frame 1) the strip's flow. The old cue (own depth only, no z-buffer) flags the edge bands;
the occlusion-aware one must not, and must still find a slow mover on the wall.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cm3d import motion
from cm3d.ops import camera
from cm3d.ops.keypoints import Matches

H, W, F = 96, 128, 100.0
K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]], np.float32)
TX = 0.08  # camera 1 is 8 cm to the right: wall flow -2 px, strip flow -8 px
STRIP = (40, 70)  # columns of the near strip in frame 0
CFG = motion.MotionConfig(appearance=False)  # the images here are blank: the geometry alone is tested
OLD = dataclasses.replace(CFG, occlusion=False, edge_radius_px=0)


def _depth(shift: int = 0):
    d = np.full((H, W), 4.0, np.float32)
    d[:, STRIP[0] - shift:STRIP[1] - shift] = 1.0
    return d


def _box(x, r=2):
    k = 2 * r + 1
    pad = np.pad(x, ((r, r), (r, r), (0, 0)), mode="edge")
    return np.mean([pad[i:i + H, j:j + W] for i in range(k) for j in range(k)], axis=0)


def _scene(mover_px: float = 0.0, noise: float = 0.05, seed: int = 0):
    """(prior_t, prior_t2, observed flow, mover mask, disoccluded band) of the two-plane scene."""
    d0, d1 = _depth(), _depth(8)
    c2w1 = np.eye(4, dtype=np.float32)
    c2w1[0, 3] = TX
    true, _ = camera.ego_flow(jnp.asarray(d0), jnp.asarray(K), jnp.eye(4), jnp.asarray(K), jnp.asarray(c2w1))
    true = np.asarray(true)
    mover = np.zeros((H, W), bool)
    mover[60:80, 90:110] = True
    true = true + mover[..., None] * np.array([mover_px, 0.0], np.float32)
    obs = _box(true)
    band = np.zeros((H, W), bool)
    band[:, STRIP[0] - 6:STRIP[0]] = True  # wall pixels the strip covers in frame 1
    obs[band] = [-8.0, 0.0]
    obs += np.random.default_rng(seed).normal(0, noise, obs.shape)
    ones = np.ones((H, W), np.float32)
    img = np.zeros((H, W, 3), np.uint8)
    p0 = motion.FramePrior(image=img, depth=jnp.asarray(d0), depth_conf=ones, intrinsic=jnp.asarray(K),
                           cam_to_world=jnp.eye(4))
    p1 = motion.FramePrior(image=img, depth=jnp.asarray(d1), depth_conf=ones, intrinsic=jnp.asarray(K),
                           cam_to_world=jnp.asarray(c2w1))
    return p0, p1, jnp.asarray(obs, jnp.float32), mover, band


NO_MATCHES = Matches(np.zeros((64, 2), np.float32), np.zeros((64, 2), np.float32), np.zeros(64, bool))
_cues = jax.jit(motion.motion_cues, static_argnums=4)


def test_static_scene_with_a_strong_depth_edge_gives_an_empty_mask():
    p0, p1, flow, _, _ = _scene()
    old = _cues(p0, p1, flow, NO_MATCHES, OLD)
    assert np.asarray(old.robust_mask).sum() > 200, "the scene must trip the old cue (edge bands)"
    new = _cues(p0, p1, flow, NO_MATCHES, CFG)
    assert np.asarray(new.robust_mask).sum() == 0
    assert np.asarray(new.geo_mask).mean() < 1e-3


def test_disoccluded_band_is_not_dynamic_and_is_marked_occluded():
    p0, p1, flow, _, band = _scene()
    edges_only = dataclasses.replace(CFG, occlusion=False)  # depth-range residual without the z-buffer
    assert np.asarray(_cues(p0, p1, flow, NO_MATCHES, edges_only).geo_mask)[band].mean() > 0.5
    cues = _cues(p0, p1, flow, NO_MATCHES, CFG)
    assert not np.asarray(cues.geo_mask)[band].any()
    occ = np.asarray(cues.occluded)
    assert occ[band].mean() > 0.9 and occ[~band].mean() < 0.01


def test_pixels_beside_a_sensor_hole_are_not_judged():
    """A depth sensor registered 4 px off the image (as 7-Scenes' Kinect): its map ends the strip at
    column 66 and loses 66-67 (a hole, confidence 0, filled with the wall), while the image's strip
    reaches column 69. Columns 68-69 move with the strip but their depth says wall: the cue without
    the hole rule calls them dynamic; with it they are beside the hole and not judged."""
    p0, p1, flow, _, _ = _scene()
    depth, conf = np.array(p0.depth), np.ones((H, W), np.float32)
    depth[:, 66:70] = 4.0
    conf[:, 66:68] = 0.0
    p0 = p0.replace(depth=jnp.asarray(depth), depth_conf=jnp.asarray(conf))
    beside = np.zeros((H, W), bool)
    beside[:, 68:70] = True
    old = np.asarray(_cues(p0, p1, flow, NO_MATCHES, dataclasses.replace(CFG, hole_edges=False)).robust_mask)
    assert old[beside].mean() > 0.8, "the registration error must trip the cue without the hole rule"
    cues = _cues(p0, p1, flow, NO_MATCHES, CFG)
    assert np.asarray(cues.robust_mask).sum() == 0
    assert not np.asarray(cues.valid)[beside].any()  # not judged (the hole itself neither)


@pytest.mark.parametrize("radius", [1, 2])
def test_line_opening_equals_scipy_openings_by_line_segments(radius):
    """The holes that count (a run of 2r+1 along a row, column or diagonal) are scipy's binary
    opening by those four segments; 20 % random dropouts keep almost none, a band keeps all."""
    from scipy import ndimage

    from cm3d.ops.components import line_opening

    m = np.random.default_rng(radius).random((60, 80)) < 0.2
    m[20:22, 5:70] = True
    k = 2 * radius + 1
    ref = np.zeros_like(m)
    for se in (np.ones((1, k)), np.ones((k, 1)), np.eye(k), np.fliplr(np.eye(k))):
        ref |= ndimage.binary_opening(m, structure=se.astype(bool))
    got = np.asarray(jax.jit(line_opening, static_argnums=1)(jnp.asarray(m), radius))
    np.testing.assert_array_equal(got, ref)
    assert got[20:22, 5:70].all()
    if radius == 2:
        assert got[:18].sum() < 0.05 * m[:18].sum()


def test_slow_mover_is_still_found():
    p0, p1, flow, mover, _ = _scene(mover_px=1.5)  # 1.5 px (under the wall parallax of 2 px) against 0.05 px noise
    m = np.asarray(_cues(p0, p1, flow, NO_MATCHES, CFG).robust_mask)
    iou = (m & mover).sum() / (m | mover).sum()
    assert iou > 0.8, iou


def test_two_pairs_must_agree():
    a = jnp.array([[True, True, False, False]])
    va = jnp.array([[True, False, True, False]])
    dyn, judged = motion.combine_pairs(a, va, jnp.array([[False, True, True, True]]),
                                       jnp.array([[True, True, True, False]]))
    np.testing.assert_array_equal(dyn, [[False, True, False, False]])
    np.testing.assert_array_equal(judged, [[True, True, True, False]])


def _fb_reference(fw, bw, alpha, beta):
    """NumPy forward-backward check (Sundaram et al. 2010) with bilinear sampling."""
    h, w = fw.shape[:2]
    out = np.zeros((h, w), bool)
    for v in range(h):
        for u in range(w):
            x, y = u + fw[v, u, 0], v + fw[v, u, 1]
            if not (0 <= x <= w - 1 and 0 <= y <= h - 1):
                continue
            x0, y0 = min(int(np.floor(x)), w - 2), min(int(np.floor(y)), h - 2)
            fx, fy = x - x0, y - y0
            b = ((bw[y0, x0] * (1 - fx) + bw[y0, x0 + 1] * fx) * (1 - fy)
                 + (bw[y0 + 1, x0] * (1 - fx) + bw[y0 + 1, x0 + 1] * fx) * fy)
            out[v, u] = np.sum((fw[v, u] + b) ** 2) <= alpha * (np.sum(fw[v, u] ** 2) + np.sum(b ** 2)) + beta
    return out


@pytest.mark.parametrize("seed", [0, 1])
def test_forward_backward_consistency_against_a_hand_made_flow(seed):
    rng = np.random.default_rng(seed)
    h, w = 24, 32
    fw = np.tile(np.array([2.5, -1.25], np.float32), (h, w, 1)) + rng.normal(0, 0.05, (h, w, 2)).astype(np.float32)
    bw = -np.tile(np.array([2.5, -1.25], np.float32), (h, w, 1))
    bw[8:14, 10:20] = [3.0, 1.0]  # where the backward flow disagrees: an occluded patch
    got = np.asarray(motion.forward_backward_consistent(jnp.asarray(fw), jnp.asarray(bw), 0.01, 0.5))
    np.testing.assert_array_equal(got, _fb_reference(fw, bw, 0.01, 0.5))
    # consistent everywhere but where the flow lands in (or bilinearly next to) the bad patch or leaves the image
    tgt_u, tgt_v = np.arange(w)[None] + 2.5, np.arange(h)[:, None] - 1.25
    inside = (tgt_u <= w - 1) & (tgt_v >= 0)
    assert got[inside & ~((tgt_u >= 9) & (tgt_u <= 20) & (tgt_v >= 7) & (tgt_v <= 14))].all()
    assert not got[(tgt_u >= 11) & (tgt_u <= 18) & (tgt_v >= 9) & (tgt_v <= 12)].any()
    assert not got[~inside].any()
