"""A second, independently written synthetic world: a held-out check only. NEVER TUNE ON IT.

No threshold, default or design choice of cm3d may be fitted, chosen or "sanity checked until it
looks right" on this world: it exists to measure how cm3d behaves on a world it was not built
against (``experiments/held_out_world.py``). It shares nothing with :mod:`cm3d.data.synthetic`
except the prior model (:mod:`cm3d.data.priors`, the one implementation) and the
:class:`~cm3d.data.Sequence` / :class:`~cm3d.data.GroundTruth` containers (no code, no
primitive, texture or path of synthetic.py is reused). It is deliberately different:

- **enclosure**: a convex polygonal hall (5-7 vertical walls of random length, floor, ceiling)
  instead of a box room;
- **primitives**: vertical cylinders (pillars, barrels), spheres, thin poles (2-4 cm), and objects
  close to the camera (0.8-1.2 m); no boxes;
- **texture**: object-space sums of 3D sinusoidal gratings mixing two colours, with cellular
  dots (one hashed feature point per grid cell) and thin dark grid lines; not value noise;
- **movers**: one that enters and leaves the view (crossing the frustum), one slow mover
  (3 cm/s), one sphere rotating in place (its pixels move, its centre does not);
- **camera paths**: visit 0 a lateral dolly looking at a fixed point (strong parallax, near objects
  sweep across the far walls); visit 1 a near-pure rotation (a pan of 50-70° about a point, 1 cm
  wobble) over the same area; later visits alternate;
- **lighting**: every visit has its own directional light (azimuth, elevation), intensity, ambient
  level and colour tint, so a revisit sees the same surfaces under other light.

Rendering is NumPy ray casting (analytic intersections, one ray per pixel centre for colour and
depth; ``supersample=2`` averages 2x2 colour rays at 5x the cost): 30 frames at 240x320 in about
18 s on one busy core. World frame: metres, ``z`` up, floor at
``z = 0``; cameras follow :mod:`cm3d.ops.camera` (OpenCV axes, ``cam_to_world``). Ground truth per
frame: RGB, depth, intrinsics, cam_to_world and the dynamic mask (pixels on a mover, the rotating
sphere included); no flow.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from cm3d.data import priors
from cm3d.data.sequence import GroundTruth, Sequence

SPHERE, CYLINDER = 0, 1


@dataclasses.dataclass(frozen=True)
class HeldOutConfig:
    """Image size, field of view (horizontal, degrees), frame rate and colour supersampling."""

    height: int = 240
    width: int = 320
    fov_deg: float = 70.0
    fps: float = 10.0
    supersample: int = 1


@dataclasses.dataclass(frozen=True)
class Solid:
    """A sphere or a vertical cylinder in its own frame (axis z; ``half_height`` for cylinders),
    with its texture parameters: two colours, grating directions (3, 3) / frequencies (3,) /
    phases (3,), dot cells per metre, a hash seed."""

    kind: int
    radius: float
    half_height: float
    colors: np.ndarray
    grating_dir: np.ndarray
    grating_freq: np.ndarray
    grating_phase: np.ndarray
    cells: float
    seed: int


@dataclasses.dataclass(frozen=True)
class Hall:
    """The static world: wall planes (inward normals (n, 2), offsets (n,)), ceiling height, the
    hall's own texture, static solids with their object_to_world poses, and the place the visits
    look at (centre, forward direction)."""

    seed: int
    wall_normals: np.ndarray
    wall_offsets: np.ndarray
    ceiling: float
    surface: Solid
    solids: tuple
    poses: np.ndarray
    centre: np.ndarray
    forward: np.ndarray


@dataclasses.dataclass(frozen=True)
class Lighting:
    """Directional light (unit, towards the light), intensity, ambient level, RGB tint."""

    direction: np.ndarray
    intensity: float
    ambient: float
    tint: np.ndarray


def intrinsics(cfg: HeldOutConfig) -> np.ndarray:
    f = 0.5 * cfg.width / np.tan(np.deg2rad(cfg.fov_deg) / 2)
    return np.array([[f, 0, (cfg.width - 1) / 2], [0, f, (cfg.height - 1) / 2], [0, 0, 1.0]])


def _solid(rng, kind, radius, half_height=0.0) -> Solid:
    dirs = rng.normal(size=(3, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    hue = rng.uniform(size=2)
    colors = np.stack([0.25 + 0.7 * np.abs(np.sin(np.pi * (h + np.array([0.0, 1 / 3, 2 / 3])))) for h in hue])
    colors *= rng.uniform(0.55, 1.0, (2, 1))
    return Solid(kind, float(radius), float(half_height), colors, dirs, rng.uniform(2.0, 11.0, 3),
                 rng.uniform(0, 2 * np.pi, 3), float(rng.uniform(5.0, 10.0)), int(rng.integers(1, 2**30)))


def _place(pos, yaw=0.0) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = pos
    return T


def make_hall(seed: int) -> Hall:
    """A polygonal hall with pillars, barrels, spheres, thin poles and one object near the views."""
    rng = np.random.default_rng([seed, 77])
    n = int(rng.integers(5, 8))
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False) + rng.uniform(-0.25, 0.25, n) + rng.uniform(0, 2 * np.pi)
    normals = -np.stack([np.cos(ang), np.sin(ang)], -1)  # inward
    offsets = -rng.uniform(3.8, 5.5, n)  # wall i: normals_i . xy >= offsets_i inside
    ceiling = float(rng.uniform(2.6, 3.4))
    surface = _solid(rng, -1, 0.0)
    yaw0 = rng.uniform(0, 2 * np.pi)
    fwd = np.array([np.cos(yaw0), np.sin(yaw0), 0.0])
    lat = np.array([-fwd[1], fwd[0], 0.0])
    centre = np.array([*rng.uniform(-0.4, 0.4, 2), 0.0])
    solids, poses = [], []

    def add(solid, pos):
        solids.append(solid), poses.append(_place(pos, rng.uniform(0, 2 * np.pi)))

    for _ in range(int(rng.integers(3, 5))):  # pillars and barrels ahead
        a, r = rng.uniform(-0.9, 0.9), rng.uniform(2.0, 3.3)
        h = rng.choice([ceiling / 2, rng.uniform(0.3, 0.7)])
        p = centre + r * (np.cos(a) * fwd + np.sin(a) * lat)
        add(_solid(rng, CYLINDER, rng.uniform(0.15, 0.45), h), p + [0, 0, h])
    for _ in range(int(rng.integers(3, 5))):  # thin poles, floor to ceiling
        a, r = rng.uniform(-0.8, 0.8), rng.uniform(1.6, 3.2)
        p = centre + r * (np.cos(a) * fwd + np.sin(a) * lat)
        add(_solid(rng, CYLINDER, rng.uniform(0.02, 0.04), ceiling / 2), p + [0, 0, ceiling / 2])
    for _ in range(2):  # spheres on the floor
        a, r, rad = rng.uniform(-1.0, 1.0), rng.uniform(2.2, 3.3), rng.uniform(0.2, 0.45)
        add(_solid(rng, SPHERE, rad), centre + r * (np.cos(a) * fwd + np.sin(a) * lat) + [0, 0, rad])
    side = rng.choice([-1.0, 1.0])  # an object close to the camera
    add(_solid(rng, CYLINDER, 0.12, 0.45), centre + rng.uniform(0.8, 1.2) * fwd + side * 0.35 * lat + [0, 0, 0.45])
    for _ in range(2):  # behind the views: identity of the hall from other directions
        a = rng.uniform(2.2, 4.1)
        add(_solid(rng, CYLINDER, rng.uniform(0.2, 0.5), ceiling / 2),
            centre + 2.6 * (np.cos(a) * fwd + np.sin(a) * lat) + [0, 0, ceiling / 2])
    return Hall(seed, normals, offsets, ceiling, surface, tuple(solids), np.array(poses), centre, fwd)


def lighting(seed: int, visit: int) -> Lighting:
    """Each visit's own light: direction, intensity, ambient, tint."""
    rng = np.random.default_rng([seed, visit, 91])
    az, el = rng.uniform(0, 2 * np.pi), rng.uniform(0.3, 1.3)
    d = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return Lighting(d, float(rng.uniform(0.5, 1.0)), float(rng.uniform(0.25, 0.55)),
                    1.0 + rng.uniform(-0.15, 0.15, 3))


