"""Resizing a frame and its per-pixel companion (mask or depth) together, for the folder readers."""

from __future__ import annotations

import numpy as np


def resize_frame(image: np.ndarray, aux: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """``image`` (H, W, 3) by area averaging and ``aux`` (H, W) (a mask or depth: values are never
    mixed) by nearest neighbour, both to ``round(scale * size)``; unchanged when ``scale == 1``."""
    if scale == 1.0:
        return image, aux
    import cv2

    size = (int(round(image.shape[1] * scale)), int(round(image.shape[0] * scale)))
    return (cv2.resize(image, size, interpolation=cv2.INTER_AREA),
            cv2.resize(aux, size, interpolation=cv2.INTER_NEAREST))
