"""Whole-image prediction: overlapping tiles through the network, blended; or the baseline.

The network sees 40x40 patches in training, so a whole image is cut into
overlapping tiles (stride 20 by default), each tile's normals are weighted by a
smooth window that favours tile centres (where the receptive field is
complete), summed, and renormalised.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from msps_render.calibration import PAPER_CROSSTALK, direction_from_slant_tilt
from msps_render.errors import InputError
from msps_render.io.images import read_image, write_png
from msps_render.models.baseline import lambertian_ps
from msps_render.patches import window_origins
from msps_render.preview import normal_to_rgb8
from msps_render.resources import data_dir


def _window(size: int) -> np.ndarray:
    w = np.hanning(size + 2)[1:-1]
    return np.outer(w, w).astype(np.float32) + 1e-3


def predict_image(model, image: np.ndarray, mask: np.ndarray, tile: int = 40, stride: int = 20,
                  batch: int = 64) -> np.ndarray:
    """Normals (H, W, 3) of an image (H, W, 3) with a dual-cue model; 0 outside the mask."""
    import torch

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
    with torch.no_grad():
        for i in range(0, len(keep), batch):
            yx = keep[i:i + batch]
            x = np.stack([image[y:y + tile, x_:x_ + tile] for y, x_ in yx]).transpose(0, 3, 1, 2)
            mk = np.stack([m[y:y + tile, x_:x_ + tile] for y, x_ in yx])[:, None]
            pred, _ = model(torch.from_numpy(np.ascontiguousarray(x, np.float32)),
                            torch.from_numpy(mk.astype(np.float32)))
            pred = pred.numpy().transpose(0, 2, 3, 1)
            for (y, x_), p in zip(yx, pred):
                acc[y:y + tile, x_:x_ + tile] += p * win[..., None]
                wsum[y:y + tile, x_:x_ + tile] += win
    n = acc / np.maximum(np.linalg.norm(acc, axis=-1, keepdims=True), 1e-12)
    n[~m] = 0.0
    return n


def load_calibration(path: str | Path | None, light_dirs: str | None, crosstalk: str | None):
    """Light directions (3x3, rows toward the lights) and crosstalk (3x3) from a JSON file or flags."""
    L = np.array([direction_from_slant_tilt(30.0, t) for t in (0, 120, 240)])
    M = PAPER_CROSSTALK.copy()
    if path:
        p = Path(path)
        try:
            d = json.loads(p.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise InputError(p, f"cannot read calibration JSON ({e})") from None
        if "light_dirs" in d:
            L = np.asarray(d["light_dirs"], dtype=np.float64)
        elif "slant_deg" in d:
            L = np.array([direction_from_slant_tilt(d["slant_deg"], t) for t in d.get("tilts_deg", (0, 120, 240))])
        if "crosstalk" in d:
            M = np.asarray(d["crosstalk"], dtype=np.float64)
    if light_dirs:
        L = np.asarray(json.loads(light_dirs), dtype=np.float64)
    if crosstalk:
        M = np.asarray(json.loads(crosstalk), dtype=np.float64)
    if L.shape != (3, 3) or M.shape != (3, 3):
        raise InputError(path or "--light-dirs/--crosstalk", f"need 3x3 light_dirs and crosstalk, got {L.shape}, {M.shape}")
    return L / np.linalg.norm(L, axis=1, keepdims=True), M


def read_inputs(image_path: str | Path, mask_path: str | Path | None) -> tuple[np.ndarray, np.ndarray]:
    img = read_image(image_path)
    if img.shape[-1] != 3:
        raise InputError(image_path, f"expected a 3-channel RGB image, got {img.shape[-1]} channel(s)")
    if mask_path:
        mk = read_image(mask_path)[..., 0] > 0
        if mk.shape != img.shape[:2]:
            raise InputError(mask_path, f"mask is {mk.shape[1]}x{mk.shape[0]}, image is {img.shape[1]}x{img.shape[0]}")
    else:
        mk = img.sum(-1) > 0
    return img, mk


def predict_main(image: str | Path, out: str | Path, checkpoint: str | Path | None = None,
                 method: str = "net", mask: str | Path | None = None, calibration: str | Path | None = None,
                 light_dirs: str | None = None, crosstalk: str | None = None) -> list[Path]:
    """Write OUT.npy (H, W, 3 normals) and OUT.png (visualisation)."""
    img, mk = read_inputs(image, mask)
    if method == "lambertian":
        L, M = load_calibration(calibration, light_dirs, crosstalk)
        n = lambertian_ps(img, L, M, mk)
    else:
        from msps_render.models.checkpoint import load_checkpoint

        ck = checkpoint or default_checkpoint()
        model, _, _ = load_checkpoint(ck)
        if min(img.shape[:2]) < 40:
            raise InputError(image, f"image is {img.shape[1]}x{img.shape[0]}; the network needs at least 40x40")
        n = predict_image(model, img, mk)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    npy = out.with_suffix(".npy")
    np.save(npy, n.astype(np.float32))
    png = write_png(out.with_suffix(".png"), normal_to_rgb8(n, mk))
    return [npy, png]


def default_checkpoint() -> Path:
    """The small checkpoint shipped in models/ (trained by docs/reproducing.md)."""
    p = data_dir("models") / "dualcue-cpu.pt"
    if not p.is_file():
        raise InputError(p, "no shipped checkpoint; pass --checkpoint")
    return p
