"""Descriptors: invariances, normalisation, masks, hashing against numpy references."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from cm3d.ops import descriptors as D


def _cloud(seed, n=400):
    rng = np.random.default_rng(seed)
    box = rng.uniform([-3, -2, 0], [3, 2, 2.5], size=(n, 3))
    box[: n // 2, 2] = 0.0  # a floor
    return box.astype(np.float32)


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10_000))
def test_cloud_descriptor_is_similarity_invariant(seed):
    rng = np.random.default_rng(seed)
    p = _cloud(seed % 7)
    R = Rotation.random(random_state=seed).as_matrix()
    s, t = rng.uniform(0.2, 5.0), rng.normal(size=3) * 3
    q = (s * p @ R.T + t).astype(np.float32)
    np.testing.assert_allclose(D.cloud_descriptor(q), D.cloud_descriptor(p), atol=2e-3)


def test_cloud_descriptor_masks_and_degenerate_input():
    p = _cloud(0)
    valid = np.arange(len(p)) < 300
    padded = np.where(valid[:, None], p, 1e3)  # garbage in the padding must not matter
    np.testing.assert_allclose(D.cloud_descriptor(padded, valid), D.cloud_descriptor(p[:300]), atol=1e-5)
    assert np.all(np.asarray(D.cloud_descriptor(p, np.zeros(len(p), bool))) == 0)
    same = D.cloud_descriptor(np.zeros((10, 3), np.float32))
    assert np.all(np.isfinite(same))
    assert float(jnp.linalg.norm(D.cloud_descriptor(p))) == np.float32(1.0) or abs(
        float(jnp.linalg.norm(D.cloud_descriptor(p))) - 1) < 1e-5
    assert abs(float(jnp.linalg.norm(D.cloud_descriptor(_cloud(1)) - D.cloud_descriptor(p)))) > 1e-3


def test_image_descriptor_unit_norm_mask_and_batching():
    rng = np.random.default_rng(0)
    imgs = rng.integers(0, 256, size=(3, 48, 64, 3)).astype(np.uint8)
    d = jax.vmap(D.image_descriptor)(imgs)
    assert d.shape == (3, D.IMAGE_DIM)
    np.testing.assert_allclose(jnp.linalg.norm(d, axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(jax.jit(D.image_descriptor)(imgs[1]), d[1], atol=1e-5)
    np.testing.assert_allclose(D.image_descriptor(imgs[1] / 255.0), d[1], atol=1e-5)  # float input
    assert np.all(np.asarray(D.image_descriptor(imgs[0], np.zeros((48, 64), bool))) == 0)
    # masked-out pixels do not matter
    mask = np.zeros((48, 64), bool)
    mask[:, :32] = True
    other = imgs[0].copy()
    other[:, 32:] = 0
    np.testing.assert_allclose(D.image_descriptor(imgs[0], mask), D.image_descriptor(other, mask), atol=1e-6)


def test_image_descriptor_tolerates_viewpoint_change_on_renders():
    from cm3d.data import synthetic

    cfg = synthetic.WorldConfig(height=96, width=128)
    seqs = [synthetic.generate(s, 0, 4, "none", cfg) for s in (0, 1, 2)]
    d = [np.asarray(jax.vmap(D.image_descriptor)(q.images, ~q.gt.dynamic_mask)) for q in seqs]
    same = np.mean([np.linalg.norm(x[0] - x[3]) for x in d])  # 0.3 s of camera motion apart
    other = np.mean([np.linalg.norm(d[i][0] - d[j][3]) for i in range(3) for j in range(3) if i != j])
    assert same < 0.5 * other, (same, other)


def test_hash_codes_and_hamming_match_numpy():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(5, 16)).astype(np.float32)
    planes = D.hash_planes(16, bits=64, seed=3)
    codes = np.asarray(D.hash_codes(x, planes))
    assert codes.shape == (5, 2) and codes.dtype == np.uint32
    bits = (x @ np.asarray(planes).T > 0)
    ref = np.stack([np.sum(bits[:, w * 32:(w + 1) * 32] << np.arange(32, dtype=np.uint64), axis=1)
                    for w in range(2)], 1).astype(np.uint32)
    np.testing.assert_array_equal(codes, ref)
    ham = np.asarray(D.hamming(codes[:, None], codes[None]))
    np.testing.assert_array_equal(ham, (bits[:, None] != bits[None]).sum(-1))


def test_detect_features_rootsift_mask_and_padding():
    from cm3d.data import synthetic
    from cm3d.ops import keypoints

    seq = synthetic.generate(3, 0, 2, "none", synthetic.WorldConfig(height=120, width=160, supersample=1))
    mask = np.zeros((120, 160), bool)
    mask[:, :80] = True
    f = keypoints.detect_features(seq.images[0], mask, capacity=400, contrast_threshold=0.01)
    n = int(f.valid.sum())
    assert 20 < n < 400 and f.desc.shape == (400, keypoints.DESCRIPTOR_DIM["sift"])
    assert np.all(f.valid[:n]) and not np.any(f.valid[n:]) and not np.any(f.desc[n:])
    np.testing.assert_allclose(np.linalg.norm(f.desc[:n], axis=1), 1.0, atol=1e-5)
    assert np.all(f.desc[:n] >= 0) and np.all(f.uv[:n, 0] < 80 + 2)  # RootSIFT; only inside the mask
    few = keypoints.detect_features(seq.images[0], mask, capacity=5, contrast_threshold=0.01)
    np.testing.assert_array_equal(few.uv, f.uv[:5])  # strongest first
    s = keypoints.detect_sequence(seq.images, None, 16)
    assert s.uv.shape == (2, 16, 2) and s.valid.shape == (2, 16)
    empty = keypoints.detect_features(np.zeros((40, 40, 3), np.uint8), capacity=8)
    assert not np.any(empty.valid)
    with pytest.raises(ValueError, match="mask"):
        keypoints.detect_features(seq.images[0], np.ones((10, 10), bool))
