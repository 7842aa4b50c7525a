"""A procedural, seeded world with full ground truth: the embedded default and the test bed.

A *scene* is a room (an inward-facing box) with static boxes; a *visit* adds a smooth camera
trajectory and moving boxes/spheres with their own rigid motions. Every surface carries a solid
3D texture (value noise plus crisp spots) defined in its object's own frame, so moving textures
move with their objects and OpenCV flow / keypoints work on the renders. Frames are ray-cast in
JAX (one compiled program for every scene and visit of the same image size) with supersampling.

World frame: metres, ``z`` up, floor at ``z = 0``. Cameras follow :mod:`cm3d.ops.camera`.

Ground truth per frame: RGB, depth (camera z at the pixel centre), intrinsics, cam_to_world,
dynamic mask (pixel centre on a moving object), forward flow to the next frame (where each pixel's
surface point is at ``t + 1``, occlusions ignored, as in Sintel), and static world points (derived,
:meth:`cm3d.data.GroundTruth.static_points`).

:func:`make_priors` turns ground truth into VGGT-like priors with the one prior model of
:mod:`cm3d.data.priors`: a per-sequence unknown scale and first-camera frame, depth scale jitter /
smooth bias / noise, a confidence map, and pose noise and drift at the named :data:`NOISE_LEVELS`.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from cm3d.data import priors
from cm3d.data.sequence import GroundTruth, Sequence

ROOM, BOX, SPHERE, EMPTY = 0, 1, 2, -1
MAX_PRIMITIVES = 16

NOISE_LEVELS, DEPTH_NOISE = priors.NOISE_LEVELS, priors.DEPTH_NOISE  # the prior model's levels


@dataclasses.dataclass(frozen=True)
class WorldConfig:
    """Static rendering and world options (all shape-affecting)."""

    height: int = 384
    width: int = 512
    fov_deg: float = 60.0  # horizontal field of view
    fps: float = 10.0
    mover_speed: float = 1.0  # the moving objects' clock against the camera's (0.1: ten times slower; 0: still)
    supersample: int = 2  # s x s rays per pixel for the RGB image
    num_static_boxes: int = 5
    num_moving: int = 3


@dataclasses.dataclass(frozen=True)
class Primitives:
    """Padded primitive table (numpy). Poses are object_to_world per frame: (S, P, 4, 4)."""

    kind: np.ndarray  # (P,) int32: ROOM, BOX, SPHERE or EMPTY
    size: np.ndarray  # (P, 3) half extents (sphere: radius in [0])
    color: np.ndarray  # (P, 3) base RGB in [0, 1]
    color2: np.ndarray  # (P, 3) RGB of faces whose object-frame normal is along z (floor, ceiling, tops)
    style: np.ndarray  # (P, 2) texture frequency scale and spot threshold
    seed: np.ndarray  # (P,) int32 texture seed
    moving: np.ndarray  # (P,) bool
    pose: np.ndarray  # (S, P, 4, 4)


@dataclasses.dataclass(frozen=True)
class Scene:
    """The static part of a world: room extents and static boxes (numpy)."""

    seed: int
    room_half: np.ndarray  # (3,) half extents of the room, centred at (0, 0, h_z)
    kind: np.ndarray
    size: np.ndarray
    color: np.ndarray
    color2: np.ndarray
    style: np.ndarray
    tex_seed: np.ndarray
    pose: np.ndarray  # (P_static, 4, 4)


def intrinsics(cfg: WorldConfig) -> np.ndarray:
    """Pinhole K (3, 3) for the configured size and horizontal field of view."""
    f = 0.5 * cfg.width / np.tan(np.deg2rad(cfg.fov_deg) / 2)
    return np.array([[f, 0, (cfg.width - 1) / 2], [0, f, (cfg.height - 1) / 2], [0, 0, 1.0]])


def _pose(R, t):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _rot_axis(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _palette(rng, n, sat=(0.2, 0.85), val=(0.5, 0.95)):
    """n random RGB colours (n, 3) from hue/saturation/value ranges."""
    import colorsys

    return np.array([colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(*sat), rng.uniform(*val)) for _ in range(n)])


def _styles(rng, n):
    """Texture styles (n, 2): frequency scale and spot threshold (spot density)."""
    return np.stack([rng.uniform(0.6, 1.6, n), rng.uniform(0.62, 0.8, n)], -1)


def make_scene(seed: int, cfg: WorldConfig = WorldConfig()) -> Scene:
    """A room of random size, palette and texture style with static boxes along its walls."""
    rng = np.random.default_rng([seed, 0])
    half = np.array([rng.uniform(3.0, 5.0), rng.uniform(2.5, 4.0), rng.uniform(1.3, 1.75)])
    kind, size, color, tex, pose = [ROOM], [half], [_palette(rng, 1)[0]], [], []
    pose.append(_pose(np.eye(3), [0, 0, half[2]]))
    for _ in range(cfg.num_static_boxes):
        h = rng.uniform([0.25, 0.25, 0.2], [0.7, 0.6, 0.9])
        wall = rng.integers(4)
        along = rng.uniform(-0.75, 0.75)
        gap = rng.uniform(0.05, 0.4)
        x = along * half[0] if wall < 2 else (1 if wall == 2 else -1) * (half[0] - h[0] - gap)
        y = (1 if wall == 0 else -1) * (half[1] - h[1] - gap) if wall < 2 else along * half[1]
        kind.append(BOX), size.append(h), color.append(_palette(rng, 1, val=(0.3, 1.0))[0])
        pose.append(_pose(_rot_z(rng.uniform(-0.3, 0.3)), [x, y, h[2]]))
    tex = rng.integers(0, 2**20, len(kind))
    color2 = _palette(rng, len(kind), val=(0.35, 0.95))
    return Scene(seed, half, np.array(kind, np.int32), np.array(size), np.array(color), color2,
                 _styles(rng, len(kind)), tex.astype(np.int32), np.array(pose))


def _look(position, yaw, pitch, roll):
    """cam_to_world of a camera at ``position`` looking along yaw/pitch (radians), rolled."""
    f = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    right = np.cross(f, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    R = np.stack([right, down, f], axis=1) @ _rot_axis([0, 0, 1], roll)
    return _pose(R, position)


#: a revisit (:func:`camera_trajectory`'s ``near``): the largest shift of the path's centre, in units of the
#: room's free half-size, and the largest turn of its starting view
REVISIT_SHIFT = 0.25
REVISIT_TURN_DEG = 30.0


def _path_draws(scene: Scene, visit: int, free: np.ndarray):
    """A visit's seeded path parameters: centre, amplitudes, frequencies, phases, start yaw, yaw rate."""
    rng = np.random.default_rng([scene.seed, visit, 1])
    centre = rng.uniform(-0.5, 0.5, 2) * free
    amp = rng.uniform(0.3, 0.6, 2) * np.minimum(free, 1.0) + 0.1
    w, ph = rng.uniform(0.25, 0.5, 2), rng.uniform(0, 2 * np.pi, 2)
    yaw0, yaw_rate = rng.uniform(0, 2 * np.pi), rng.choice([-1, 1]) * rng.uniform(0.1, 0.2)
    return centre, amp, w, ph, yaw0, yaw_rate


