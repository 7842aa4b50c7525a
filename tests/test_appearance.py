"""The appearance check (cm3d.motion.appearance) on a hand-built fronto-parallel wall.

A textured wall at depth 4 seen by a camera sliding 8 cm sideways: every static pixel moves -2 px.
Frame t2 is frame t shifted by 2 px (exactly what the static scene predicts) except where a
textured patch really moves, or where a textureless patch gets a wrong flow (as DIS returns on a
blank surface). The geometry cue flags both patches; the images must keep only the mover.
"""

import jax
import jax.numpy as jnp
import numpy as np

from cm3d import motion
from cm3d.motion import appearance
from cm3d.ops.keypoints import Matches

H, W, F = 96, 128, 100.0
K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]], np.float32)
SHIFT = 2  # static flow (px, to the left): F * 0.08 / 4
MOVER = (slice(20, 44), slice(20, 48))
BLANK = (slice(56, 84), slice(70, 110))
CFG = motion.MotionConfig()
NO_MATCHES = Matches(np.zeros((64, 2), np.float32), np.zeros((64, 2), np.float32), np.zeros(64, bool))


def _texture(rng, h, w):
    """Smooth random texture in [0, 255] (uint8, 3 channels)."""
    x = rng.normal(size=(h // 4 + 2, w // 4 + 2))
    x = np.kron(x, np.ones((4, 4)))[:h, :w]
    x = (x - x.min()) / (x.max() - x.min())
    return np.repeat((40 + 180 * x)[..., None], 3, -1)


def _scene(mover_px: int = 3, brightness: float = 0.0, seed: int = 0):
    rng = np.random.default_rng(seed)
    img0 = _texture(rng, H, W + 8)
    img0[BLANK] = 128.0  # a blank patch: no texture, any flow matches it
    img1 = np.roll(img0, -SHIFT, axis=1)  # frame t2: the static scene moved by the ego flow
    m0 = img0[MOVER[0], MOVER[1].start - mover_px:MOVER[1].stop - mover_px]
    img1[MOVER[0], MOVER[1].start - SHIFT:MOVER[1].stop - SHIFT] = m0  # the mover: mover_px further left
    img1 = img1 + brightness
    flow = np.zeros((H, W, 2), np.float32)
    flow[..., 0] = -SHIFT
    flow[MOVER[0], MOVER[1], 0] = -SHIFT - mover_px
    flow[BLANK[0], BLANK[1], 0] = -SHIFT + 3.0  # wrong, as on a textureless surface
    flow += np.random.default_rng(seed + 1).normal(0, 0.05, flow.shape).astype(np.float32)
    c2w1 = np.eye(4, dtype=np.float32)
    c2w1[0, 3] = 0.08
    depth, ones = np.full((H, W), 4.0, np.float32), np.ones((H, W), np.float32)
    u8 = [np.clip(np.round(i[:, :W]), 0, 255).astype(np.uint8) for i in (img0, img1)]
    p0 = motion.FramePrior(image=u8[0], depth=depth, depth_conf=ones, intrinsic=K,
                           cam_to_world=np.eye(4, dtype=np.float32))
    p1 = motion.FramePrior(image=u8[1], depth=depth, depth_conf=ones, intrinsic=K, cam_to_world=c2w1)
    return p0, p1, jnp.asarray(flow)


_cues = jax.jit(motion.motion_cues, static_argnums=4)


def test_textureless_wrong_flow_is_dropped_and_the_textured_mover_kept():
    p0, p1, flow = _scene()
    cues = _cues(p0, p1, flow, NO_MATCHES, CFG)
    # the candidates are the geometric regions before the appearance check
    assert np.asarray(cues.candidates)[BLANK].mean() > 0.8, "the blank patch must trip the geometry cue"
    mask = np.asarray(cues.robust_mask)
    assert mask[BLANK].sum() == 0
    assert mask[MOVER].mean() > 0.8
    outside = np.ones((H, W), bool)
    outside[MOVER] = False
    assert mask[outside].sum() == 0


def test_a_brightness_change_is_not_motion():
    p0, p1, flow = _scene(brightness=25.0)
    mask = np.asarray(_cues(p0, p1, flow, NO_MATCHES, CFG).robust_mask)
    assert mask[BLANK].sum() == 0 and mask[MOVER].mean() > 0.8


def test_warp_dissimilarity_against_numpy():
    rng = np.random.default_rng(3)
    g0 = rng.uniform(size=(24, 32)).astype(np.float32)
    g1 = np.roll(g0, -1, axis=1) + 0.3  # a 1 px shift and an offset: zero dissimilarity inside
    flow = np.zeros((24, 32, 2), np.float32)
    flow[..., 0] = -1.0
    got = np.asarray(appearance.warp_dissimilarity(jnp.asarray(g0), jnp.asarray(g1), jnp.asarray(flow), 2))
    np.testing.assert_allclose(got[:, 3:-3], 0.0, atol=2e-3)
    # the zero flow: the patch standard deviation of g0 - g1, by a direct loop
    d = g0 - g1
    ref = np.array([[d[max(0, i - 2):i + 3, max(0, j - 2):j + 3].std() for j in range(32)] for i in range(24)])
    got0 = np.asarray(appearance.warp_dissimilarity(jnp.asarray(g0), jnp.asarray(g1), jnp.zeros((24, 32, 2)), 2))
    np.testing.assert_allclose(got0, ref, atol=1e-4)


def test_jit_vmap_invariance():
    scenes = [_scene(seed=s) for s in (0, 1)]
    batch = jax.tree.map(lambda *a: jnp.stack(a), *scenes)
    f = jax.vmap(lambda a, b, fl: appearance.static_rejected(a.image, b.image, fl, jnp.full((H, W, 2), -2.0),
                                                            jnp.ones((H, W), bool)))
    out = np.asarray(jax.jit(f)(*batch))
    for i, (a, b, fl) in enumerate(scenes):
        one = appearance.static_rejected(a.image, b.image, fl, jnp.full((H, W, 2), -2.0), jnp.ones((H, W), bool))
        np.testing.assert_array_equal(out[i], np.asarray(one))
