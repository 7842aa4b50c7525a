"""Motion cues: ego-motion residual, keypoint cue, components, edge cases, jit/vmap, refinement."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.measure import label as sk_label

from cm3d import motion, refine
from cm3d.data import synthetic
from cm3d.eval.metrics import mask_metrics
from cm3d.ops import components, se3
from cm3d.ops.keypoints import Matches

SMALL = synthetic.WorldConfig(height=64, width=96, num_moving=2, supersample=1)
CFG = motion.MotionConfig(pose_stride=2, gmm=dataclasses.replace(motion.MotionConfig().gmm, max_iters=15))
N_KP = 32
CUES = jax.jit(motion.motion_cues, static_argnums=4)


@pytest.fixture(scope="module")
def clean_seq():
    """A noise-free render: priors equal ground truth up to the prior's frame and scale."""
    return synthetic.generate(scene_seed=2, visit=1, num_frames=3, level="none", cfg=SMALL)


def _pair(seq, i=0):
    p = motion.FramePrior.from_sequence(seq)
    return jax.tree.map(lambda a: a[i], p), jax.tree.map(lambda a: a[i + 1], p)


def _no_matches(n=N_KP):
    return Matches(np.zeros((n, 2), np.float32), np.zeros((n, 2), np.float32), np.zeros(n, bool))


def _finite(tree):
    return all(np.all(np.isfinite(np.asarray(x, np.float64))) for x in jax.tree.leaves(tree))


@pytest.mark.parametrize("refine_pose", [False, True])
def test_ego_residual_near_zero_on_static_pixels(clean_seq, refine_pose):
    a, b = _pair(clean_seq)
    cfg = dataclasses.replace(CFG, refine_pose=refine_pose, residual_floor_px=0.1)  # tiny images: slow movers
    cue = jax.jit(motion.geometry_motion_cue, static_argnums=3)(a, b, jnp.asarray(clean_seq.gt.flow[0]), cfg)
    geo, residual, valid = cue.mask, cue.residual, cue.valid
    static = np.asarray(valid) & ~clean_seq.gt.dynamic_mask[0]
    assert static.sum() > 0.5 * static.size
    res = np.asarray(residual)[static]
    # exact poses: float32 round-off only; flow-refined poses: movers of ~1 px at this size pull a little
    tol = (0.05, 0.1) if refine_pose else (0.002, 0.01)
    assert np.median(res) < tol[0] and np.percentile(res, 99) < tol[1], np.percentile(res, [50, 99, 100])
    moving = np.asarray(valid) & clean_seq.gt.dynamic_mask[0]
    assert np.median(np.asarray(residual)[moving]) > 5 * np.percentile(res, 99)  # the movers stand out
    assert float(mask_metrics(np.asarray(geo), clean_seq.gt.dynamic_mask[0])["iou"]) > 0.6


def test_refined_pose_recovers_prior_error(clean_seq):
    a, b = _pair(clean_seq)
    true_rel = motion.relative_pose(a, b)
    noisy = se3.exp(jnp.array([0.01, -0.02, 0.0, 0.02, -0.015, 0.01])) @ true_rel  # ~1.6 deg
    weight = (a.depth > 0).astype(jnp.float32)
    est = jax.jit(motion.refine_relative_pose, static_argnums=6)(
        a.depth, a.intrinsic, b.intrinsic, jnp.asarray(clean_seq.gt.flow[0]), noisy, weight, CFG)
    err = float(jnp.rad2deg(se3.rotation_angle(est[:3, :3].T @ true_rel[:3, :3])))
    start = float(jnp.rad2deg(se3.rotation_angle(noisy[:3, :3].T @ true_rel[:3, :3])))
    assert err < 0.15 and err < start / 10, (start, err)


