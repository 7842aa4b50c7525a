"""Contrastive training of the PointNet++ scene descriptor (issue #9) on synthetic static clouds.

    .venv/bin/python experiments/train_pointnet2.py [--quick] [--json PATH] [--out PATH] [--steps N]

Data (host, cached under ``~/.cache/cm3d/pointnet2``): training scenes are
:mod:`cm3d.data.synthetic` rooms with seeds from 100000, validation scenes seeds from 200000 —
disjoint from the memory-recall scenes (0-199 stored, 10000-10199 unseen). Each visit is rendered
at 30x40 pixels (the 120x160 renders of ``experiments/memory_recall.py`` sampled every 4th pixel,
as the bank does), given VGGT-like "slight" priors (its own first-camera frame and unknown scale),
and turned into a bank entry by the bank's own functions (:func:`cm3d.memory.sequence_cloud` on the
ground-truth static pixels, :func:`cm3d.memory.build_entry`: adaptive voxel size, downsampling to
4096 voxels): the training clouds are what the bank stores. Training scenes have a 32-frame visit
(like a stored map) and three 12-frame visits (like revisit queries).

Training: NT-Xent / InfoNCE (temperature 0.1, symmetric) over a batch of ``B`` scenes, two views
of each (positives: two augmentations of one visit with probability 0.5, else two different visits
of the scene; negatives: every other cloud in the batch), each augmented in JAX: partial crop by a
random vertical plane (p = 0.5, keeps 55-100%), density dropout (keeps 60-100%), Gaussian noise (1%
of the RMS radius), random yaw about the camera y axis (about gravity in a first-camera frame; the
network is invariant to it by construction), tilt up to 5 degrees, translation and scale. AdamW
(lr 3e-4) with warm-up and cosine decay, 800 steps. Checkpoints (atomic, tagged with the
configuration) every 100 steps beside ``--out``; a rerun of the same configuration resumes.
``--set FIELD=VALUE`` overrides :class:`TrainConfig` fields (e.g. ``--set lr=1e-3 steps=400``).

Evaluation on the held-out validation scenes: each scene's 32-frame visit is stored, its 12-frame
visit queries; top-1 retrieval by cosine similarity of the learned descriptor vs the handcrafted
one (:func:`cm3d.ops.descriptors.cloud_descriptor`).

``--quick``: 6 training and 4 validation scenes of 6-frame visits, 2 steps, weights written to a
temporary folder (never over the shipped ones).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # OpenBLAS threads spin on shared cores

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

from cm3d import memory  # noqa: E402
from cm3d.data import synthetic  # noqa: E402
from cm3d.data.atomic import atomic_write  # noqa: E402
from cm3d.models import pointnet2 as pn  # noqa: E402
from cm3d.outputs import write_json  # noqa: E402

WORLD = synthetic.WorldConfig(height=30, width=40, supersample=1, fps=1.0)
BANK = memory.MemoryConfig(max_maps=1, max_points=4096, max_keyframes=1, voxel_resolution=40.0, pixel_stride=1)
LEVEL = "slight"
TRAIN_SEED, VAL_SEED = 100_000, 200_000
CACHE = Path(os.environ.get("CM3D_CACHE", Path.home() / ".cache" / "cm3d")) / "pointnet2"


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    train_scenes: int = 300
    val_scenes: int = 100
    visit_frames: tuple[int, ...] = (32, 12, 12, 12)  # per visit index of a training scene
    steps: int = 800
    batch: int = 24  # scenes per step (2 views each)
    lr: float = 3e-4
    warmup: int = 50
    weight_decay: float = 1e-4
    temperature: float = 0.1
    max_tilt_deg: float = 5.0
    crop_prob: float = 0.5
    same_visit_prob: float = 0.5  # share of positive pairs made of two augmentations of one visit
    seed: int = 0


# ----------------------------------------------------------------------------------------------
# Data: bank entries of synthetic visits


@jax.jit
def _entry_cloud(depth, conf, K, c2w, images, static):
    cloud = memory.sequence_cloud(depth, conf, K, c2w, images, static, BANK)
    e = memory.build_entry(cloud, jnp.zeros((1, BANK.image_dim)), jnp.zeros(1, bool), BANK)
    return e.points, e.point_valid, e.cloud_desc


def visit_cloud(seed: int, visit: int, frames: int):
    """One visit's stored cloud as the bank builds it: (points (P, 3) float16 in the visit's prior
    frame, valid (P,) bool, handcrafted descriptor (D,) float32)."""
    seq = synthetic.generate(seed, visit, frames, LEVEL, WORLD)
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    p, v, d = _entry_cloud(f32(seq.depth), f32(seq.depth_conf), f32(seq.intrinsic), f32(seq.cam_to_world),
                           jnp.asarray(seq.images), jnp.asarray(~seq.gt.dynamic_mask))
    return np.asarray(p, np.float16), np.asarray(v), np.asarray(d, np.float32)


def make_clouds(seeds, frames, use_cache: bool, label: str):
    """Clouds of every (seed, visit) with ``frames[visit]`` frames: points (S, V, P, 3), valid
    (S, V, P), handcrafted (S, V, D); cached on disk when ``use_cache``."""
    bank = {k: getattr(BANK, k) for k in ("max_points", "voxel_resolution", "min_conf_quantile", "pixel_stride")}
    key = json.dumps([list(seeds), list(frames), dataclasses.asdict(WORLD), bank, LEVEL, 1])
    path = CACHE / f"{label}_{hashlib.sha256(key.encode()).hexdigest()[:16]}.npz"
    if use_cache and path.exists():
        with np.load(path) as z:
            return z["points"], z["valid"], z["hand"]
    out = [[visit_cloud(s, v, f) for v, f in enumerate(frames)] for s in _bar(list(seeds), f"render {label}")]
    pts, val, hand = (np.stack([np.stack([c[i] for c in row]) for row in out]) for i in range(3))
    if use_cache:
        with atomic_write(path) as f:
            np.savez(f, points=pts, valid=val, hand=hand)
    return pts, val, hand


def _bar(items, desc):
    try:
        from tqdm import tqdm

        return tqdm(items, desc=desc, mininterval=2.0, ncols=90)
    except ImportError:  # a simple printed bar
        def gen():
            n = len(items)
            for i, x in enumerate(items):
                if i % max(1, n // 20) == 0:
                    print(f"{desc}: [{'#' * (20 * i // n):<20}] {i}/{n}", flush=True)
                yield x
        return gen()


# ----------------------------------------------------------------------------------------------
# Augmentation (JAX)


def _rotation(axis, angle):
    axis = axis / jnp.maximum(jnp.linalg.norm(axis), 1e-12)
    K = jnp.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return jnp.eye(3) + jnp.sin(angle) * K + (1 - jnp.cos(angle)) * K @ K


def augment(key, points, valid, max_tilt_deg: float, crop_prob: float = 0.5):
    """A random partial, sparser, noisier view under a random similarity: (points, valid)."""
    k = jax.random.split(key, 9)
    p = jnp.asarray(points, jnp.float32)
    w = valid.astype(jnp.float32)
    n = jnp.maximum(w.sum(), 1.0)
    c = (w[:, None] * p).sum(0) / n
    r = jnp.sqrt(jnp.maximum((w * jnp.sum((p - c) ** 2, -1)).sum() / n, 1e-12))
    # partial crop by a plane containing the camera y axis (a vertical plane in a first-camera frame)
    a = jax.random.uniform(k[0], (), maxval=2 * jnp.pi)
    u = jnp.array([jnp.cos(a), 0.0, jnp.sin(a)])
    t = (p - c) @ u
    keep_frac = jax.random.uniform(k[1], (), minval=0.55, maxval=1.0)
    thr = jnp.nanquantile(jnp.where(valid, t, jnp.nan), keep_frac)
    crop = jax.random.bernoulli(k[2], crop_prob)
    v = valid & (~crop | (t <= thr))
    # density dropout
    v = v & jax.random.bernoulli(k[3], jax.random.uniform(k[4], (), minval=0.6, maxval=1.0), v.shape)
    v = jnp.where(jnp.sum(v) >= 32, v, valid)
    p = p + 0.01 * r * jax.random.normal(k[5], p.shape)
    yaw = _rotation(jnp.array([0.0, 1.0, 0.0]), jax.random.uniform(k[6], (), maxval=2 * jnp.pi))
    b = jax.random.uniform(k[7], (), maxval=2 * jnp.pi)
    tilt = _rotation(jnp.array([jnp.cos(b), 0.0, jnp.sin(b)]),
                     jnp.deg2rad(max_tilt_deg) * jax.random.uniform(k[8], ()))
    kt, ks = jax.random.split(k[8])
    s = jnp.exp(jax.random.uniform(ks, (), minval=-1.0, maxval=1.0))
    p = s * (p - c) @ (tilt @ yaw).T + r * jax.random.normal(kt, (3,))
    return p, v


# ----------------------------------------------------------------------------------------------
# Training


def nt_xent(z1, z2, temperature: float):
    """Symmetric InfoNCE over 2B unit descriptors: each view's positive is its pair."""
    z = jnp.concatenate([z1, z2])
    B = z1.shape[0]
    s = z @ z.T / temperature
    s = jnp.where(jnp.eye(2 * B, dtype=bool), -jnp.inf, s)
    pos = jnp.concatenate([jnp.arange(B) + B, jnp.arange(B)])
    return jnp.mean(jax.nn.logsumexp(s, axis=1) - s[jnp.arange(2 * B), pos])


