"""Multi-view depth fusion (cm3d.eval.fusion) against a per-pixel NumPy loop, on exact and noisy depths."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cm3d.eval import fusion

S, H, W = 5, 12, 16
K = np.array([[14.0, 0.0, 7.5], [0.0, 14.0, 5.5], [0.0, 0.0, 1.0]])
NB = fusion.neighbour_frames(S, (-2, -1, 1, 2))


def _poses():
    """Cameras looking along +z, moving sideways and turning a little (cam_to_world)."""
    T = np.tile(np.eye(4), (S, 1, 1))
    for i in range(S):
        T[i, :3, :3] = Rotation.from_rotvec([0.01 * i, 0.03 * (i - 2), 0.005 * i]).as_matrix()
        T[i, :3, 3] = [0.12 * (i - 2), 0.03 * np.sin(i), 0.05 * i]
    return T


def _true_depth(poses):
    """Depth of a slanted wall (z = 4 + 0.3 x + 0.2 y) with a square plate at z = 2 in front of it:
    piecewise planar, so a bilinear sample of inverse depth is exact away from the plate's edges."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays_c = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
    out = np.zeros((S, H, W))
    for i, T in enumerate(poses):
        o, r = T[:3, 3], rays_c @ T[:3, :3].T  # world ray origin and direction (camera z = 1)
        n, c = np.array([-0.3, -0.2, 1.0]), 4.0  # wall: n . X = c
        d_wall = (c - n @ o) / (r @ n)
        d_plate = (2.0 - o[2]) / r[..., 2]
        hit = o + d_plate[..., None] * r
        on_plate = (np.abs(hit[..., 0]) < 0.4) & (np.abs(hit[..., 1]) < 0.3)
        out[i] = np.where(on_plate, d_plate, d_wall)
    return out


def reference(depth, valid, poses, nb, cfg, weights):
    """The fusion of the module doc written as a loop over frames, pixels and neighbours
    (confidence-weighted mean: a neighbour's weight is bilinear in its confidence image)."""
    Kinv = np.linalg.inv(K)
    out, sup = depth.copy(), np.zeros(depth.shape, np.int32)
    for t in range(S):
        own = valid[t] & (depth[t] > 0)
        est = np.where(own, depth[t], 0.0)
        for _ in range(cfg.iterations):
            new, cnt_img = est.copy(), np.zeros((H, W), np.int32)
            for v in range(H):
                for u in range(W):
                    if not own[v, u]:
                        continue
                    num, den, cnt = weights[t, v, u] * depth[t, v, u], weights[t, v, u], 0
                    X = poses[t] @ np.append(Kinv @ [u, v, 1.0] * est[v, u], 1.0)
                    for k in nb[t]:
                        if k < 0:
                            continue
                        Xk = np.linalg.inv(poses[k]) @ X
                        if Xk[2] <= cfg.near:
                            continue
                        us, vs = (K @ Xk[:3] / Xk[2])[:2]
                        x0, y0 = int(np.floor(us)), int(np.floor(vs))
                        if not (0 <= x0 <= W - 2 and 0 <= y0 <= H - 2):
                            continue
                        c = depth[k, y0:y0 + 2, x0:x0 + 2]
                        if not valid[k, y0:y0 + 2, x0:x0 + 2].all() or (c <= 0).any():
                            continue
                        if c.max() > (1 + cfg.edge_tol) * c.min():
                            continue
                        fx, fy = us - x0, vs - y0
                        inv = ((1 - fx) * (1 - fy) / c[0, 0] + fx * (1 - fy) / c[0, 1] + (1 - fx) * fy / c[1, 0]
                               + fx * fy / c[1, 1])
                        Y = np.linalg.inv(poses[t]) @ poses[k] @ np.append(Kinv @ [us, vs, 1.0] / inv, 1.0)
                        if Y[2] <= cfg.near:
                            continue
                        q = K @ Y[:3] / Y[2]
                        if abs(Y[2] - est[v, u]) > cfg.rel_tol * est[v, u] or np.hypot(q[0] - u, q[1] - v) > cfg.px_tol:
                            continue
                        wk = weights[k, y0:y0 + 2, x0:x0 + 2]
                        w = ((1 - fx) * (1 - fy) * wk[0, 0] + fx * (1 - fy) * wk[0, 1] + (1 - fx) * fy * wk[1, 0]
                             + fx * fy * wk[1, 1])
                        num, den, cnt = num + w * Y[2], den + w, cnt + 1
                    new[v, u] = num / den if cnt else est[v, u]
                    cnt_img[v, u] = cnt
            est = new
        out[t] = np.where(own, est, depth[t])
        sup[t] = cnt_img
    return out, sup