def _look_at(pos, target) -> np.ndarray:
    f = target - pos
    f /= np.linalg.norm(f)
    right = np.cross(f, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, np.cross(f, right), f], 1)
    T[:3, 3] = pos
    return T


def camera_path(hall: Hall, visit: int, num_frames: int) -> np.ndarray:
    """cam_to_world (S, 4, 4): even visits dolly sideways looking at a fixed point (parallax), odd
    visits pan about a fixed point (near-pure rotation)."""
    rng = np.random.default_rng([hall.seed, visit, 5])
    fwd = hall.forward
    lat = np.array([-fwd[1], fwd[0], 0.0])
    u = np.linspace(0.0, 1.0, num_frames)
    height = rng.uniform(1.3, 1.6)
    base = hall.centre - 0.3 * fwd + [0, 0, height]
    if visit % 2 == 0:
        length = rng.uniform(1.2, 1.8)
        target = hall.centre + rng.uniform(2.2, 2.8) * fwd + [0, 0, rng.uniform(0.6, 1.0)]
        pos = base + ((u - 0.5) * length)[:, None] * lat + 0.05 * np.sin(3 * u)[:, None] * fwd
        return np.array([_look_at(p, target) for p in pos])
    span = np.deg2rad(rng.uniform(50, 70))
    yaw = (u - 0.5) * span * rng.choice([-1, 1])
    pitch = -0.2 + 0.05 * np.sin(2 * np.pi * u)
    wobble = 0.01 * np.stack([np.sin(5 * u), np.cos(4 * u), np.sin(3 * u)], -1)
    out = []
    for y, p, w in zip(yaw, pitch, wobble):
        d = np.cos(y) * fwd + np.sin(y) * lat
        d = np.cos(p) * d + np.sin(p) * np.array([0, 0, 1.0])
        out.append(_look_at(base + w, base + w + d))
    return np.array(out)


