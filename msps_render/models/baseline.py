"""Calibrated Lambertian photometric stereo on the three channels of one image (Woodham).

With light k of direction l_k whose response in channel i on a white surface
is M[i, k] (the crosstalk matrix), a Lambertian pixel of grey albedo rho and
normal n reads c_i = rho * sum_k M[i, k] max(0, l_k . n).  Ignoring the
max (unshadowed pixels) this is c = rho * M L n, so n = normalise((M L)^-1 c).
The grey-albedo assumption is the paper's "constant albedo" baseline: coloured
surfaces break it, which is exactly why the network is needed.
"""
from __future__ import annotations

import numpy as np


def lambertian_ps(image: np.ndarray, light_dirs: np.ndarray, crosstalk: np.ndarray,
                  mask: np.ndarray | None = None) -> np.ndarray:
    """Normals (..., 3) from an image (..., 3); light_dirs rows = unit vectors toward the lights."""
    A = np.asarray(crosstalk, dtype=np.float64) @ np.asarray(light_dirs, dtype=np.float64)  # c = A (rho n)
    b = np.asarray(image, dtype=np.float64) @ np.linalg.inv(A).T
    n = b / np.maximum(np.linalg.norm(b, axis=-1, keepdims=True), 1e-12)
    n[np.linalg.norm(b, axis=-1) < 1e-12] = (0.0, 0.0, 1.0)
    if mask is not None:
        n = np.where(np.asarray(mask, bool)[..., None], n, 0.0)
    return n.astype(np.float32)


def unshadowed(normal: np.ndarray, light_dirs: np.ndarray, mask: np.ndarray, margin: float = 0.02) -> np.ndarray:
    """Pixels lit by every light (n . l_k > margin for all k): where Lambertian PS is exact."""
    d = np.asarray(normal) @ np.asarray(light_dirs).T
    return np.asarray(mask, bool) & (d > margin).all(-1)
