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


def _visit(scene, visit, frames, level):
    from cm3d.data import synthetic

    seq = synthetic.generate(scene, visit, frames, level, synthetic.WorldConfig(height=120, width=160, supersample=1))
    s = seq.meta["prior_scale"]
    prior_from_world = np.diag([s, s, s, 1.0]) @ np.linalg.inv(seq.gt.cam_to_world[0])
    return seq, prior_from_world


def test_floor_plane_and_orthophoto_against_ground_truth():
    from cm3d.ops import keypoints

    seq, pfw = _visit(9, 1, 6, "none")  # exact priors up to the visit's unknown scale
    static = ~seq.gt.dynamic_mask
    n, c = keypoints.floor_plane(seq.depth, seq.intrinsic, seq.cam_to_world, static)
    n_gt = pfw[:3, :3] @ np.array([0.0, 0.0, 1.0])  # the world floor is z = 0
    n_gt /= np.linalg.norm(n_gt)
    height_gt = seq.gt.cam_to_world[0][2, 3] * seq.meta["prior_scale"]
    assert np.degrees(np.arccos(np.clip(n @ n_gt, -1, 1))) < 0.5
    assert abs(c - height_gt) < 0.01 * height_gt
    img, ok, to_world = keypoints.floor_orthophoto(seq.images, seq.depth, seq.intrinsic, seq.cam_to_world, static,
                                                   (n, c))
    assert img.shape[:2] == ok.shape and 0.3 < ok.mean() < 1.0 and img[ok].std() > 5
    v, u = np.nonzero(ok)
    X = np.stack([u, v, np.ones_like(u)], -1) @ to_world.T
    np.testing.assert_allclose(X @ n + c, 0.0, atol=1e-6)  # every pixel is a point of the plane
    # the orthophoto's colour at a floor point is the first frame's colour where that point projects
    K, w2c = seq.intrinsic[0], np.linalg.inv(seq.cam_to_world[0])
    Xc = X @ w2c[:3, :3].T + w2c[:3, 3]
    uv = Xc[:, :2] / Xc[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
    H, W = seq.depth.shape[1:]
    inside = (Xc[:, 2] > 0) & np.all((uv > 2) & (uv < [W - 3, H - 3]), 1)
    ui, vi = np.round(uv[inside]).astype(int).T
    near = inside.copy()
    near[inside] = static[0, vi, ui] & (Xc[inside, 2] < 1.2 * seq.depth[0, vi, ui])  # not hidden
    ui, vi = np.round(uv[near]).astype(int).T
    diff = np.abs(img[v[near], u[near]].astype(float) - seq.images[0, vi, ui].astype(float)).mean(1)
    assert near.sum() > 1000 and np.median(diff) < 25


def test_floor_features_match_across_visits_better_than_image_sift():
    import jax.numpy as jnp

    from cm3d import memory
    from cm3d.ops import keypoints

    def mutual_right(a_pts, a_desc, b_pts, b_desc, T, tol):
        d = ((a_desc[:, None] - b_desc[None]) ** 2).sum(-1)
        nn, back = d.argmin(1), d.argmin(0)
        mutual = back[nn] == np.arange(len(a_pts))
        moved = a_pts @ T[:3, :3].T + T[:3, 3]
        return int(np.sum(mutual & (np.linalg.norm(moved - b_pts[nn], axis=1) < tol)))

    (a, pa), (b, pb) = _visit(9, 0, 8, "slight"), _visit(9, 1, 8, "slight")  # own scale, frame, priors
    T = pa @ np.linalg.inv(pb)  # visit b's prior frame -> visit a's
    tol = 0.15 * np.cbrt(np.linalg.det(pa[:3, :3]))  # 15 cm
    fa, fb = (keypoints.floor_features(s.images, s.depth, s.intrinsic, s.cam_to_world, ~s.gt.dynamic_mask, 256)
              for s in (a, b))
    assert fa.valid.sum() > 100 and fb.valid.sum() > 100
    np.testing.assert_allclose(np.linalg.norm(fa.desc[fa.valid], axis=1), 1.0, atol=1e-5)
    floor = mutual_right(fb.points[fb.valid], fb.desc[fb.valid], fa.points[fa.valid], fa.desc[fa.valid], T, tol)

    def image_keypoints(s):  # the perspective images' SIFT, lifted (the memory's image keypoints)
        f = keypoints.detect_sequence(s.images, ~s.gt.dynamic_mask, 32, contrast_threshold=0.01)
        kp = memory.lift_keypoints(f.uv, f.desc, f.valid, jnp.asarray(s.depth), s.intrinsic, s.cam_to_world, 256)
        return np.asarray(kp.points)[np.asarray(kp.valid)], np.asarray(kp.desc)[np.asarray(kp.valid)]

    image = mutual_right(*image_keypoints(b), *image_keypoints(a), T, tol)
    assert floor >= 10 and floor > 2 * image, (floor, image)


def test_floor_features_without_a_floor_and_bad_input():
    from cm3d.ops import keypoints

    S, H, W = 2, 24, 32
    K = np.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]])
    images = np.random.default_rng(0).integers(0, 255, (S, H, W, 3), dtype=np.uint8)
    wall = np.full((S, H, W), 2.0)  # a wall facing the camera: no plane within max_tilt of up
    poses = np.broadcast_to(np.eye(4), (S, 4, 4))
    f = keypoints.floor_features(images, wall, np.broadcast_to(K, (S, 3, 3)), poses, None, 16)
    assert f.points.shape == (16, 3) and f.desc.shape == (16, 128) and not f.valid.any()
    with pytest.raises(ValueError, match="cam_to_world"):
        keypoints.floor_features(images, wall, np.broadcast_to(K, (S, 3, 3)), np.eye(4), None, 16)
    with pytest.raises(ValueError, match="singular"):
        keypoints.floor_features(images, wall, np.zeros((S, 3, 3)), poses, None, 16)
    with pytest.raises(ValueError, match="images"):
        keypoints.floor_features(images.astype(np.float32), wall, np.broadcast_to(K, (S, 3, 3)), poses, None, 16)
    with pytest.raises(ValueError, match="up_prior"):
        keypoints.FloorConfig(up_prior=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="plane_tolerance"):
        keypoints.FloorConfig(plane_tolerance=0.0)