def camera_trajectory(scene: Scene, visit: int, num_frames: int, cfg: WorldConfig, loop: bool = False,
                      near: int | None = None) -> np.ndarray:
    """A smooth, rotating camera path (S, 4, 4) inside the free middle of the room.

    loop: a closed path instead (same scene-dependent centre, amplitudes and start): one cycle of
    the position, the view turning away by up to ``loop_turn`` (~115°) and back, so the last frames
    revisit the first frames' place and view (the last pose equals the first).

    near: a revisit of visit ``near``'s place: its path's centre is that visit's, moved by up to a
    quarter of the free half-size, and its starting view is that visit's, turned by up to 30° about
    the vertical (:data:`REVISIT_SHIFT`, :data:`REVISIT_TURN_DEG`); amplitudes, frequencies, phases and
    turning direction stay this visit's own. Without it, two visits of a short path may look at opposite
    halves of the room and share no surface."""
    t = np.arange(num_frames) / cfg.fps
    free = scene.room_half[:2] - 1.6
    centre, amp, w, ph, yaw0, yaw_rate = _path_draws(scene, visit, free)
    if near is not None and near != visit:
        base_centre, *_, base_yaw0, _ = _path_draws(scene, near, free)
        own = np.random.default_rng([scene.seed, visit, 5])
        centre = np.clip(base_centre + own.uniform(-REVISIT_SHIFT, REVISIT_SHIFT, 2) * free, -0.5 * free, 0.5 * free)
        yaw0 = base_yaw0 + np.deg2rad(own.uniform(-REVISIT_TURN_DEG, REVISIT_TURN_DEG))
    if loop:
        loop_turn = 2.0
        u = np.arange(num_frames) / max(num_frames - 1, 1)  # 0 .. 1, the path's phase
        poses = []
        for ui in u:
            a = 2 * np.pi * ui
            xy = centre + amp * np.sin(a + ph)
            z = 1.45 + 0.1 * np.sin(a + ph[0])
            yaw = yaw0 + np.sign(yaw_rate) * loop_turn * np.sin(np.pi * ui)
            pitch = -0.3 + 0.06 * np.sin(a + ph[1])
            roll = 0.04 * np.sin(2 * a)
            poses.append(_look(np.array([*xy, z]), yaw, pitch, roll))
        return np.array(poses)
    poses = []
    for ti in t:
        xy = centre + amp * np.sin(w * ti + ph)
        z = 1.45 + 0.1 * np.sin(0.7 * ti + ph[0])
        yaw = yaw0 + yaw_rate * ti + 0.08 * np.sin(0.9 * ti)
        pitch = -0.3 + 0.06 * np.sin(0.6 * ti + ph[1])
        roll = 0.04 * np.sin(0.8 * ti)
        poses.append(_look(np.array([*xy, z]), yaw, pitch, roll))
    return np.array(poses)


