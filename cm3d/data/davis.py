"""DAVIS-layout video folders: ``SEQ/images/*.jpg`` (or ``.png``) and ``SEQ/masks/*.png`` (the
ground-truth foreground mask of every frame, {0, 255}). No depth, no poses."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cm3d.data.resize import resize_frame


def load_davis(folder, resize: float = 1.0, max_frames: int | None = None):
    """A DAVIS-layout folder -> (images (S, H, W, 3) uint8 RGB, masks (S, H, W) bool); ``resize``
    scales both (area for images, nearest for masks); ``max_frames``: the first N frames."""
    import cv2

    folder = Path(folder)
    files = sorted((folder / "images").glob("*.jpg")) or sorted((folder / "images").glob("*.png"))
    if not files:
        raise ValueError(f"{folder}: no images/*.jpg or *.png (expected the DAVIS layout SEQ/images, SEQ/masks)")
    files = files[:max_frames]
    images, masks = [], []
    for p in files:
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        mpath = folder / "masks" / f"{p.stem}.png"
        m = cv2.imread(str(mpath), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise ValueError(f"{p}: cannot read image")
        if m is None:
            raise ValueError(f"{mpath}: missing or unreadable mask")
        if m.shape != img.shape[:2]:
            raise ValueError(f"{mpath}: mask is {m.shape[1]}x{m.shape[0]}, image {img.shape[1]}x{img.shape[0]}")
        img, m = resize_frame(img, m, resize)
        images.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
        masks.append(m > 127)
    return np.stack(images), np.stack(masks)