def movers(hall: Hall, visit: int, num_frames: int, cfg: HeldOutConfig):
    """Solids and their poses (S, M, 4, 4): a crosser entering and leaving the view, a slow mover
    (3 cm/s) and a sphere rotating in place."""
    rng = np.random.default_rng([hall.seed, visit, 6])
    fwd = hall.forward
    lat = np.array([-fwd[1], fwd[0], 0.0])
    t = np.arange(num_frames) / cfg.fps
    dur = max(t[-1], 1e-6)
    c = hall.centre
    d_cross = rng.uniform(2.0, 2.6)
    half = np.tan(np.deg2rad(cfg.fov_deg) / 2) * (d_cross + 0.3) + 0.6
    r_cross = rng.uniform(0.2, 0.3)
    sgn = rng.choice([-1, 1])
    solids = [_solid(rng, SPHERE, r_cross), _solid(rng, CYLINDER, 0.18, 0.3), _solid(rng, SPHERE, 0.3)]
    slow0, slow_dir = rng.uniform(-0.5, 0.5), rng.choice([-1, 1])
    spin_pos = c + rng.uniform(2.4, 2.9) * fwd + rng.choice([-1, 1]) * rng.uniform(0.5, 0.9) * lat + [0, 0, 0.3]
    spin_rate = rng.uniform(1.0, 2.0) * rng.choice([-1, 1])
    poses = []
    for ti in t:
        s = ti / dur
        cross = c + d_cross * fwd + sgn * (-half + 2 * half * s) * lat + [0, 0, 0.9 + 0.2 * np.sin(4 * s)]
        slow = c + 1.9 * fwd + (slow0 + slow_dir * 0.03 * ti) * lat + [0, 0, 0.3]
        poses.append([_place(cross, 0.5 * ti), _place(slow, 0.0), _place(spin_pos, spin_rate * ti)])
    return tuple(solids), np.array(poses)


# ----------------------------------------------------------------------------------------------
# Ray casting (NumPy)