def test_motion_cues_jit_vmap_invariance(clean_seq):
    """The batched cues (the step's: reverse flows, occlusion check, frame t >= 1 also judged against
    t - 1) equal the single-pair function called frame by frame."""
    pri = motion.FramePrior.from_sequence(clean_seq)
    flows = jnp.asarray(clean_seq.gt.flow)
    rng = np.random.default_rng(0)
    uv0 = rng.uniform([0, 0], [SMALL.width - 1, SMALL.height - 1], (2, N_KP, 2)).astype(np.float32)
    m = Matches(uv0, uv0 + np.asarray(clean_seq.gt.flow)[0, 0, 0], np.ones((2, N_KP), bool))
    rev = -flows[:, ::-1]  # any flow field will do for the comparison
    both = motion.sequence_motion_cues(pri, flows, m, CFG, flows_rev=rev)
    for i in range(2):
        a, b = _pair(clean_seq, i)
        second = motion.SecondPair(partner=jax.tree.map(lambda x: x[max(i - 1, 0)], pri), flow=rev[max(i - 1, 0)],
                                   flow_rev=flows[max(i - 1, 0)], valid=jnp.asarray(i >= 1))
        single = CUES(a, b, flows[i], jax.tree.map(lambda x: x[i], m), CFG, rev[i], second)
        for f in ("flow_mask", "geo_mask", "valid", "candidates", "robust_mask", "baseline_mask", "kp_dynamic",
                  "occluded"):
            np.testing.assert_array_equal(getattr(both, f)[i], getattr(single, f), err_msg=f)
        np.testing.assert_allclose(both.residual[i], single.residual, atol=1e-3)
        assert _finite(single)


@pytest.mark.parametrize("case", ["zero_flow", "constant_flow", "all_static", "all_dynamic"])
def test_edge_cases_no_nan(clean_seq, case):
    a, b = _pair(clean_seq)
    H, W = SMALL.height, SMALL.width
    cfg = CFG
    ego, _ = jax.jit(motion.ego_flow_rel)(a.depth, a.intrinsic, b.intrinsic, motion.relative_pose(a, b))
    if case == "zero_flow":
        flow = jnp.zeros((H, W, 2))
    elif case == "constant_flow":
        flow = jnp.full((H, W, 2), 2.5, jnp.float32)  # (not weakly typed: zero_flow's program)
    elif case == "all_static":  # the flow is exactly the ego flow: nothing moves
        flow = ego
    else:  # every pixel moves 6 px against the (trusted, unrefined) ego motion
        flow = ego + jnp.array([6.0, 0.0])
        cfg = dataclasses.replace(CFG, refine_pose=False)
    cues = CUES(a, b, flow, _no_matches(), cfg)
    assert _finite(cues)
    assert cues.flow_mask.dtype == jnp.bool_ and cues.robust_mask.shape == (H, W)
    if case == "all_static":
        assert not np.asarray(cues.geo_mask).any() and not np.asarray(cues.robust_mask).any()
    if case == "all_dynamic":
        # The fixed-threshold baseline flags every valid pixel; the geometric cue's noise floor
        # (k * median residual) takes the majority motion for the static level, so it flags none
        # (documented: a frame moving as a whole is indistinguishable from ego-motion error).
        assert np.asarray(cues.baseline_mask)[np.asarray(cues.valid)].all()
        assert not np.asarray(cues.geo_mask).any()


def test_empty_and_full_keypoint_sets(clean_seq):
    a, b = _pair(clean_seq)
    flow = jnp.asarray(clean_seq.gt.flow[0])
    empty = CUES(a, b, flow, _no_matches(), CFG)
    assert _finite(empty) and not np.asarray(empty.kp_dynamic).any() and not np.asarray(empty.kp_valid).any()
    # without keypoints a region cannot be confirmed: keep_unverified decides
    strict = CUES(a, b, flow, _no_matches(), dataclasses.replace(CFG, keep_unverified=False))
    assert not np.asarray(strict.robust_mask).any()
    np.testing.assert_array_equal(empty.robust_mask, empty.candidates)


