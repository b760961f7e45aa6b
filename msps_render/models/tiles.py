"""Whole-image prediction by a patch network: overlapping tiles through the network, blended.

The network sees 40x40 patches in training, so a whole image is cut into
overlapping tiles (stride 20 by default), each tile's normals are weighted by a
smooth window that favours tile centres (where the receptive field is
complete), summed, and renormalised.
"""
from __future__ import annotations

import numpy as np

from msps_render.patches import window_origins


def _window(size: int) -> np.ndarray:
    w = np.hanning(size + 2)[1:-1]
    return np.outer(w, w).astype(np.float32) + 1e-3


def predict_image(model, image: np.ndarray, mask: np.ndarray, tile: int = 40, stride: int = 20,
                  batch: int = 64, rig: np.ndarray | None = None, on_batch=None) -> np.ndarray:
    """Normals (H, W, 3) of an image (H, W, 3) with a dual-cue model; 0 outside the mask.
    `rig` = crosstalk @ light_dirs (3, 3): needed by a network with the Lambertian cue.
    `on_batch(done, total)`: told the tiles done, 0 first (a progress line on large images)."""
    import torch

    rig_t = None if rig is None else torch.as_tensor(np.asarray(rig), dtype=torch.float32)
    H, W = mask.shape
    if H < tile or W < tile:
        raise ValueError(f"image {H}x{W} is smaller than the {tile}x{tile} tile")
    origins = window_origins(H, W, tile, stride)
    m = mask.astype(bool)
    keep = [(y, x) for y, x in origins if m[y:y + tile, x:x + tile].any()]
    acc = np.zeros((H, W, 3), np.float32)
    wsum = np.zeros((H, W), np.float32)
    win = _window(tile)
    model.eval()
    if on_batch:
        on_batch(0, len(keep))
    with torch.no_grad():
        for i in range(0, len(keep), batch):
            yx = keep[i:i + batch]
            x = np.stack([image[y:y + tile, x_:x_ + tile] for y, x_ in yx]).transpose(0, 3, 1, 2)
            mk = np.stack([m[y:y + tile, x_:x_ + tile] for y, x_ in yx])[:, None]
            pred, _ = model(torch.from_numpy(np.ascontiguousarray(x, np.float32)),
                            torch.from_numpy(mk.astype(np.float32)), rig_t)
            pred = pred.numpy().transpose(0, 2, 3, 1)
            for (y, x_), p in zip(yx, pred):
                acc[y:y + tile, x_:x_ + tile] += p * win[..., None]
                wsum[y:y + tile, x_:x_ + tile] += win
            if on_batch:
                on_batch(min(i + batch, len(keep)), len(keep))
    n = acc / np.maximum(np.linalg.norm(acc, axis=-1, keepdims=True), 1e-12)
    n[~m] = 0.0
    return n
