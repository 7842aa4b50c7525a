"""Camera geometry against OpenCV and against the renderer's independent ground truth."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cm3d.data import synthetic
from cm3d.ops import camera, se3

K = np.array([[500.0, 0.0, 319.5], [0.0, 480.0, 239.5], [0.0, 0.0, 1.0]])


def _pose(xi):
    return np.asarray(se3.exp(jnp.asarray(xi, jnp.float32)), np.float64)


def test_project_matches_opencv():
    rng = np.random.default_rng(0)
    T = _pose([0.2, -0.1, 0.3, 0.05, -0.1, 0.2])
    pts = rng.uniform([-2, -2, 2], [2, 2, 6], size=(50, 3))
    uv, z = camera.project(jnp.asarray(pts, jnp.float32), jnp.asarray(K, jnp.float32), jnp.asarray(T, jnp.float32))
    E = np.linalg.inv(T)
    ref, _ = cv2.projectPoints(pts, cv2.Rodrigues(E[:3, :3])[0], E[:3, 3], K, None)
    np.testing.assert_allclose(uv, ref[:, 0], atol=2e-3)
    np.testing.assert_allclose(z, (pts @ E[:3, :3].T + E[:3, 3])[:, 2], atol=1e-4)


def test_unproject_project_round_trip_and_batching():
    rng = np.random.default_rng(1)
    depth = jnp.asarray(rng.uniform(1, 5, size=(3, 6, 8)), jnp.float32)
    Ts = jnp.asarray(np.stack([_pose(rng.normal(size=6) * 0.3) for _ in range(3)]), jnp.float32)
    Ks = jnp.broadcast_to(jnp.asarray(K, jnp.float32), (3, 3, 3))
    pts = camera.unproject(depth, Ks, Ts)
    uv, z = camera.project(pts.reshape(3, -1, 3), Ks, Ts)
    np.testing.assert_allclose(uv.reshape(3, 6, 8, 2), np.broadcast_to(camera.pixel_grid(6, 8), (3, 6, 8, 2)), atol=2e-3)
    np.testing.assert_allclose(z.reshape(3, 6, 8), depth, rtol=1e-5)
    np.testing.assert_allclose(jax.vmap(camera.unproject)(depth, Ks, Ts), pts, atol=1e-5)
    np.testing.assert_allclose(jax.jit(camera.unproject)(depth, Ks, Ts), pts, atol=1e-5)


def test_ego_flow_identity_and_pure_translation():
    depth = jnp.full((4, 5), 2.0)
    Kj, I = jnp.asarray(K, jnp.float32), jnp.eye(4)
    flow, valid = camera.ego_flow(depth, Kj, I, Kj, I)
    assert bool(valid.all()) and float(jnp.abs(flow).max()) < 1e-4
    # camera moves +x by 0.1 m: a static point at depth 2 moves by -fx * 0.1 / 2 pixels
    T1 = I.at[0, 3].set(0.1)
    flow, _ = camera.ego_flow(depth, Kj, I, Kj, T1)
    np.testing.assert_allclose(flow[..., 0], -500 * 0.1 / 2, rtol=1e-5)
    np.testing.assert_allclose(flow[..., 1], 0.0, atol=1e-4)
    # points behind the next camera are invalid
    T2 = I.at[2, 3].set(3.0)
    _, valid = camera.ego_flow(depth, Kj, I, Kj, T2)
    assert not bool(valid.any())


@pytest.fixture(scope="module")
def world():
    """A short visit at 192x256 (supersampled as the default 384x512 is), rendered once for the module:
    a quarter of the default's pixels, the same scene and camera path."""
    return synthetic.generate(scene_seed=3, visit=0, num_frames=5, level="none",
                              cfg=synthetic.WorldConfig(height=192, width=256, supersample=2))


def test_ego_flow_equals_renderer_flow_on_static_pixels(world):
    gt = world.gt
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    flow, valid = camera.ego_flow(f32(gt.depth[:-1]), f32(gt.intrinsic[:-1]), f32(gt.cam_to_world[:-1]),
                                  f32(gt.intrinsic[1:]), f32(gt.cam_to_world[1:]))
    static = np.asarray(valid) & ~gt.dynamic_mask[:-1]
    err = np.linalg.norm(np.asarray(flow) - gt.flow, axis=-1)[static]
    assert static.mean() > 0.5
    assert np.median(err) < 0.05, np.median(err)
    # on moving objects the two must differ: the renderer's flow carries object motion
    dyn = gt.dynamic_mask[:-1] & np.asarray(valid)
    assert dyn.sum() > 100
    assert np.median(np.linalg.norm(np.asarray(flow) - gt.flow, axis=-1)[dyn]) > 0.5


def test_opencv_dis_flow_agrees_with_ground_truth_on_renders(world):
    gt, imgs = world.gt, world.images
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    errs = []
    for i in range(world.num_frames - 1):
        g0, g1 = (cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in (imgs[i], imgs[i + 1]))
        flow = dis.calc(g0, g1, None)
        # static pixels with texture (local gradient), away from the image border
        gy, gx = np.gradient(g0.astype(np.float32))
        textured = np.hypot(gx, gy) > 2.0
        textured[:16], textured[-16:], textured[:, :16], textured[:, -16:] = False, False, False, False
        m = textured & ~gt.dynamic_mask[i]
        errs.append(np.linalg.norm(flow - gt.flow[i], axis=-1)[m])
    epe = np.median(np.concatenate(errs))
    assert epe < 1.0, epe