def test_dynamic_keypoints_flags_the_movers(clean_seq):
    """Static keypoints follow the ego flow; a few are displaced: exactly those are dynamic."""
    a, b = _pair(clean_seq)
    rel = motion.relative_pose(a, b)
    ego, ok = jax.jit(motion.ego_flow_rel)(a.depth, a.intrinsic, b.intrinsic, rel)
    static = np.argwhere(np.asarray(ok) & ~clean_seq.gt.dynamic_mask[0] & (np.asarray(a.depth) > 0))
    rng = np.random.default_rng(1)
    pick = static[rng.choice(len(static), N_KP, replace=False)]
    uv0 = pick[:, ::-1].astype(np.float32)
    uv1 = uv0 + np.asarray(ego)[pick[:, 0], pick[:, 1]]
    moved = np.zeros(N_KP, bool)
    moved[:5] = True
    uv1[moved] += np.array([6.0, -4.0], np.float32)
    m = Matches(uv0, uv1, np.ones(N_KP, bool))
    @jax.jit
    def cue(a, b, m, rel):
        disp, ray, kp_ok = motion.keypoint_displacements(a, b, m, rel, CFG)
        no_reference = jnp.zeros_like(kp_ok)  # every keypoint on a candidate: static-scene model
        return (motion.dynamic_keypoints(disp, ray, kp_ok, CFG), kp_ok,
                motion.dynamic_keypoints(disp, ray, kp_ok, CFG, no_reference))

    dyn, kp_ok, dyn_model = (np.asarray(v) for v in cue(a, b, m, rel))
    np.testing.assert_array_equal(dyn_model, dyn)
    np.testing.assert_array_equal(dyn[np.asarray(kp_ok)], moved[np.asarray(kp_ok)])
    assert np.asarray(kp_ok).sum() >= N_KP - 8 and dyn.sum() >= 3  # a few sit on depth edges: not judged


def test_connected_components_match_skimage():
    rng = np.random.default_rng(0)
    lab_j = jax.jit(jax.vmap(components.label_components))
    masks = rng.random((4, 24, 40)) < np.array([0.3, 0.5, 0.6, 0.7])[:, None, None]
    ours = np.asarray(lab_j(masks))
    for mask, lab in zip(masks, ours):
        ref = sk_label(mask, connectivity=1)
        assert (lab >= 0).sum() == mask.sum()
        # same partition: a bijection between our roots and skimage's labels
        pairs = set(zip(lab[mask].tolist(), ref[mask].tolist()))
        assert len(pairs) == len(set(lab[mask].tolist())) == ref.max()
        flat = np.flatnonzero(mask.ravel())
        assert all(lab.ravel()[i] <= i for i in flat)  # the root is the first pixel
    area = np.asarray(components.region_area(jnp.asarray(ours[0])))
    ref = sk_label(masks[0], connectivity=1)
    np.testing.assert_array_equal(area[masks[0]], np.bincount(ref.ravel())[ref[masks[0]]])


def test_warp_mask_shifts_with_the_flow():
    mask = np.zeros((20, 30), bool)
    mask[5:10, 4:12] = True
    flow = np.broadcast_to(np.array([3.0, 2.0], np.float32), (20, 30, 2))
    np.testing.assert_array_equal(np.asarray(motion.warp_mask(mask, flow)), np.roll(mask, (2, 3), (0, 1)))
    # the host twin (refine's tracking) is bitwise the jitted one, borders, half pixels and splat holes included
    rng = np.random.default_rng(0)
    for _ in range(3):
        m = rng.random((37, 53)) < 0.3
        f = (rng.normal(0, 4, (37, 53, 2)) + rng.choice([0.0, 0.5, -1.5], (37, 53, 2))).astype(np.float32)
        np.testing.assert_array_equal(refine.warp_mask(m, f), np.asarray(motion.warp_mask(m, f)))


def _green(rng, shape):
    return (rng.integers(0, 60, shape + (3,)) + np.array([20, 140, 40])).astype(np.uint8)  # noisy green


def _red(rng, n):
    return (rng.integers(0, 60, (n, 3)) + np.array([170, 30, 60])).astype(np.uint8)  # n noisy red pixels


def _disk_scene(H=80, W=100):
    rng = np.random.default_rng(0)
    img = _green(rng, (H, W))
    v, u = np.mgrid[0:H, 0:W]
    disk = (u - 55) ** 2 + (v - 40) ** 2 < 18**2
    img[disk] = _red(rng, disk.sum())
    return img, disk


def test_grabcut_refiner_snaps_a_dilated_mask_to_the_object():
    img, disk = _disk_scene()
    coarse = refine._dilate(disk, 5)
    pts, ids, _ = refine.sample_prompts(coarse, 5, seed=0)
    assert len(pts) == 5 and coarse[pts[:, 1], pts[:, 0]].all()
    out = refine.GrabCutRefiner(reference_width=img.shape[1])(img, coarse, pts, ids)
    iou = lambda m: (m & disk).sum() / (m | disk).sum()  # noqa: E731
    assert iou(out) > 0.95 > iou(coarse)
    ws = refine.WatershedRefiner()(img, coarse, pts, ids, refine.RefineHints())
    assert iou(ws) > iou(coarse)
    assert not refine.GrabCutRefiner()(img, np.zeros_like(disk), pts[:0], ids[:0]).any()  # nothing to refine
    full = np.ones_like(disk)  # all dynamic: no background seed, the mask is kept
    assert refine.GrabCutRefiner()(img, full, pts, ids).all()