def test_floor_features_on_a_real_tum_frame(shared_data):
    """A real RGB-D frame (TUM fr2, camera looking down at a desk): the dominant horizontal plane below the
    camera is the desk top, and its orthophoto yields keypoints on it."""
    import cv2

    from cm3d.ops import keypoints

    root = shared_data / "tum_fr2_pair"
    image = cv2.imread(str(root / "1.png"))[None, ..., ::-1].copy()
    depth = cv2.imread(str(root / "1_depth.png"), cv2.IMREAD_UNCHANGED)[None] / 5000.0  # metres, 0 = none
    K = np.array([[[520.9, 0, 325.1], [0, 521.0, 249.7], [0, 0, 1]]])
    pose = np.eye(4)[None]
    n, c = keypoints.floor_plane(depth, K, pose)
    assert n @ np.array([0.0, -1.0, 0.0]) > np.cos(np.radians(35)) and 0.5 < c < 1.2  # desk ~0.5-1 m below
    f = keypoints.floor_features(image, depth, K, pose, None, 128)
    k = int(f.valid.sum())
    assert k >= 20
    np.testing.assert_allclose(f.points[:k] @ n + c, 0.0, atol=1e-6)  # on the plane
    # the keypoints are where the frame sees the plane: their depth agrees with the measured depth
    uvw = f.points[:k] @ K[0].T
    u, v = np.round(uvw[:, :2] / uvw[:, 2:]).astype(int).T
    measured = depth[0, v, u]
    ok = measured > 0
    assert ok.mean() > 0.8 and np.median(np.abs(uvw[ok, 2] / measured[ok] - 1)) < 0.03