def make_step(cfg: TrainConfig, opt, net: pn.PointNet2Config):
    encode = jax.vmap(lambda prm, p, v: pn.apply(prm, p, v, net), in_axes=(None, 0, 0))
    aug = jax.vmap(lambda k, p, v: augment(k, p, v, cfg.max_tilt_deg, cfg.crop_prob))

    def loss_fn(params, key, pts, val, a, b):
        B = pts.shape[0]
        k1, k2 = jax.random.split(key)
        i = jnp.arange(B)
        p1, v1 = aug(jax.random.split(k1, B), pts[i, a], val[i, a])
        p2, v2 = aug(jax.random.split(k2, B), pts[i, b], val[i, b])
        return nt_xent(encode(params, p1, v1), encode(params, p2, v2), cfg.temperature)

    @jax.jit
    def step(params, opt_state, key, pts, val, a, b):
        loss, g = jax.value_and_grad(loss_fn)(params, key, pts, val, a, b)
        upd, opt_state = opt.update(g, opt_state, params)
        return optax.apply_updates(params, upd), opt_state, loss

    return step


def _save_checkpoint(path: Path, state, step: int, losses, tag: str):
    leaves = jax.tree.leaves(state)
    with atomic_write(path) as f:
        np.savez(f, step=step, losses=np.asarray(losses, np.float32), n=len(leaves), tag=np.array(tag),
                 **{f"leaf{i}": np.asarray(x) for i, x in enumerate(leaves)})


