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
