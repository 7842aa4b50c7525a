"""One entry point for every input format: :func:`load_input`.

- ``*.npz``: a sequence file / saved VGGT predictions (:mod:`cm3d.data.io`);
- a folder with ``rgb.txt`` and ``depth.txt``: TUM RGB-D (:mod:`cm3d.data.tum_rgbd`);
- a folder with ``images/`` and ``priors.npz``: images plus priors (:func:`load_image_folder`);
- a folder with ``frame-XXXXXX.color.jpg|png``: 7-Scenes / tsdf-fusion (:mod:`cm3d.data.sevenscenes`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cm3d.data import io
from cm3d.data.sequence import Sequence

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def load_image_folder(folder) -> Sequence:
    """``folder/images/*.png|jpg`` (sorted) plus ``folder/priors.npz`` holding the other sequence keys
    (e.g. VGGT run on those images)."""
    import cv2

    folder = Path(folder)
    files = sorted(p for p in (folder / "images").iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise ValueError(f"{folder / 'images'}: no .png/.jpg images")
    images = []
    for p in files:
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            raise ValueError(f"{p}: cannot read image")
        images.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
    shapes = {im.shape for im in images}
    if len(shapes) != 1:
        raise ValueError(f"{folder / 'images'}: images differ in size {sorted(shapes)}")
    priors = folder / "priors.npz"
    if not priors.exists():
        raise ValueError(f"{folder}: priors.npz missing (depth, intrinsic, extrinsic per image)")
    with np.load(priors, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files if k != "images"}
    arrays["images"] = np.stack(images)
    return io.sequence_from_arrays(arrays, source=str(folder))


def write_image_folder(folder, seq: Sequence) -> None:
    """Write ``seq`` as an image folder (``images/000000.png`` ... + ``priors.npz`` with every other
    key), the layout :func:`load_image_folder` reads; the folder must not hold images already."""
    import cv2

    from cm3d.data.atomic import atomic_write

    folder = Path(folder)
    io.validate_sequence(seq, source=str(folder))
    (folder / "images").mkdir(parents=True, exist_ok=True)
    if any((folder / "images").iterdir()):
        raise ValueError(f"{folder / 'images'}: not empty (refusing to mix two sequences)")
    for i, im in enumerate(seq.images):
        ok, png = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(im), cv2.COLOR_RGB2BGR))
        if not ok:
            raise ValueError(f"frame {i}: cannot encode as PNG")
        with atomic_write(folder / f"images/{i:06d}.png", "wb") as f:
            f.write(png.tobytes())
    arrays = {k: v for k, v in io.sequence_arrays(seq).items() if k != "images"}
    with atomic_write(folder / "priors.npz", "wb") as f:
        np.savez(f, **arrays)


def load_input(path, **kwargs) -> Sequence:
    """Load a sequence from any supported input (see the module docstring)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or folder")
    if path.is_file():
        if path.suffix != ".npz":
            raise ValueError(f"{path}: unsupported file type (expected a .npz sequence or a folder)")
        return io.load_sequence(path)
    if (path / "rgb.txt").exists():
        from cm3d.data.tum_rgbd import load_tum_rgbd

        return load_tum_rgbd(path, **kwargs)
    if (path / "images").is_dir():
        return load_image_folder(path)
    from cm3d.data.sevenscenes import is_sevenscenes_folder, load_sevenscenes

    if is_sevenscenes_folder(path):
        return load_sevenscenes(path, **kwargs)
    raise ValueError(f"{path}: not a recognised input folder (expected rgb.txt + depth.txt for TUM "
                     "RGB-D, images/ + priors.npz, or frame-XXXXXX.color.jpg + camera-intrinsics.txt for 7-Scenes)")