def test_matches_numpy_loop_with_noise_outliers_and_masks():
    rng = np.random.default_rng(0)
    poses = _poses()
    depth = _true_depth(poses) * (1 + 0.01 * rng.normal(size=(S, H, W)))
    outlier = rng.random((S, H, W)) < 0.05
    depth[outlier] *= 1.3
    valid = rng.random((S, H, W)) > 0.1
    conf = rng.uniform(1.0, 3.0, (S, H, W))
    cfg = fusion.FusionConfig()  # 5 %, 1 px, 2 passes
    want, want_sup = reference(depth, valid, poses, NB, cfg, conf)
    with jax.enable_x64(True):
        out = fusion.fuse_depths(jnp.asarray(depth), valid, poses, K, NB, conf, cfg=cfg)
        got, sup = np.asarray(out.depth), np.asarray(out.support)
    np.testing.assert_array_equal(sup, want_sup)
    np.testing.assert_allclose(got, want, rtol=1e-9)
    assert (sup > 0).mean() > 0.3 and (sup == 0).sum() > 20  # fused and fallback pixels both occur
    assert np.all(got[~valid] == depth[~valid])  # masked pixels keep their own depth


def test_exact_depths_and_poses_are_recovered_exactly():
    poses = _poses()
    true = _true_depth(poses)
    with jax.enable_x64(True):
        out = fusion.fuse_depths(jnp.asarray(true), np.ones(true.shape, bool), poses, K, NB)
        got, sup = np.asarray(out.depth), np.asarray(out.support)
    np.testing.assert_allclose(got, true, rtol=1e-10)
    assert (sup >= 2).mean() > 0.7  # most pixels really were fused from several neighbours


def test_fusion_lowers_independent_noise():
    rng = np.random.default_rng(1)
    poses = _poses()
    true = _true_depth(poses)
    noisy = (true * (1 + 0.01 * rng.normal(size=true.shape))).astype(np.float32)
    ones = np.ones(true.shape, bool)
    out = fusion.fuse_depths(noisy, ones, poses.astype(np.float32), K, NB)
    err = lambda d: float(np.mean(np.abs(d - true) / true))  # noqa: E731
    assert err(np.asarray(out.depth)) < 0.6 * err(noisy)  # up to 5 independent samples per pixel


def test_lax_map_over_frames_equals_vmap_of_fuse_frame():
    rng = np.random.default_rng(2)
    poses = _poses().astype(np.float32)
    depth = (_true_depth(poses) * (1 + 0.01 * rng.normal(size=(S, H, W)))).astype(np.float32)
    valid = rng.random((S, H, W)) > 0.05
    one = fusion.fuse_depths(depth, valid, poses, K, NB)  # lax.map, one frame at a time
    i = np.maximum(NB, 0)
    Ks = np.broadcast_to(K.astype(np.float32), (S, 3, 3))
    vm = jax.jit(jax.vmap(fusion.fuse_frame))(depth, valid, None, poses, Ks, depth[i], valid[i], None, poses[i],
                                               Ks[i], jnp.asarray(NB >= 0))
    np.testing.assert_allclose(np.asarray(vm[0]), np.asarray(one.depth), rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(vm[1]), np.asarray(one.support))
    assert (np.asarray(one.support) > 0).mean() > 0.5


def test_neighbour_frames_and_bad_input():
    nb = fusion.neighbour_frames(5, (-2, -1, 1, 2))
    np.testing.assert_array_equal(nb[0], [2, 1, -1, -1])  # -2 and -1 reflected; their reflections repeat
    np.testing.assert_array_equal(nb[2], [0, 1, 3, 4])
    assert not (nb == np.arange(5)[:, None]).any()
    with pytest.raises(ValueError, match="offsets"):
        fusion.neighbour_frames(5, (0, 1))
    with pytest.raises(ValueError, match="rel_tol"):
        fusion.FusionConfig(rel_tol=0.0)
    d = np.ones((S, H, W), np.float32)
    with pytest.raises(ValueError, match="valid must be"):
        fusion.fuse_depths(d, np.ones((S, H, W - 1), bool), _poses(), K, NB)
    with pytest.raises(ValueError, match="cam_to_world must be"):
        fusion.fuse_depths(d, d > 0, _poses()[:3], K, NB)
    with pytest.raises(ValueError, match="neighbours must be"):
        fusion.fuse_depths(d, d > 0, _poses(), K, NB[:2])