def _load_checkpoint(path: Path, template, tag: str):
    """(state, step, losses) from a checkpoint of the same run (same ``tag``), else None."""
    with np.load(path) as z:
        if "tag" not in z.files or str(z["tag"]) != tag:
            return None
        leaves = [jnp.asarray(z[f"leaf{i}"]) for i in range(int(z["n"]))]
        step, losses = int(z["step"]), list(z["losses"])
    return jax.tree.unflatten(jax.tree.structure(template), leaves), step, losses


def train(cfg: TrainConfig, pts, val, ckpt: Path | None, net: pn.PointNet2Config = pn.CONFIG):
    """Train from scratch or resume from ``ckpt``: (params, losses)."""
    warm = min(cfg.warmup, cfg.steps // 2)
    sched = optax.warmup_cosine_decay_schedule(0.0, cfg.lr, warm, max(cfg.steps, warm + 1))
    opt = optax.adamw(sched, weight_decay=cfg.weight_decay)
    params = pn.init_params(jax.random.PRNGKey(cfg.seed), net)
    state, start, losses = (params, opt.init(params)), 0, []
    tag = json.dumps([dataclasses.asdict(cfg), dataclasses.asdict(net), pts.shape])
    if ckpt is not None and ckpt.exists():
        resumed = _load_checkpoint(ckpt, state, tag)
        if resumed is None:
            print(f"{ckpt}: a checkpoint of another configuration, starting afresh")
        else:
            state, start, losses = resumed
            print(f"resumed from {ckpt} at step {start}")
    step = make_step(cfg, opt, net)
    S, V = val.shape[:2]
    B = min(cfg.batch, S)
    pts_j, val_j = jnp.asarray(pts), jnp.asarray(val)
    bar = _bar(range(start, cfg.steps), "train")
    for it in bar:
        rng = np.random.default_rng([cfg.seed, it])  # per step: a resumed run draws the same batches
        scenes = rng.choice(S, B, replace=False)
        a = rng.integers(V, size=B)
        b = (a + rng.integers(1, V, size=B)) % V
        b = np.where(rng.random(B) < cfg.same_visit_prob, a, b)  # two augmentations of one visit
        params, opt_state, loss = step(*state, jax.random.PRNGKey(it), pts_j[scenes], val_j[scenes],
                                       jnp.asarray(a), jnp.asarray(b))
        state = (params, opt_state)
        losses.append(float(loss))
        if hasattr(bar, "set_postfix") and it % 10 == 0:
            bar.set_postfix(loss=f"{np.mean(losses[-20:]):.3f}")
        if (it + 1) % 100 == 0:
            print(f"step {it + 1}: loss {np.mean(losses[-100:]):.3f}", flush=True)
        if ckpt is not None and ((it + 1) % 100 == 0 or it + 1 == cfg.steps):
            _save_checkpoint(ckpt, state, it + 1, losses, tag)
    return state[0], losses


def top1(bank, queries):
    """Share of queries whose most cosine-similar bank row is their own (row i <-> query i)."""
    sim = np.asarray(queries) @ np.asarray(bank).T
    return float(np.mean(np.argmax(sim, axis=1) == np.arange(len(sim))))


def describe(params, pts, val, net: pn.PointNet2Config = pn.CONFIG, chunk: int = 50):
    f = jax.jit(jax.vmap(lambda p, v: pn.apply(params, p, v, net)))
    chunk = min(chunk, len(pts))
    out = []
    for i in range(0, len(pts), chunk):
        p, v = pts[i:i + chunk], val[i:i + chunk]
        m = len(p)
        if m < chunk:  # one shape, one compilation
            p = np.concatenate([p, np.repeat(p[:1], chunk - m, 0)])
            v = np.concatenate([v, np.repeat(v[:1], chunk - m, 0)])
        out.append(np.asarray(f(jnp.asarray(p, jnp.float32), jnp.asarray(v)))[:m])
    return np.concatenate(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--out", type=Path, help="weights file (default: the shipped cm3d/models/pointnet2.npz; "
                                             "--quick: a temporary file)")
    ap.add_argument("--steps", type=int)
    ap.add_argument("--train-scenes", type=int)
    ap.add_argument("--no-cache", action="store_true")
    ap.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE", help="override TrainConfig fields")
    args = ap.parse_args(argv)
    cfg = TrainConfig()
    for kv in args.set:
        k, v = kv.split("=", 1)
        if k not in {f.name for f in dataclasses.fields(TrainConfig)}:
            raise SystemExit(f"--set: unknown TrainConfig field {k!r}")
        old = getattr(cfg, k)
        cfg = dataclasses.replace(cfg, **{k: tuple(json.loads(v)) if isinstance(old, tuple) else type(old)(json.loads(v))})
    if args.quick:
        cfg = dataclasses.replace(cfg, train_scenes=6, val_scenes=4, visit_frames=(6, 6), steps=2, batch=4)
    if args.steps is not None:
        cfg = dataclasses.replace(cfg, steps=args.steps)
    if args.train_scenes is not None:
        cfg = dataclasses.replace(cfg, train_scenes=args.train_scenes)
    tmp = tempfile.TemporaryDirectory() if args.quick and args.out is None else None
    out = Path(tmp.name) / "pointnet2.npz" if tmp else (args.out or pn.DEFAULT_WEIGHTS)
    use_cache = not (args.quick or args.no_cache)

    t0 = time.perf_counter()
    tr_seeds = range(TRAIN_SEED, TRAIN_SEED + cfg.train_scenes)
    tr_pts, tr_val, _ = make_clouds(tr_seeds, cfg.visit_frames, use_cache, "train")
    va_frames = (cfg.visit_frames[0], cfg.visit_frames[-1])
    va_pts, va_val, va_hand = make_clouds(range(VAL_SEED, VAL_SEED + cfg.val_scenes), va_frames, use_cache, "val")
    t_data = time.perf_counter() - t0
    print(f"data: {cfg.train_scenes} training scenes x {len(cfg.visit_frames)} visits, {cfg.val_scenes} validation "
          f"scenes; mean {tr_val.sum(-1).mean():.0f} voxels per cloud; {t_data:.1f} s (cached: {use_cache})")

    t1 = time.perf_counter()
    ckpt = out.with_name(out.name + ".ckpt")
    params, losses = train(cfg, tr_pts, tr_val, ckpt)
    train_min = (time.perf_counter() - t1) / 60

    bank = describe(params, va_pts[:, 0], va_val[:, 0])
    query = describe(params, va_pts[:, 1], va_val[:, 1])
    fig = {
        "val_top1": top1(bank, query),
        "val_top1_handcrafted": top1(va_hand[:, 0], va_hand[:, 1]),
        "val_scenes": cfg.val_scenes,
        "train_scenes": cfg.train_scenes,
        "steps": cfg.steps,
        "final_loss": float(np.mean(losses[-50:])) if losses else float("nan"),
        "train_minutes": train_min,
        "data_minutes": t_data / 60,
    }
    sims = np.asarray(query) @ np.asarray(bank).T
    fig["val_pos_cos"] = float(np.mean(np.diag(sims)))
    fig["val_neg_cos"] = float((sims.sum() - np.trace(sims)) / max(sims.size - len(sims), 1))
    info = {"command": "experiments/train_pointnet2.py " + " ".join(sys.argv[1:] if argv is None else argv),
            "train": dataclasses.asdict(cfg), **{k: v for k, v in fig.items()}}
    pn.save_params(params, out, info=info)
    if ckpt.exists():  # the run finished and its weights are saved: the checkpoint served its purpose
        ckpt.unlink()

    print(f"\nretrieval on {cfg.val_scenes} held-out scenes ({va_frames[0]}-frame visit stored, "
          f"{va_frames[1]}-frame visit queries)")
    print(f"{'descriptor':>12} {'top-1':>7}")
    print(f"{'handcrafted':>12} {100 * fig['val_top1_handcrafted']:>6.1f}%")
    print(f"{'pointnet2':>12} {100 * fig['val_top1']:>6.1f}%")
    print(f"cosine: same scene {fig['val_pos_cos']:.3f}, other scenes {fig['val_neg_cos']:.3f}; final loss "
          f"{fig['final_loss']:.3f}; training {train_min:.1f} min ({cfg.steps} steps), data {t_data / 60:.1f} min")
    print(f"weights: {out} ({out.stat().st_size / 1e6:.2f} MB)")
    if args.json:
        write_json(args.json, fig)
    if tmp:
        tmp.cleanup()
    return fig


if __name__ == "__main__":
    main()
