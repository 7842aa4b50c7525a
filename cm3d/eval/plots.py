"""Pictures (PNG, matplotlib's Agg backend): trajectories, mask overlays, top-down maps."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cm3d.data.atomic import atomic_write


def _figure():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path) -> None:
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120, bbox_inches="tight")
    with atomic_write(path) as f:
        f.write(buf.getvalue())


def _plane_axes(points: np.ndarray) -> tuple[int, int]:
    """The two coordinate axes of largest spread (a top-down view for most scenes)."""
    spread = np.ptp(points.reshape(-1, 3), axis=0)
    a, b = sorted(np.argsort(spread)[-2:])
    return int(a), int(b)


def plot_trajectories(path, trajectories: dict[str, np.ndarray], title: str = "trajectories") -> None:
    """Top-down plot of camera positions; ``trajectories`` maps a label to cam_to_world (N, 4, 4)
    or positions (N, 3). Align them to one frame first (e.g. :func:`cm3d.eval.align_trajectory`)."""
    plt = _figure()
    pos = {k: (np.asarray(v)[:, :3, 3] if np.asarray(v).ndim == 3 else np.asarray(v)) for k, v in trajectories.items()}
    a, b = _plane_axes(np.concatenate(list(pos.values())))
    fig, ax = plt.subplots(figsize=(5, 5))
    for label, p in pos.items():
        ax.plot(p[:, a], p[:, b], "-", lw=1.5, label=label)
        ax.plot(p[:1, a], p[:1, b], "o", ms=4, color=ax.lines[-1].get_color())
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("xyz"[a])
    ax.set_ylabel("xyz"[b])
    ax.set_title(title)
    ax.legend()
    _save(fig, path)
    plt.close(fig)


def mask_overlay(image: np.ndarray, mask: np.ndarray, color=(255, 40, 40), alpha: float = 0.5) -> np.ndarray:
    """RGB image (H, W, 3) uint8 with the mask tinted in ``color``."""
    out = image.astype(np.float32)
    m = np.asarray(mask, bool)
    out[m] = (1 - alpha) * out[m] + alpha * np.asarray(color, np.float32)
    return out.round().astype(np.uint8)


def save_mask_overlays(folder, images: np.ndarray, masks: np.ndarray, every: int = 1) -> list[Path]:
    """``folder/overlay_NNNNNN.png`` for every ``every``-th frame."""
    import cv2

    paths = []
    for i in range(0, len(images), every):
        ok, buf = cv2.imencode(".png", cv2.cvtColor(mask_overlay(images[i], masks[i]), cv2.COLOR_RGB2BGR))
        path = Path(folder) / f"overlay_{i:06d}.png"
        with atomic_write(path) as f:
            f.write(buf.tobytes())
        paths.append(path)
    return paths


def plot_topdown_map(path, points: np.ndarray, colors: np.ndarray | None = None,
                     from_memory: np.ndarray | None = None, cameras: np.ndarray | None = None,
                     max_points: int = 60000, title: str = "static map") -> None:
    """Top-down scatter of a static map; points recalled from memory (``from_memory`` mask) are
    drawn brighter and larger, the rest dimmed, as in the paper's figures."""
    plt = _figure()
    pts = np.asarray(points)
    keep = np.random.default_rng(0).permutation(len(pts))[:max_points]
    pts = pts[keep]
    col = np.full((len(pts), 3), 0.5) if colors is None else np.asarray(colors)[keep] / 255.0
    mem = np.zeros(len(pts), bool) if from_memory is None else np.asarray(from_memory, bool)[keep]
    a, b = _plane_axes(pts)
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.scatter(pts[~mem, a], pts[~mem, b], s=0.5, c=0.35 * col[~mem] + 0.1, linewidths=0)
    ax.scatter(pts[mem, a], pts[mem, b], s=1.5, c=np.clip(0.3 + col[mem], 0, 1), linewidths=0)
    if cameras is not None:
        c = np.asarray(cameras)[:, :3, 3]
        ax.plot(c[:, a], c[:, b], "-", color="tab:orange", lw=1.5, label="camera")
        ax.legend()
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(title)
    _save(fig, path)
    plt.close(fig)
