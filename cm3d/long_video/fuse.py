"""Placing chunks by Sim(3)s and fusing them into one sequence with one entry per frame.

``G_k = [s R, t]`` maps chunk k's poses to ``[R R_i, s R t_i + t]`` and depths to ``s d``; shared
frames are blended with weights ramping across the overlap, so there is no step at a boundary.
Host NumPy: poses float64, maps float32.
"""

from __future__ import annotations

import numpy as np

from cm3d.data.sequence import GroundTruth, Sequence
from cm3d.long_video.layout import StitchError, blend_weights, check_chunks, chunk_layout
from cm3d.ops import sim3


def place_poses(G, poses):
    """Poses (N, 4, 4) of a chunk moved by the similarity ``G`` (4x4 ``[s R, t]``): rigid poses
    ``[R R_i, s R t_i + t]`` in G's target frame and units (NumPy float64)."""
    G, poses = np.asarray(G, np.float64), np.asarray(poses, np.float64)
    out = np.array(poses)
    out[:, :3, :3] = sim3.rotation(G) @ poses[:, :3, :3]
    out[:, :3, 3] = poses[:, :3, 3] @ G[:3, :3].T + G[:3, 3]
    return out


def _orthonormalize(M):
    """Nearest rotations (N, 3, 3) to M (Frobenius): ``U diag(1, 1, det(U V^T)) V^T``."""
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    U[..., :, 2] *= np.where(d == 0, 1.0, d)[..., None]
    return U @ Vt


def fuse_frames(frame, weight, poses, depth, conf, intrinsic, *, num_frames: int):
    """Fuse per-chunk copies of frames into one per frame -> (poses, depth, conf, intrinsic).

    frame (N,) global frame of each copy; weight (N,) summing to 1 per frame; poses (N, 4, 4) common
    frame; depth, conf (N, H, W); intrinsic (N, 3, 3). Weighted translation, chordal rotation mean,
    depth over the copies with positive depth, weighted confidence and intrinsics.
    """
    def seg(x):
        out = np.zeros((num_frames,) + x.shape[1:], x.dtype)
        np.add.at(out, frame, x)
        return out

    weight, poses = np.asarray(weight, np.float64), np.asarray(poses, np.float64)
    P = np.tile(np.eye(4), (num_frames, 1, 1))
    P[:, :3, 3] = seg(weight[:, None] * poses[:, :3, 3])
    P[:, :3, :3] = _orthonormalize(seg(weight[:, None, None] * poses[:, :3, :3]))
    wm = weight.astype(depth.dtype)[:, None, None]  # maps stay in their (float32) dtype
    wd = wm * (depth > 0)
    den = seg(wd)
    d = np.where(den > 0, seg(wd * depth) / np.where(den > 0, den, 1.0), 0.0).astype(depth.dtype)
    return P, d, seg(wm * conf), seg(weight[:, None, None] * np.asarray(intrinsic, np.float64))


def merge_chunks(chunks, ranges, overlaps, ts, G, method: str, weights=None):
    """Merged Sequence of the chunks placed by the similarities G (K, 4, 4) -> (sequence, frame_chunk
    (S,): the chunk each frame's image and ground truth come from)."""
    S = ranges[-1][1]
    weights = blend_weights(ranges, overlaps) if weights is None else weights
    frame = np.concatenate([np.arange(a, b) for a, b in ranges])
    w = np.concatenate(weights)
    placed = np.concatenate([place_poses(G[k], c.cam_to_world) for k, c in enumerate(chunks)])
    scales = [float(sim3.scale(np.asarray(G[k], np.float64))) for k in range(len(chunks))]
    depth = np.concatenate([(c.depth * scales[k]).astype(np.float32) for k, c in enumerate(chunks)])
    conf = np.concatenate([c.depth_conf for c in chunks]).astype(np.float32)
    K = np.concatenate([c.intrinsic for c in chunks])
    poses, d, cf, Kf = fuse_frames(frame, w, placed, depth, conf, K, num_frames=S)
    # images and ground truth: from the copy of largest weight (the earlier chunk on ties)
    primary = np.full(S, -1)
    best = np.full(S, -1.0)
    for i, (f, wi) in enumerate(zip(frame, w)):
        if wi > best[f] + 1e-12:
            best[f], primary[f] = wi, i
    frame_chunk = np.searchsorted(np.cumsum([b - a for a, b in ranges]), primary, side="right")
    images = np.concatenate([c.images for c in chunks])[primary]
    meta = {k: v for k, v in chunks[0].meta.items() if k not in ("chunk", "chunk_start", "chunk_stop")}
    meta["stitched"] = {"method": method, "num_chunks": len(chunks), "ranges": [list(r) for r in ranges],
                        "overlaps": list(overlaps), "chunk_scales": scales}
    seq = Sequence(images=images, depth=np.asarray(d, np.float32), depth_conf=np.asarray(cf, np.float32),
                   intrinsic=np.asarray(Kf, np.float64), cam_to_world=np.asarray(poses, np.float64),
                   timestamps=ts, gt=_merge_gt(chunks, ranges, primary), meta=meta)
    return seq, frame_chunk


def _merge_gt(chunks, ranges, primary):
    if any(c.gt is None for c in chunks):
        return None
    gts = [c.gt for c in chunks]
    cat = lambda name: np.concatenate([getattr(g, name) for g in gts])  # noqa: E731
    dyn = None if any(g.dynamic_mask is None for g in gts) else cat("dynamic_mask")[primary]
    flow = None
    if all(g.flow is not None for g in gts):
        S = ranges[-1][1]
        flow = np.zeros((S - 1,) + gts[0].flow.shape[1:], np.float32)
        for (a, b), g in zip(ranges, gts):  # later chunks overwrite shared pairs: identical ground truth
            flow[a:b - 1] = g.flow
    return GroundTruth(cam_to_world=cat("cam_to_world")[primary], depth=cat("depth")[primary],
                       intrinsic=cat("intrinsic")[primary], dynamic_mask=dyn, flow=flow)



def place_chunks(chunks, transforms, overlap: int | None = None) -> Sequence:
    """The merged sequence of chunks placed by given Sim(3)s ``transforms`` (K, 4, 4), chunk k ->
    common frame (e.g. a pose graph's, or ground truth's for a reference), fused as in
    :func:`cm3d.long_video.stitch_chunks`."""
    chunks = check_chunks(chunks)
    ranges, overlaps, ts = chunk_layout(chunks, overlap)
    G = np.asarray(transforms, np.float64)
    if G.shape != (len(chunks), 4, 4):
        raise StitchError(f"transforms: expected shape ({len(chunks)}, 4, 4) (one per chunk), got {G.shape}")
    return merge_chunks(chunks, ranges, overlaps, ts, G, "placed")[0]