def test_context_boxes_grow_each_region_and_merge_overlaps():
    seeds = np.zeros((100, 200), bool)
    seeds[10:20, 10:30] = True  # 10 x 20: grown by 10 / 20 px each side, clipped at the top
    seeds[60:70, 150:160] = True  # far away: its own window
    assert sorted(refine.context_boxes(seeds, 1.0)) == [(0, 30, 0, 50), (50, 80, 140, 170)]
    seeds[33:38, 53:58] = True  # a speck whose window (28-43, 48-63) overlaps the first one's
    assert sorted(refine.context_boxes(seeds, 1.0)) == [(0, 43, 0, 63), (50, 80, 140, 170)]
    assert refine.context_boxes(np.zeros((5, 5), bool), 1.0) == []
    # on its window the refiner snaps the disk as it does on the whole frame (the default)
    img, disk = _disk_scene()
    coarse = refine._dilate(disk, 5)
    pts, ids, _ = refine.sample_prompts(coarse, 5, seed=0)
    local = refine.GrabCutRefiner(reference_width=img.shape[1], context=1.0)(img, coarse, pts, ids)
    iou = lambda m: (m & disk).sum() / (m | disk).sum()  # noqa: E731
    assert iou(local) > 0.95


def _leak_scene(obj_flow):
    """Flow (64, 96, 2): background (-3, 0) px plus a slight zoom, a square object moving
    ``obj_flow``; the mask is the object plus a 6-px leak into the background on its left."""
    H, W = 64, 96
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    flow = np.stack([-3.0 + 0.01 * (u - W / 2), 0.01 * (v - H / 2)], -1)
    obj = np.zeros((H, W), bool)
    obj[20:44, 40:64] = True
    flow[obj] = obj_flow
    flow += np.random.default_rng(0).normal(0, 0.1, flow.shape).astype(np.float32)
    leak = np.zeros((H, W), bool)
    leak[20:44, 34:40] = True
    return flow, obj, leak


def test_background_movers_finds_the_leak_and_nothing_when_the_motions_agree():
    flow, obj, leak = _leak_scene((2.0, 0.5))
    movers = refine.background_movers(obj | leak, flow)
    assert movers[leak].mean() > 0.9 and movers[obj].mean() < 0.02
    flow, obj, leak = _leak_scene((-3.0, 0.0))  # a camera following the object: the flow cannot tell
    assert refine.background_movers(obj | leak, flow).mean() < 0.01
    assert not refine.background_movers(np.zeros((64, 96), bool), flow).any()


