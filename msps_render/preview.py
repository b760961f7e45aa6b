"""Display helpers: tone mapping and normal-map colouring for PNG previews.

Storage stays linear HDR; these are for eyes only.
"""
from __future__ import annotations

import numpy as np


def tonemap(img: np.ndarray, mask: np.ndarray | None = None, percentile: float = 99.0) -> np.ndarray:
    """Exposure to the given percentile of the object, then sRGB gamma -> uint8."""
    a = np.asarray(img, dtype=np.float64)
    ref = a[mask] if mask is not None and mask.any() else a.reshape(-1, a.shape[-1])
    white = np.percentile(ref, percentile) if ref.size else 1.0
    return srgb8(a / max(white, 1e-8))


def srgb8(x: np.ndarray) -> np.ndarray:
    """Linear values in [0, 1] (clipped) -> sRGB-encoded uint8 (albedo maps: 1 = white)."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0, 1)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return (srgb * 255 + 0.5).astype(np.uint8)


def normal_to_rgb8(n: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Usual (n+1)/2 colouring; background black."""
    rgb = ((np.asarray(n, dtype=np.float64) + 1) * 0.5 * 255 + 0.5).clip(0, 255).astype(np.uint8)
    if mask is not None:
        rgb[~mask] = 0
    return rgb