def _hit_solid(solid: Solid, o, d):
    """Distances (N,) to a solid in its own frame (inf when missed), and local normals (N, 3)."""
    N = len(d)
    t = np.full(N, np.inf)
    n = np.zeros((N, 3))
    eps = 1e-4
    if solid.kind == SPHERE:
        b = np.sum(o * d, -1)
        a = np.sum(d * d, -1)
        c = np.sum(o * o, -1) - solid.radius ** 2
        disc = b * b - a * c
        ok = disc > 0
        tt = (-b - np.sqrt(np.where(ok, disc, 0))) / a
        ok &= tt > eps
        t[ok] = tt[ok]
        p = o + t[:, None] * d
        n[ok] = p[ok] / solid.radius
        return t, n
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1]
    c = o[:, 0] ** 2 + o[:, 1] ** 2 - solid.radius ** 2
    disc = b * b - a * c
    ok = (disc > 0) & (a > 1e-12)
    ts = (-b - np.sqrt(np.where(ok, disc, 0))) / np.where(a > 1e-12, a, 1)
    z = o[:, 2] + ts * d[:, 2]
    ok &= (ts > eps) & (np.abs(z) <= solid.half_height)
    t[ok] = ts[ok]
    n[ok] = np.stack([o[ok, 0] + ts[ok] * d[ok, 0], o[ok, 1] + ts[ok] * d[ok, 1], np.zeros(ok.sum())], -1) / solid.radius
    for cap in (-1.0, 1.0):
        dz = np.where(np.abs(d[:, 2]) < 1e-12, 1e-12, d[:, 2])
        tc = (cap * solid.half_height - o[:, 2]) / dz
        p = o + tc[:, None] * d
        okc = (tc > eps) & (p[:, 0] ** 2 + p[:, 1] ** 2 <= solid.radius ** 2) & (tc < t)
        t[okc] = tc[okc]
        n[okc] = [0, 0, cap]
    return t, n


def _hit_hall(hall: Hall, o, d):
    """Distance (N,) to the enclosure from inside, and world normals (N, 3)."""
    N = len(d)
    t = np.full(N, np.inf)
    n = np.zeros((N, 3))
    planes = [(np.array([*nn, 0.0]), off) for nn, off in zip(hall.wall_normals, hall.wall_offsets)]
    planes += [(np.array([0, 0, 1.0]), 0.0), (np.array([0, 0, -1.0]), -hall.ceiling)]
    for nn, off in planes:
        dn = d @ nn
        tt = (off - o @ nn) / np.where(np.abs(dn) < 1e-12, -1e-12, dn)
        ok = (dn < 0) & (tt > 1e-4) & (tt < t)
        t[ok] = tt[ok]
        n[ok] = nn
    return t, n


def _hash01(ix, iy, iz, seed, k):
    h = (ix.astype(np.int64) * 73856093) ^ (iy.astype(np.int64) * 19349663) ^ (iz.astype(np.int64) * 83492791)
    h = (h ^ (seed * 2654435761 + k * 40503)) & 0xFFFFFFFF
    h = (h * 0x45D9F3B) & 0xFFFFFFFF
    h = ((h >> 16) ^ h) * 0x45D9F3B & 0xFFFFFFFF
    h = (h >> 16) ^ h
    return (h & 0xFFFFFF) / float(1 << 24)


def texture(solid: Solid, p):
    """Colour (N, 3) in [0, 1] at local points (N, 3): two colours mixed by three 3D gratings,
    dark cellular dots and thin grid lines."""
    g = sum(np.sin(2 * np.pi * solid.grating_freq[k] * (p @ solid.grating_dir[k]) + solid.grating_phase[k])
            for k in range(3)) / 3.0
    mix = 0.5 + 0.5 * np.tanh(3.0 * g)
    col = mix[:, None] * solid.colors[0] + (1 - mix[:, None]) * solid.colors[1]
    q = p * solid.cells
    i = np.floor(q)
    f = q - i
    jit = np.stack([_hash01(i[:, 0], i[:, 1], i[:, 2], solid.seed, k) for k in range(3)], -1)
    dist = np.linalg.norm(f - (0.2 + 0.6 * jit), axis=-1)
    size = 0.12 + 0.18 * _hash01(i[:, 0], i[:, 1], i[:, 2], solid.seed, 7)
    dot = dist < size
    bright = _hash01(i[:, 0], i[:, 1], i[:, 2], solid.seed, 9) > 0.5
    col = np.where((dot & bright)[:, None], 1.0 - 0.6 * col, np.where(dot[:, None], 0.15 * col, col))
    line = np.min(np.minimum(f, 1 - f), -1) < 0.03
    return np.where(line[:, None], 0.6 * col, col)