def test_grabcut_drops_uncertain_pixels_of_background_colour():
    img, disk = _disk_scene()
    leak = refine._dilate(disk, 12) & ~disk
    leak[:, : img.shape[1] // 2] = False  # a thick one-sided leak: thicker than the core erosion
    coarse = disk | leak
    pts, ids, _ = refine.sample_prompts(disk, 5, seed=0)
    g = refine.GrabCutRefiner(reference_width=img.shape[1], core_px=4)
    plain = g(img, coarse, pts, ids)
    hinted = g(img, coarse, pts, ids, refine.RefineHints(uncertain=leak))
    iou = lambda m: (m & disk).sum() / (m | disk).sum()  # noqa: E731
    assert iou(hinted) > 0.95 and iou(hinted) > iou(plain) + 0.05


def _moving_disk(frames: int, shift: int = 4):
    """The disk scene moving ``shift`` px right per frame: images, flows (t -> t+1, one per frame),
    true masks and the first frame's disk."""
    img0, disk = _disk_scene()
    images = np.stack([np.roll(img0, shift * t, axis=1) for t in range(frames)])
    flows = np.broadcast_to(np.array([shift, 0.0], np.float32), (frames,) + disk.shape + (2,)).copy()
    truth = np.stack([np.roll(disk, shift * t, axis=1) for t in range(frames)])
    return images, flows, truth, disk


def test_refine_and_track_follows_a_moving_object():
    images, flows, truth, disk = _moving_disk(4)
    flows, truth = flows[:3], truth[:3]
    calls = []

    def detect(t):
        calls.append(t)
        return refine._dilate(truth[t], 3)

    candidates = np.stack([refine._dilate(truth[t], 3) for t in range(3)])
    masks, detected = refine.refine_and_track(images, flows, candidates, detect,
                                              refine.GrabCutRefiner(reference_width=100))
    assert calls == [0] and detected.tolist() == [True, False, False]  # tracked, no re-detection
    for t in range(3):
        assert (masks[t] & truth[t]).sum() / (masks[t] | truth[t]).sum() > 0.9
    # a new mover appearing in frame 2 triggers detection there
    extra = np.zeros_like(disk)
    extra[5:20, 5:25] = True
    candidates[2] |= extra
    calls.clear()
    _, detected = refine.refine_and_track(images, flows, candidates, detect, refine.GrabCutRefiner(reference_width=100))
    assert calls == [0, 2] and detected.tolist() == [True, False, True]


def test_tracking_keeps_only_the_refined_regions_that_hold_a_sure_seed():
    """A red disk moves 3 px a frame over a static green background; frame 0's detection also holds a
    static red blob (a false detection). From frame 1 the blob moves with the background (a background
    mover, so not a sure seed), but GrabCut calls it foreground by its colour: kept, it would be carried
    forward for ever; ``keep_seeded`` drops it and keeps the disk."""
    rng = np.random.default_rng(0)
    H, W, T = 80, 100, 4
    v, u = np.mgrid[0:H, 0:W]
    blob = (u - 15) ** 2 + (v - 15) ** 2 < 8**2
    back = _green(rng, (H, W))
    back[blob] = _red(rng, blob.sum())
    disks = np.stack([(u - 45 - 3 * t) ** 2 + (v - 45) ** 2 < 14**2 for t in range(T)])
    images = np.stack([np.where(disks[t][..., None], _red(rng, H * W).reshape(H, W, 3), back) for t in range(T)])
    flows = np.zeros((T, H, W, 2), np.float32)
    flows[..., 0] = 3.0 * disks
    g = refine.GrabCutRefiner(reference_width=W)
    run = lambda keep: refine.refine_and_track(  # noqa: E731
        images, flows, np.ones((T, H, W), bool), lambda t: disks[0] | blob if t == 0 else np.zeros((H, W), bool),
        g, cfg=refine.TrackConfig(grow=False, new_region_frac=2.0, keep_seeded=keep, check_added=False))[0]
    kept, loose = run(True), run(False)
    iou = lambda a, b: (a & b).sum() / (a | b).sum()  # noqa: E731
    assert loose[1:, blob].mean() > 0.9  # the check below can fail: without the rule the blob stays
    for t in range(1, T):
        assert not kept[t, blob].any() and iou(kept[t], disks[t]) > 0.9


def test_tracking_drops_added_pixels_that_move_like_the_background():
    """A red disk moves +3 px a frame while the camera pans (background flow -3 px); in frame 1 a red
    strip of the background touches it. GrabCut adds the strip (the disk's colour, inside its band) and
    it is connected to the disk, so only its motion tells it apart: over frame 1's own flow it moves
    like the background around the mask, and ``check_added`` drops it."""
    rng = np.random.default_rng(1)
    H, W, T = 80, 100, 3
    v, u = np.mgrid[0:H, 0:W]
    disks = np.stack([(u - 40 - 3 * t) ** 2 + (v - 40) ** 2 < 14**2 for t in range(T)])
    strip = (u >= 57) & (u < 62) & (v >= 30) & (v < 50) & ~disks[1]
    images = _green(rng, (T, H, W))
    for t in range(T):
        images[t][disks[t]] = _red(rng, disks[t].sum())
    images[1][strip] = _red(rng, strip.sum())
    flows = np.zeros((T, H, W, 2), np.float32)
    flows[..., 0] = np.where(disks, 3.0, -3.0)
    flows += rng.normal(0, 0.1, flows.shape).astype(np.float32)
    run = lambda check: refine.refine_and_track(  # noqa: E731
        images, flows, np.ones((T, H, W), bool), lambda t: disks[0] if t == 0 else np.zeros((H, W), bool),
        refine.GrabCutRefiner(reference_width=W), cfg=refine.TrackConfig(grow=False, new_region_frac=2.0,
                                                                           check_added=check))[0]
    checked, loose = run(True), run(False)
    iou = lambda a, b: (a & b).sum() / (a | b).sum()  # noqa: E731
    assert loose[1, strip].mean() > 0.8  # the check below can fail: without it the strip joins the mask
    assert checked[1, strip].mean() < 0.1 and iou(checked[1], disks[1]) > 0.9


def test_refine_sequence_snaps_the_cue_masks_and_keeps_empty_frames_empty():
    images, flows, truth, _ = _moving_disk(4)
    coarse = np.stack([refine._dilate(truth[t], 4) for t in range(4)])
    coarse[3] = False  # the cue found nothing in the last frame
    g = refine.GrabCutRefiner(reference_width=100)
    out = refine.refine_sequence(images, flows[:3], coarse, g)
    iou = lambda a, b: (a & b).sum() / (a | b).sum()  # noqa: E731
    for t in range(3):
        assert iou(out[t], truth[t]) > 0.9 > iou(coarse[t], truth[t])
    assert not out[3].any()
    assert not refine.refine_sequence(images, flows, np.zeros_like(coarse), g).any()  # a static scene
    with pytest.raises(ValueError, match="flows"):
        refine.refine_sequence(images, flows[:, :10], coarse, g)


def _track_problem(seed=0):
    """Landmark tracks (2 seeding blocks at frames 0 and 2, 4 observations each) of a static scene
    seen by 6 cameras with exact poses, lifted with per-frame perturbed prior poses; block 1 also
    holds movers drifting ~1.5 px per frame (about the size of the prior's pose error)."""
    rng = np.random.default_rng(seed)
    W, T, per = 6, 4, 40
    K = np.array([[110.0, 0, 63.5], [0, 110.0, 47.5], [0, 0, 1]])
    true = np.tile(np.eye(4), (W, 1, 1))
    true[:, 0, 3] = 0.05 * np.arange(W)
    from scipy.spatial.transform import Rotation

    noise = np.tile(np.eye(4), (W, 1, 1))
    noise[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.03, (W, 3))).as_matrix()
    noise[:, :3, 3] = rng.normal(0, 0.03, (W, 3))
    prior = true @ noise
    seed = np.repeat([0, 2], per)
    L = len(seed)
    uv0 = rng.uniform([10, 10], [117, 85], (L, 2))
    d = rng.uniform(2.0, 5.0, L)
    Xc = np.concatenate([uv0, np.ones((L, 1))], 1) @ np.linalg.inv(K).T * d[:, None]
    Xw = np.einsum("lij,lj->li", true[seed, :3, :3], Xc) + true[seed, :3, 3]
    lifted = np.einsum("lij,lj->li", prior[seed, :3, :3], Xc) + prior[seed, :3, 3]  # prior pose of the seed
    mover = np.zeros(L, bool)
    mover[per:per + 8] = True
    vel = np.where(mover[:, None], rng.choice([-1, 1], (L, 3)) * np.array([0.06, 0.04, 0.0]), 0.0)
    t = np.arange(T)
    pose_idx = seed[:, None] + t
    P = Xw[:, None] + vel[:, None] * t[None, :, None]
    inv = np.linalg.inv(true[pose_idx])
    pc = np.einsum("ltij,ltj->lti", inv[..., :3, :3], P) + inv[..., :3, 3]
    uv = (pc @ K.T)[..., :2] / pc[..., 2:]
    uv[:, 1:] += rng.normal(0, 0.05, (L, T - 1, 2))
    valid = np.ones((L, T), bool)
    return dict(points=lifted, poses=prior, K=np.broadcast_to(K, (W, 3, 3)), pose_idx=pose_idx.ravel(),
                uv=uv.reshape(-1, 2), valid=valid.ravel(), block=seed // 2, mover=mover, T=T)


def test_track_cue_rigid_fit_matches_opencv_pnp_and_flags_slow_movers():
    """Per (seed block, frame) the rigid correction is a least-squares pose fit: on a static group its
    residuals equal those of OpenCV's iterative PnP on the same points; tracks on slow movers (which
    the two-frame residual flow cannot separate from the prior's pose error) are flagged, no others."""
    import cv2

    p = _track_problem()
    cfg = motion.MotionConfig()

    def run(points, poses, K, pose_idx, uv, valid, block):
        r, judged = motion.track_residuals(points, poses, K, pose_idx, uv, valid, block, 2, cfg)
        return (r, judged), motion.moving_from_residuals(r, judged, points.shape[0], cfg)

    run = jax.jit(run, compiler_options={"xla_backend_optimization_level": 0})  # tiny: compile time dominates
    (r, judged), moving = run(*(jnp.asarray(p[k], jnp.float32 if p[k].dtype == np.float64 else None)
                                for k in ("points", "poses", "K", "pose_idx", "uv", "valid", "block")))
    r, judged, moving = np.asarray(r), np.asarray(judged), np.asarray(moving)
    np.testing.assert_array_equal(moving, p["mover"])
    T = p["T"]
    j = np.tile(np.arange(T), len(p["mover"]))
    np.testing.assert_array_equal(judged, j > 0)
    # block 0 (static), frame 3: OpenCV's PnP on the landmarks' prior camera points
    sel = (np.repeat(p["block"], T) == 0) & (p["pose_idx"] == 3)
    inv = np.linalg.inv(p["poses"][3])
    obj = p["points"][np.repeat(np.arange(len(p["mover"])), T)[sel]] @ inv[:3, :3].T + inv[:3, 3]
    img = p["uv"][sel]
    ok, rvec, tvec = cv2.solvePnP(obj, img, p["K"][0], None, np.zeros(3), np.zeros(3), True, cv2.SOLVEPNP_ITERATIVE)
    assert ok
    proj, _ = cv2.projectPoints(obj, rvec, tvec, p["K"][0], None)
    # Geman-McClure weights at the 0.25 px scale floor on 0.05 px noise: nearly least squares
    np.testing.assert_allclose(r[sel], proj[:, 0] - img, atol=5e-3)
    assert np.sqrt(np.mean(np.sum(r[sel] ** 2, -1))) < 0.1  # the pose error (tens of px) is explained
    # the cue can be switched off; too few observations for a rigid fit is a config error
    assert not np.any(np.asarray(motion.moving_tracks(*(jnp.asarray(p[k]) for k in (
        "points", "poses", "K", "pose_idx", "uv", "valid", "block")), 2, dataclasses.replace(cfg, track_cue=False))))
    with pytest.raises(ValueError, match="track_min_obs"):
        motion.MotionConfig(track_min_obs=3)


def test_the_pipelines_mask_stream_equals_refine_sequence():
    """:class:`cm3d.pipeline.run.MaskStream` refines a sequence piece by piece in its thread (padded
    last piece, the last frame's flow slot holding the reversed pair as in the pipeline's inputs):
    bitwise :func:`refine.refine_sequence`'s masks, whatever state earlier OpenCV calls left the
    calling thread's random generator in (GrabCut's colour models start from it)."""
    from types import SimpleNamespace

    import cv2

    from cm3d.pipeline.run import MaskStream

    cv2.randu(np.zeros((7, 1), np.float32), 0.0, 1.0)  # advance this thread's generator

    S, size = 7, 3
    images, flows, truth, _ = _moving_disk(S)
    coarse = np.stack([refine._dilate(truth[t], 4) for t in range(S)])
    coarse[5] = False
    ref = refine.refine_sequence(images, flows[:S - 1], coarse)
    flows[S - 1] = -flows[S - 2]  # the pipeline's last frame: its pair with S-2, reversed
    pad = lambda a: np.concatenate([a, np.repeat(a[-1:], 9 - S, axis=0)])  # noqa: E731
    img_p, flow_p, mask_p = pad(images), pad(flows), pad(coarse)
    mask_p[S:] = True  # padding frames are never read
    stream = MaskStream(SimpleNamespace(depth=np.zeros((S,) + coarse.shape[1:])), SimpleNamespace(stride=1))
    for first in range(0, 9, size):
        sl = slice(first, first + size)
        stream.add(first, SimpleNamespace(num_frames=size, flow=flow_p[sl], frame=SimpleNamespace(image=img_p[sl])),
                   mask_p[sl])
    out = stream.result()
    np.testing.assert_array_equal(out, ref)
    iou = lambda a, b: (a & b).sum() / (a | b).sum()  # noqa: E731
    assert iou(out[2], truth[2]) > 0.8 and not out[5].any()