def moving_objects(scene: Scene, visit: int, cams: np.ndarray, cfg: WorldConfig):
    """Moving boxes and spheres for one visit, placed ahead of the camera:
    (kind, size, color, seed, pose (S,M,4,4)); their colour2 / style come from :func:`assemble`."""
    rng = np.random.default_rng([scene.seed, visit, 2])
    S = len(cams)
    t = np.arange(S) / cfg.fps * cfg.mover_speed
    mid = cams[S // 2]
    kinds, sizes, colors, seeds, poses = [], [], [], [], []
    for k in range(cfg.num_moving):
        kind = BOX if rng.random() < 0.5 else SPHERE
        size = rng.uniform(0.2, 0.4, 3) if kind == BOX else np.full(3, rng.uniform(0.2, 0.35))
        bearing = (k - (cfg.num_moving - 1) / 2) * 0.45 + rng.uniform(-0.1, 0.1)
        fwd = mid[:3, 2].copy()
        fwd[2] = 0
        fwd /= np.linalg.norm(fwd)
        d = _rot_z(bearing) @ fwd * rng.uniform(2.0, 3.2)
        base = mid[:3, 3] + d
        base[:2] = np.clip(base[:2], -scene.room_half[:2] + 0.8, scene.room_half[:2] - 0.8)
        amp, w, ph = rng.uniform(0.3, 0.6, 2), rng.uniform(0.6, 1.2), rng.uniform(0, 2 * np.pi)
        spin, tilt = rng.uniform(-1.2, 1.2), rng.normal(size=3)
        lift = size[2] + rng.uniform(0.0, 0.5)
        per_frame = []
        for ti in t:
            xy = base[:2] + amp * np.array([np.sin(w * ti + ph), np.sin(0.7 * w * ti + 2 * ph)])
            z = lift + 0.15 * np.sin(1.3 * w * ti + ph)
            R = _rot_z(spin * ti + ph) @ _rot_axis(tilt, 0.3 * np.sin(w * ti))
            per_frame.append(_pose(R, [*xy, z]))
        kinds.append(kind), sizes.append(size), colors.append(rng.uniform(0.2, 1.0, 3))
        seeds.append(rng.integers(0, 2**20)), poses.append(per_frame)
    poses = np.array(poses).transpose(1, 0, 2, 3) if poses else np.zeros((S, 0, 4, 4))
    return np.array(kinds, np.int32), np.array(sizes), np.array(colors), np.array(seeds, np.int32), poses


def assemble(scene: Scene, visit: int, cams: np.ndarray, cfg: WorldConfig) -> Primitives:
    """Static and moving primitives, padded to :data:`MAX_PRIMITIVES`."""
    mk, ms, mc, mseed, mpose = moving_objects(scene, visit, cams, cfg)
    rng = np.random.default_rng([scene.seed, visit, 4])
    S, Ps = len(cams), len(scene.kind)
    P = Ps + len(mk)
    if P > MAX_PRIMITIVES:
        raise ValueError(f"{P} primitives exceed MAX_PRIMITIVES={MAX_PRIMITIVES}")
    pad = MAX_PRIMITIVES - P
    kind = np.concatenate([scene.kind, mk, np.full(pad, EMPTY, np.int32)])
    size = np.concatenate([scene.size, ms.reshape(-1, 3), np.ones((pad, 3))])
    color = np.concatenate([scene.color, mc.reshape(-1, 3), np.zeros((pad, 3))])
    color2 = np.concatenate([scene.color2, _palette(rng, len(mk)).reshape(-1, 3), np.zeros((pad, 3))])
    style = np.concatenate([scene.style, _styles(rng, len(mk)).reshape(-1, 2), np.ones((pad, 2))])
    seed = np.concatenate([scene.tex_seed, mseed, np.zeros(pad, np.int32)])
    moving = np.concatenate([np.zeros(Ps, bool), np.ones(len(mk), bool), np.zeros(pad, bool)])
    static_pose = np.broadcast_to(scene.pose, (S, Ps, 4, 4))
    pose = np.concatenate([static_pose, mpose, np.broadcast_to(np.eye(4), (S, pad, 4, 4))], 1)
    return Primitives(kind, size, color, color2, style, seed, moving, pose)


# ----------------------------------------------------------------------------------------------
# Ray casting (JAX)


def _hash(ix, iy, iz, seed):
    """Integer lattice hash -> uniform [0, 1)."""
    u = lambda a: (a + (1 << 20)).astype(jnp.uint32)  # noqa: E731  (shift negatives, then wrap)
    h = u(ix) * jnp.uint32(0x8DA6B343) ^ u(iy) * jnp.uint32(0xD8163841)
    h = h ^ u(iz) * jnp.uint32(0xCB1AB31F) ^ seed.astype(jnp.uint32) * jnp.uint32(0x165667B1)
    h = (h ^ (h >> 15)) * jnp.uint32(0x2C1B3C6D)
    h = (h ^ (h >> 12)) * jnp.uint32(0x297A2D39)
    h = h ^ (h >> 15)
    return (h >> 8).astype(jnp.float32) / float(1 << 24)


def value_noise(p, seed):
    """Smooth 3D value noise in [0, 1] at points (..., 3) with per-point seeds (...)."""
    i = jnp.floor(p)
    f = p - i
    w = f * f * (3 - 2 * f)
    i = i.astype(jnp.int32)
    out = 0.0
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                h = _hash(i[..., 0] + dx, i[..., 1] + dy, i[..., 2] + dz, seed)
                wx = w[..., 0] if dx else 1 - w[..., 0]
                wy = w[..., 1] if dy else 1 - w[..., 1]
                wz = w[..., 2] if dz else 1 - w[..., 2]
                out = out + h * wx * wy * wz
    return out


def texture(p_local, seed, base_color, style):
    """Solid texture colour (..., 3): octaves of value noise, crisp spots and a colour wobble;
    ``style`` (..., 2) scales the frequencies and sets the spot threshold."""
    n = 0.0
    p = p_local * style[..., :1]
    for k, (freq, amp) in enumerate([(2.5, 0.35), (7.0, 0.3), (16.0, 0.25), (36.0, 0.15)]):
        n = n + amp * value_noise(p * freq, seed + 7919 * k)
    spots = value_noise(p * 18.0, seed + 104729)
    spots = jnp.clip((spots - style[..., 1]) / 0.04, 0.0, 1.0)
    hue = value_noise(p_local * 1.2, seed + 31)[..., None]
    col = (hue * base_color + (1 - hue) * base_color[..., ::-1]) * (0.25 + 1.0 * n[..., None])
    return col * (1.0 - 0.7 * spots[..., None]) + 0.3 * spots[..., None] * (1.0 - base_color)


def _intersect(o, d, kind, size, obj_to_world):
    """Ray (..., 3) hits against every primitive: distances (..., P) (inf when missed)."""
    R, c = obj_to_world[:, :3, :3], obj_to_world[:, :3, 3]  # (P, 3, 3), (P, 3)
    ol = jnp.einsum("pji,...pj->...pi", R, o[..., None, :] - c)
    dl = jnp.einsum("pji,...j->...pi", R, d)
    safe = jnp.where(jnp.abs(dl) < 1e-12, 1e-12, dl)
    t1, t2 = (-size - ol) / safe, (size - ol) / safe
    tmin = jnp.max(jnp.minimum(t1, t2), -1)
    tmax = jnp.min(jnp.maximum(t1, t2), -1)
    eps = 1e-4
    t_box = jnp.where((tmax >= tmin) & (tmin > eps), tmin, jnp.inf)
    t_room = jnp.where(tmax > eps, tmax, jnp.inf)
    r = size[:, 0]
    a = jnp.sum(dl * dl, -1)
    b = jnp.sum(ol * dl, -1)
    cc = jnp.sum(ol * ol, -1) - r * r
    disc = b * b - a * cc
    t_sph = (-b - jnp.sqrt(jnp.maximum(disc, 0.0))) / a
    t_sph = jnp.where((disc > 0) & (t_sph > eps), t_sph, jnp.inf)
    t = jnp.select([kind == ROOM, kind == BOX, kind == SPHERE], [t_room, t_box, t_sph], jnp.inf)
    return t


def _shade(x, obj, prim, obj_to_world):
    """Lambert-shaded texture colour (..., 3) at world hit points ``x`` on objects ``obj``."""
    T = obj_to_world[obj]
    pl = jnp.einsum("...ji,...j->...i", T[..., :3, :3], x - T[..., :3, 3])
    kind, size = prim["kind"][obj], prim["size"][obj]
    rel = jnp.abs(pl) / size
    axis = jnp.argmax(rel, -1)
    n_box = jax.nn.one_hot(axis, 3) * jnp.sign(jnp.take_along_axis(pl, axis[..., None], -1))
    n_box = jnp.where((kind == ROOM)[..., None], -n_box, n_box)
    n_sph = pl / jnp.linalg.norm(pl, axis=-1, keepdims=True)
    nl = jnp.where((kind == SPHERE)[..., None], n_sph, n_box)
    n = jnp.einsum("...ij,...j->...i", T[..., :3, :3], nl)
    light = jnp.array([0.4, 0.25, 0.88])
    light = light / jnp.linalg.norm(light)
    lambert = 0.45 + 0.55 * jnp.abs(jnp.sum(n * light, -1))
    horizontal = (jnp.abs(nl[..., 2]) > 0.5) & (kind != SPHERE)
    base = jnp.where(horizontal[..., None], prim["color2"][obj], prim["color"][obj])
    col = texture(pl, prim["seed"][obj], base, prim["style"][obj])
    return jnp.clip(col * lambert[..., None], 0.0, 1.0)


@functools.partial(jax.jit, static_argnames=("height", "width", "supersample"))
def _render(prim, K, cams, cams_next, pose, pose_next, *, height, width, supersample):
    """Render frames: rgb (S,H,W,3) float, depth, object id, flow (S,H,W,2) to the next frame."""
    Kinv = jnp.linalg.inv(K)
    v, u = jnp.meshgrid(jnp.arange(height, dtype=jnp.float32), jnp.arange(width, dtype=jnp.float32),
                        indexing="ij")
    s = supersample
    offs = (jnp.arange(s, dtype=jnp.float32) + 0.5) / s - 0.5
    ou, ov = jnp.meshgrid(offs, offs)
    sub = jnp.stack([ou.ravel(), ov.ravel()], -1)  # (s*s, 2)

    def frame(args):
        c2w, c2w_next, T, T_next = args
        o = c2w[:3, 3]

        def cast(uu, vv):
            ray_c = jnp.stack([uu, vv, jnp.ones_like(uu)], -1) @ Kinv.T  # camera z = 1
            d = ray_c @ c2w[:3, :3].T
            t = _intersect(o, d, prim["kind"], prim["size"], T)
            obj = jnp.argmin(t, -1)
            tt = jnp.min(t, -1)
            return o + tt[..., None] * d, obj, tt

        rgb = 0.0
        for k in range(s * s):
            x, obj, _ = cast(u + sub[k, 0], v + sub[k, 1])
            rgb = rgb + _shade(x, obj, prim, T) / (s * s)
        x, obj, depth = cast(u, v)
        # Ground-truth flow: carry the surface point with its object to t+1, project there.
        Tobj, Tobj_next = T[obj], T_next[obj]
        pl = jnp.einsum("...ji,...j->...i", Tobj[..., :3, :3], x - Tobj[..., :3, 3])
        x_next = jnp.einsum("...ij,...j->...i", Tobj_next[..., :3, :3], pl) + Tobj_next[..., :3, 3]
        xc = (x_next - c2w_next[:3, 3]) @ c2w_next[:3, :3]
        uv = (xc @ K.T)[..., :2] / xc[..., 2:3]
        flow = uv - jnp.stack([u, v], -1)
        return rgb, depth, obj, flow

    return jax.lax.map(frame, (cams, cams_next, pose, pose_next))


RENDER_BLOCK = 8  # frames per call of the compiled renderer


def render(prims: Primitives, cams: np.ndarray, cfg: WorldConfig):
    """Ray-cast a visit: (rgb uint8 (S,H,W,3), depth (S,H,W), object id (S,H,W), flow (S-1,H,W,2))."""
    K = intrinsics(cfg)
    prim = {k: jnp.asarray(getattr(prims, k)) for k in ("kind", "seed")}
    prim |= {k: jnp.asarray(getattr(prims, k), jnp.float32) for k in ("size", "color", "color2", "style")}
    cams_next = np.concatenate([cams[1:], cams[-1:]])
    pose_next = np.concatenate([prims.pose[1:], prims.pose[-1:]])
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    # Fixed blocks of RENDER_BLOCK frames (the last one padded with its final frame): one compiled
    # renderer per image size serves every sequence length (frames are rendered independently).
    n = len(cams)
    pad = lambda a: np.concatenate([a, np.repeat(a[-1:], -n % RENDER_BLOCK, 0)])  # noqa: E731
    args = [pad(np.asarray(a)) for a in (cams, cams_next, prims.pose, pose_next)]
    parts = [_render(prim, f32(K), *(f32(a[b:b + RENDER_BLOCK]) for a in args), height=cfg.height,
                     width=cfg.width, supersample=cfg.supersample) for b in range(0, n, RENDER_BLOCK)]
    rgb, depth, obj, flow = (np.concatenate([np.asarray(p[i]) for p in parts])[:n] for i in range(4))
    rgb = np.round(rgb * np.float32(255.0)).astype(np.uint8)
    return rgb, depth, obj, flow[:-1]


def render_ground_truth(scene: Scene, visit: int, num_frames: int, cfg: WorldConfig = WorldConfig(),
                        loop: bool = False, near: int | None = None):
    """Images (S,H,W,3) uint8 and :class:`GroundTruth` of one visit of a scene (``loop``: the closed
    camera path, ``near``: a revisit of that visit's place; :func:`camera_trajectory`)."""
    cams = camera_trajectory(scene, visit, num_frames, cfg, loop=loop, near=near)
    prims = assemble(scene, visit, cams, cfg)
    rgb, depth, obj, flow = render(prims, cams, cfg)
    K = np.broadcast_to(intrinsics(cfg), (num_frames, 3, 3)).copy()
    gt = GroundTruth(cam_to_world=cams, depth=depth, intrinsic=K,
                     dynamic_mask=prims.moving[obj], flow=flow)
    return rgb, gt


# ----------------------------------------------------------------------------------------------
# Prior model: the one implementation lives in :mod:`cm3d.data.priors`


def make_priors(images, gt: GroundTruth, level: str = "moderate", seed: int = 0,
                timestamps=None, meta=None, drift: float = 1.0) -> Sequence:
    """VGGT-like priors from ground truth: :func:`cm3d.data.priors.make_priors` (first camera's
    frame, unknown scale, depth jitter / bias / noise, confidence, pose noise and drift at the named
    :data:`NOISE_LEVELS`)."""
    return priors.make_priors(images, gt, level, seed, timestamps=timestamps, meta=meta, drift=drift)


def generate(scene_seed: int = 0, visit: int = 0, num_frames: int = 30, level: str = "moderate",
             cfg: WorldConfig = WorldConfig()) -> Sequence:
    """One visit of one scene with VGGT-like priors and ground truth."""
    scene = make_scene(scene_seed, cfg)
    images, gt = render_ground_truth(scene, visit, num_frames, cfg)
    meta = {"source": "synthetic", "scene": scene_seed, "visit": visit}
    return make_priors(images, gt, level, seed=scene_seed * 1009 + visit,
                       timestamps=np.arange(num_frames) / cfg.fps, meta=meta)


def generate_world(scene_seed: int = 0, num_visits: int = 3, num_frames: int = 30,
                   level: str = "moderate", cfg: WorldConfig = WorldConfig()) -> list[Sequence]:
    """Several visits of the same static scene (different cameras and moving objects)."""
    return [generate(scene_seed, v, num_frames, level, cfg) for v in range(num_visits)]


# ----------------------------------------------------------------------------------------------
# Long videos in overlapping chunks (VGGT run chunk by chunk)


def chunk_ranges(num_frames: int, chunk_size: int, overlap: int) -> list[tuple[int, int]]:
    """Frame ranges ``[(start, stop), ...]`` of chunks of ``chunk_size`` frames, consecutive chunks
    sharing ``overlap`` frames, covering ``0 .. num_frames - 1``; the last chunk may be shorter
    (but holds at least one frame beyond its overlap)."""
    if not 0 < overlap < chunk_size:
        raise ValueError(f"overlap: must be in [1, chunk_size - 1] = [1, {chunk_size - 1}], got {overlap}")
    if num_frames < chunk_size:
        raise ValueError(f"num_frames: {num_frames} is fewer than one chunk of {chunk_size} frames")
    ranges, start = [], 0
    while True:
        stop = min(start + chunk_size, num_frames)
        ranges.append((start, stop))
        if stop == num_frames:
            return ranges
        start = stop - overlap


def make_chunk_priors(images, gt: GroundTruth, chunk_size: int = 40, overlap: int = 10,
                      level: str = "moderate", seed: int = 0, timestamps=None, meta=None,
                      drift: float = 1.0) -> list[Sequence]:
    """Split one long rendered video into overlapping chunks, each with its own VGGT-like prior
    (:func:`cm3d.data.priors.segment_priors`: its own unknown scale, its first camera as the frame,
    its own depth and pose noise), as VGGT gives when run chunk by chunk. Ground truth stays in the
    common metric world frame; timestamps are global (default: frame index); ``drift``: see
    :func:`cm3d.data.priors.make_priors`."""
    return priors.segment_priors(images, gt, chunk_ranges(len(images), chunk_size, overlap), level, seed,
                                 timestamps=timestamps, meta=meta, drift=drift)


def generate_long_video(scene_seed: int = 0, visit: int = 0, num_frames: int = 200, chunk_size: int = 40,
                        overlap: int = 10, level: str = "moderate",
                        cfg: WorldConfig = WorldConfig(height=96, width=128), loop: bool = False,
                        drift: float = 1.0):
    """One long visit rendered once and split into overlapping VGGT-like chunks.

    loop: the camera comes back to its start (:func:`camera_trajectory`), so the last chunk revisits
    the first chunk's place; drift: the priors' drift factor (:func:`make_priors`). Returns (chunks:
    list of :class:`Sequence`, images (S, H, W, 3) uint8, ground truth of the whole video). 200
    frames at 96x128 render in ~12 s on 2 CPU cores (192x256: ~90 s).
    """
    scene = make_scene(scene_seed, cfg)
    images, gt = render_ground_truth(scene, visit, num_frames, cfg, loop=loop)
    meta = {"source": "synthetic", "scene": scene_seed, "visit": visit}
    chunks = make_chunk_priors(images, gt, chunk_size, overlap, level, seed=scene_seed * 1009 + visit,
                               timestamps=np.arange(num_frames) / cfg.fps, meta=meta, drift=drift)
    return chunks, images, gt


def room_cloud(n: int, seed: int = 0, size=(4.0, 3.0, 2.5), boxes=()) -> np.ndarray:
    """A room-like point cloud (n, 3) float32 for registration tests and benchmarks: floor,
    ceiling, four walls and axis-aligned boxes ``(x, y, a, b, h)`` (corner, footprint, height),
    sampled uniformly by area with 3 mm Gaussian noise."""
    rng = np.random.default_rng(seed)
    L, W, H = size
    rects = [((0, 0, 0), (L, 0, 0), (0, W, 0)), ((0, 0, H), (L, 0, 0), (0, W, 0)), ((0, 0, 0), (L, 0, 0), (0, 0, H)),
             ((0, W, 0), (L, 0, 0), (0, 0, H)), ((0, 0, 0), (0, W, 0), (0, 0, H)), ((L, 0, 0), (0, W, 0), (0, 0, H))]
    for (x, y, a, b, h) in boxes:
        rects += [((x, y, h), (a, 0, 0), (0, b, 0)), ((x, y, 0), (a, 0, 0), (0, 0, h)), ((x, y + b, 0), (a, 0, 0), (0, 0, h)),
                  ((x, y, 0), (0, b, 0), (0, 0, h)), ((x + a, y, 0), (0, b, 0), (0, 0, h))]
    o, u, v = (np.array([r[i] for r in rects], float) for i in range(3))
    area = np.linalg.norm(np.cross(u, v), axis=1)
    k = rng.choice(len(rects), n, p=area / area.sum())
    st = rng.random((n, 2))
    return (o[k] + st[:, :1] * u[k] + st[:, 1:] * v[k] + rng.normal(scale=0.003, size=(n, 3))).astype(np.float32)
