"""The accuracy metric of the project: the angle between normals, atan2(|a x b|, a . b).

One definition for the training loss and validation (`angular_error`, torch tensors
(B, 3, H, W)), the Lambertian baseline and evaluation (`angular_error_deg`, numpy
(..., 3)), and the summary statistics of a set of errors (`error_stats`).

Why atan2 and not acos(a . b): acos has an infinite gradient at zero error, and
clamping the cosine in float32 biases every correct pixel by ~0.08 deg.

numpy only at import; the torch function uses tensor methods, so the Lambertian
baseline stays torch-free.
"""
from __future__ import annotations

import numpy as np


def angular_error(pred, gt):
    """Per-pixel angle (radians) between (B, 3, H, W) tensors, shape (B, 1, H, W)."""
    a = pred / pred.norm(dim=1, keepdim=True).clamp_min(1e-12)
    b = gt / gt.norm(dim=1, keepdim=True).clamp_min(1e-12)
    cross = a.cross(b, dim=1)
    sin = ((cross ** 2).sum(1, keepdim=True) + 1e-12).sqrt()
    return sin.atan2((a * b).sum(1, keepdim=True))


def angular_error_deg(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per-pixel angle (degrees) between normals (..., 3) (normalised here)."""
    p = np.asarray(pred, dtype=np.float64)
    g = np.asarray(gt, dtype=np.float64)
    p = p / np.maximum(np.linalg.norm(p, axis=-1, keepdims=True), 1e-12)
    g = g / np.maximum(np.linalg.norm(g, axis=-1, keepdims=True), 1e-12)
    sin = np.linalg.norm(np.cross(p, g), axis=-1)
    return np.degrees(np.arctan2(sin, (p * g).sum(-1)))


def error_stats(err: np.ndarray) -> dict:
    """MAE, median, max and the share under 10/20/30 degrees of per-pixel errors (degrees)."""
    err = np.asarray(err, dtype=np.float64)
    if err.size == 0:
        return {"n_pixels": 0}
    return {"mae_deg": float(err.mean()), "median_deg": float(np.median(err)), "max_deg": float(err.max()),
            "pct_under_10": float((err < 10).mean() * 100), "pct_under_20": float((err < 20).mean() * 100),
            "pct_under_30": float((err < 30).mean() * 100), "n_pixels": int(err.size)}
