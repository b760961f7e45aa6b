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

from msps_render.calibration import geometry_warnings, load_calibration_file, parse_calibration
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
    """Light directions (3x3, rows toward the lights) and crosstalk (3x3) from a calibration JSON
    (schema: `msps_render.calibration`) and/or the --light-dirs/--crosstalk flags (which win)."""
    L, M = load_calibration_file(path) if path else parse_calibration({})
    if light_dirs or crosstalk:
        d = {}
        for key, text in (("light_dirs", light_dirs), ("crosstalk", crosstalk)):
            if text:
                try:
                    d[key] = json.loads(text)
                except json.JSONDecodeError as e:
                    raise InputError(f"--{key.replace('_', '-')}", f"not valid JSON ({e})") from None
        L2, M2 = parse_calibration({"light_dirs": d.get("light_dirs", L.tolist()),
                                    "crosstalk": d.get("crosstalk", M.tolist())},
                                   "--light-dirs/--crosstalk")
        L, M = L2, M2
    return L, M


def read_inputs(image_path: str | Path, mask_path: str | Path | None,
                linear: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """PNG keeps 16 bits (Pillow would truncate them) and is sRGB-decoded unless `linear`."""
    if Path(image_path).suffix.lower() == ".png":
        from msps_render.compose import read_photo

        img = read_photo(Path(image_path), srgb=not linear).astype(np.float32)
    else:
        img = read_image(image_path)
    if img.shape[-1] == 4:  # RGBA: the alpha channel carries no radiance
        img = np.ascontiguousarray(img[..., :3])
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
                 light_dirs: str | None = None, crosstalk: str | None = None, warn=None,
                 linear: bool = False) -> list[Path]:
    """Write OUT.npy (H, W, 3 normals) and OUT.png (visualisation).

    `warn(message)` (default: a 'warning: ...' line on stderr) hears when the Lambertian path assumes
    the paper's lights for lack of a calibration, and when the given lights differ from the geometry
    the network was trained for (the network takes no light input)."""
    warn = warn or _warn_stderr
    img, mk = read_inputs(image, mask, linear)
    calibrated = bool(calibration or light_dirs or crosstalk)
    L, M = load_calibration(calibration, light_dirs, crosstalk)  # validated on both paths
    if method == "lambertian":
        if not calibrated:
            warn("no --calibration: assuming the paper's lights (slant 30 deg, tilts 0/120/240 deg, "
                 "crosstalk 0.92/0.04)")
        n = lambertian_ps(img, L, M, mk)
    else:
        from msps_render.models.checkpoint import load_checkpoint

        ck = checkpoint or default_checkpoint()
        model, _, ckd = load_checkpoint(ck)
        if calibrated:
            for w in geometry_warnings(L, M, ckd.get("train_lights")):
                warn(w)
        if min(img.shape[:2]) < 40:
            raise InputError(image, f"image is {img.shape[1]}x{img.shape[0]}; the network needs at least 40x40")
        n = predict_image(model, img, mk)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    npy = out.with_suffix(".npy")
    np.save(npy, n.astype(np.float32))
    png = write_png(out.with_suffix(".png"), normal_to_rgb8(n, mk))
    return [npy, png]


def _warn_stderr(msg: str) -> None:
    import sys

    print(f"warning: {msg}", file=sys.stderr)


def default_checkpoint() -> Path:
    """The small checkpoint shipped in models/ (trained by docs/reproducing.md)."""
    p = data_dir("models") / "dualcue-cpu.pt"
    if not p.is_file():
        raise InputError(p, "no shipped checkpoint; pass --checkpoint")
    return p
