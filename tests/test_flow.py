"""Host-side OpenCV flow and keypoint matches: sign convention, padding, bad input."""

import numpy as np
import pytest

from cm3d.ops import flow as flow_ops
from cm3d.ops import keypoints


def _texture(H=96, W=128, seed=0):
    import cv2

    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.integers(0, 256, (H, W, 3)).astype(np.uint8), (0, 0), 1.5)
    coarse = rng.integers(0, 256, (H // 8, W // 8, 3)).astype(np.uint8)
    spots = cv2.resize(coarse, (W, H), interpolation=cv2.INTER_NEAREST)
    return cv2.addWeighted(img, 0.5, spots, 0.5, 0)


def _shifted(img, du, dv):
    """The content of ``img`` moved by (du, dv) pixels (wrapping around)."""
    return np.roll(img, (dv, du), axis=(0, 1))


@pytest.mark.parametrize("method", ["dis", "farneback"])
def test_flow_sign_convention(method):
    img0 = _texture()
    img1 = _shifted(img0, 3, -2)
    f = flow_ops.compute_flow(img0, img1, flow_ops.FlowConfig(method=method))
    assert f.shape == img0.shape[:2] + (2,) and f.dtype == np.float32
    inner = f[16:-16, 16:-16].reshape(-1, 2)
    np.testing.assert_allclose(np.median(inner, 0), [3.0, -2.0], atol=0.25)


def test_sequence_flow_and_precomputed():
    imgs = np.stack([_shifted(_texture(48, 64), k, 0) for k in range(3)])
    flows = flow_ops.sequence_flow(imgs, flow_ops.FlowConfig(dis_preset="fast"))
    assert flows.shape == (2, 48, 64, 2)
    pre = np.zeros((2, 48, 64, 2), np.float32)
    cfg = flow_ops.FlowConfig(method="precomputed")
    np.testing.assert_array_equal(flow_ops.sequence_flow(imgs, cfg, pre), pre)
    with pytest.raises(ValueError, match="shape"):
        flow_ops.sequence_flow(imgs, cfg, pre[:1])
    with pytest.raises(ValueError, match="non-finite"):
        flow_ops.sequence_flow(imgs, cfg, np.full_like(pre, np.nan))
    with pytest.raises(ValueError, match="needs the flow"):
        flow_ops.sequence_flow(imgs, cfg)
    assert flow_ops.sequence_flow(imgs[:1]).shape == (0, 48, 64, 2)


def test_flow_bad_input():
    with pytest.raises(ValueError):
        flow_ops.FlowConfig(method="raft")
    with pytest.raises(ValueError):
        flow_ops.FlowConfig(dis_preset="slow")
    img = _texture(32, 32)
    with pytest.raises(ValueError, match="uint8"):
        flow_ops.compute_flow(img.astype(np.float32), img)
    with pytest.raises(ValueError, match="differs"):
        flow_ops.compute_flow(img, img[:16])


@pytest.mark.parametrize("detector", ["sift", "orb"])
def test_matches_follow_the_motion_and_are_padded(detector):
    img0 = _texture(128, 160, seed=1)
    img1 = _shifted(img0, 5, 2)
    cfg = keypoints.KeypointConfig(detector=detector, max_matches=64)
    m = keypoints.match_keypoints(img0, img1, cfg)
    assert m.uv0.shape == (64, 2) and m.uv1.shape == (64, 2) and m.valid.shape == (64,)
    n = int(m.valid.sum())
    assert n >= 10
    assert m.valid[:n].all() and not m.valid[n:].any()  # valid first, then padding
    d = (m.uv1 - m.uv0)[m.valid]
    assert np.median(np.abs(d - [5.0, 2.0]).max(1)) < 0.6
    assert np.all(m.uv0[~m.valid] == 0)


def test_empty_keypoint_sets_keep_the_shape():
    blank = np.full((64, 64, 3), 128, np.uint8)
    cfg = keypoints.KeypointConfig(max_matches=16)
    m = keypoints.match_keypoints(blank, blank, cfg)
    assert m.uv0.shape == (16, 2) and not m.valid.any()
    seq = keypoints.sequence_matches(np.stack([blank] * 3), cfg)
    assert seq.uv0.shape == (2, 16, 2) and seq.valid.shape == (2, 16)
    none = keypoints.sequence_matches(blank[None], cfg)
    assert none.uv0.shape == (0, 16, 2)
    with pytest.raises(ValueError):
        keypoints.KeypointConfig(detector="surf")


def test_spread_order_is_a_round_robin_over_grid_cells():
    rng = np.random.default_rng(6)
    uv = rng.uniform(0, 100, (300, 2))
    uv[:150] = rng.uniform(0, 20, (150, 2))  # a strong textured corner holds half the detections
    order = rng.permutation(300)  # priority (e.g. strongest first)
    got = keypoints.spread_order(uv[order], 4, order)
    lo, span = uv.min(0), np.ptp(uv, axis=0)
    cell = lambda p: tuple(np.minimum(np.floor((p - lo) / span * 4), 3).astype(int))  # noqa: E731
    seen, rank = {}, {}
    for i in order:  # reference: each point's rank within its cell, in priority order
        rank[i] = seen.get(cell(uv[i]), 0)
        seen[cell(uv[i])] = rank[i] + 1
    pos = {i: k for k, i in enumerate(order)}
    assert list(got) == sorted(order, key=lambda i: (rank[i], pos[i]))
    assert len({cell(uv[i]) for i in got[:16]}) == 16  # the first 16 cover every cell
    assert len({cell(uv[i]) for i in order[:16]}) < 16  # strongest first would not
    assert len(keypoints.spread_order(np.zeros((0, 2)), 4)) == 0
    with pytest.raises(ValueError, match="spread_cells"):
        keypoints.KeypointConfig(spread_cells=-1)
    with pytest.raises(ValueError, match="contrast_threshold"):
        keypoints.KeypointConfig(contrast_threshold=0.0)
    img = _texture(96, 128, seed=3)
    det = keypoints.detect(img, keypoints.KeypointConfig(contrast_threshold=0.01))
    plain = keypoints.features_from(det, 4000, keypoints.KeypointConfig())
    spread = keypoints.features_from(det, 4000, keypoints.KeypointConfig(spread_cells=8))
    n = int(plain.valid.sum())
    assert n == int(spread.valid.sum()) and n > 50  # the same detections, another order
    assert sorted(map(tuple, plain.uv[:n])) == sorted(map(tuple, spread.uv[:n]))
    assert len(keypoints.detect(img)[0]) < n  # the lower contrast threshold finds more


def test_match_contrast_matches_as_a_detection_at_that_contrast():
    img0 = _texture(160, 200, seed=4)
    fade = np.linspace(0.1, 1.0, 200)[None, :, None]  # contrast falls off to the left: weak keypoints there
    img0 = (128 + (img0.astype(np.float32) - 128) * fade).astype(np.uint8)
    img1 = _shifted(img0, 4, 3)
    low = keypoints.KeypointConfig(max_matches=512, contrast_threshold=0.01)
    filt = keypoints.KeypointConfig(max_matches=512, contrast_threshold=0.01, match_contrast=0.04)
    high = keypoints.KeypointConfig(max_matches=512, contrast_threshold=0.04)
    d_low = [keypoints.detect(im, low) for im in (img0, img1)]
    d_high = [keypoints.detect(im, high) for im in (img0, img1)]
    assert len(d_low[0][0]) > 1.3 * len(d_high[0][0])  # the low threshold finds many weak keypoints
    got = keypoints.match_detections(*d_low, filt)
    ref = keypoints.match_detections(*d_high, high)
    n = int(ref.valid.sum())
    assert n >= 20 and int(got.valid.sum()) == n
    assert np.array_equal(got.uv0[:n], ref.uv0[:n]) and np.array_equal(got.uv1[:n], ref.uv1[:n])
    assert int(keypoints.match_detections(*d_low, low).valid.sum()) > n  # unfiltered: more matches
    with pytest.raises(ValueError, match="match_contrast"):
        keypoints.KeypointConfig(match_contrast=0.0)


@pytest.mark.parametrize("factor", [1, 2, 3])
def test_reduced_detection_finds_blobs_where_they_are_in_full_resolution_pixels(factor):
    """Gaussian blobs at known sub-pixel centres: detect_reduced's keypoints, found on the image area-averaged by
    ``factor`` (3: 320 / 107 is not an integer ratio), lie on the centres in the full image's pixels. A mapping
    ``f u`` (no pixel-centre term) or OpenCV's default upscale would put them 0.25-0.5 px off."""
    H, W = 240, 320
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    rng = np.random.default_rng(0)
    centres = np.stack([rng.uniform(30, W - 30, 12), rng.uniform(30, H - 30, 12)], 1)
    img = np.full((H, W), 60.0)
    for cx, cy in centres:
        img += 150 * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * 4.0**2))
    kps, desc = keypoints.detect_reduced(np.clip(img, 0, 255).astype(np.uint8), keypoints.KeypointConfig(), factor)
    pts = np.array([k.pt for k in kps])
    assert desc.shape == (len(kps), 128)
    nearest = np.linalg.norm(pts[:, None] - centres[None], axis=-1).min(1)
    on_blob = nearest < 1.0  # (a blob's flanks give further keypoints at coarser scales)
    assert on_blob.sum() >= 12
    assert np.median(nearest[on_blob]) < 0.05