def _cast(hall: Hall, solids, poses, light: Lighting, o, d, shade: bool):
    """Nearest hits of rays (origin (3,), directions (N, 3)): (t (N,), object (N,): -1 hall, i >= 0
    the i-th solid, colour (N, 3) or None)."""
    t, n = _hit_hall(hall, np.broadcast_to(o, d.shape), d)
    obj = np.full(len(d), -1)
    for i, (s, T) in enumerate(zip(solids, poses)):
        R, c = T[:3, :3], T[:3, 3]
        ti, ni = _hit_solid(s, np.broadcast_to((o - c) @ R, d.shape), d @ R)
        closer = ti < t
        t[closer], obj[closer], n[closer] = ti[closer], i, ni[closer] @ R.T
    if not shade:
        return t, obj, None
    x = o + t[:, None] * d
    col = np.zeros((len(d), 3))
    sel = obj < 0
    col[sel] = texture(hall.surface, x[sel])
    for i, (s, T) in enumerate(zip(solids, poses)):
        sel = obj == i
        if sel.any():
            col[sel] = texture(s, (x[sel] - T[:3, 3]) @ T[:3, :3])
    lam = np.clip(n @ light.direction, 0.0, None)
    return t, obj, np.clip(col * (light.ambient + light.intensity * lam)[:, None] * light.tint, 0, 1)


def render_visit(hall: Hall, visit: int, num_frames: int, cfg: HeldOutConfig = HeldOutConfig()):
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        return _render_visit(hall, visit, num_frames, cfg)


def _render_visit(hall: Hall, visit: int, num_frames: int, cfg: HeldOutConfig):
    """Images (S, H, W, 3) uint8 and :class:`GroundTruth` (depth, K, poses, dynamic mask) of a visit."""
    cams = camera_path(hall, visit, num_frames)
    mov, mpose = movers(hall, visit, num_frames, cfg)
    solids = hall.solids + mov
    n_static = len(hall.solids)
    light = lighting(hall.seed, visit)
    K = intrinsics(cfg)
    Kinv = np.linalg.inv(K)
    H, W, s = cfg.height, cfg.width, cfg.supersample
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    offs = (np.arange(s) + 0.5) / s - 0.5
    images, depth, dyn = [], [], []
    centre = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3) @ Kinv.T  # camera z = 1: t is depth
    for k, c2w in enumerate(cams):
        poses = np.concatenate([hall.poses, mpose[k]])
        t, obj, rgb = _cast(hall, solids, poses, light, c2w[:3, 3], centre @ c2w[:3, :3].T, s == 1)
        if s > 1:
            rgb = np.zeros((H * W, 3))
            for du in offs:
                for dv in offs:
                    ray = np.stack([u + du, v + dv, np.ones_like(u)], -1).reshape(-1, 3) @ Kinv.T
                    rgb += _cast(hall, solids, poses, light, c2w[:3, 3], ray @ c2w[:3, :3].T, True)[2] / (s * s)
        images.append(np.round(rgb.reshape(H, W, 3) * 255).astype(np.uint8))
        depth.append(np.where(np.isfinite(t), t, 0.0).reshape(H, W).astype(np.float32))
        dyn.append((obj >= n_static).reshape(H, W))
    Ks = np.broadcast_to(K, (num_frames, 3, 3)).copy()
    gt = GroundTruth(cam_to_world=cams, depth=np.stack(depth), intrinsic=Ks, dynamic_mask=np.stack(dyn))
    return np.stack(images), gt


def generate(hall_seed: int = 0, visit: int = 0, num_frames: int = 30, level: str = "moderate",
             cfg: HeldOutConfig = HeldOutConfig()) -> Sequence:
    """One visit of a held-out hall with VGGT-like priors (:func:`cm3d.data.priors.make_priors`)."""
    hall = make_hall(hall_seed)
    images, gt = render_visit(hall, visit, num_frames, cfg)
    meta = {"source": "held_out_world", "scene": hall_seed, "visit": visit,
            "path": "parallax" if visit % 2 == 0 else "rotation"}
    return priors.make_priors(images, gt, level, seed=hall_seed * 4099 + visit + 17,
                              timestamps=np.arange(num_frames) / cfg.fps, meta=meta)
