"""The photometric set-up as numbers: light directions from slant/tilt (camera frame, pointing
toward the light), the paper's crosstalk matrix, and the check that a crosstalk matrix is usable.
Shared by the scene sampler, dataset verification and prediction (numpy only)."""
from __future__ import annotations

import numpy as np

from msps_render.errors import InputError

PAPER_CROSSTALK = np.full((3, 3), 0.04) + np.eye(3) * 0.88  # 0.92 diagonal, 0.04 elsewhere


def crosstalk_problem(M) -> str | None:
    """What is wrong with a crosstalk matrix (rows: camera channels, columns: lights), or None.

    It must be finite and non-negative, every light must reach at least one
    channel, and for three lights it must be invertible (well conditioned):
    a singular matrix makes the lights inseparable and demultiplexing impossible.
    """
    M = np.asarray(M, dtype=np.float64)
    if M.ndim != 2 or M.shape[0] != 3 or M.shape[1] < 1:
        return f"must be a 3xK matrix, got shape {M.shape}"
    if not np.isfinite(M).all():
        return f"has {int((~np.isfinite(M)).sum())} NaN/inf entries"
    if (M < 0).any():
        i, j = (int(x) for x in np.argwhere(M < 0)[0])
        return f"has negative entries (row {i}, column {j}: {M[i, j]:g})"
    dead = [k for k in range(M.shape[1]) if M[:, k].sum() <= 0]
    if dead:
        return f"light {dead[0]} reaches no camera channel (column {dead[0]} is all zero)"
    if M.shape[1] == 3:
        sv = np.linalg.svd(M, compute_uv=False)
        if sv[-1] <= 1e-6 * sv[0]:
            return (f"is singular (rank {int((sv > 1e-6 * sv[0]).sum())}, condition number "
                    f"{'inf' if sv[-1] == 0 else f'{sv[0] / sv[-1]:.3g}'}): the lights cannot be told apart")
    return None


def check_crosstalk(M, source: str = "lights.crosstalk") -> np.ndarray:
    """`M` as a float array, or InputError naming `source`."""
    why = crosstalk_problem(M)
    if why:
        raise InputError(source, f"crosstalk {why}")
    return np.asarray(M, dtype=np.float64)


def direction_from_slant_tilt(slant_deg: float, tilt_deg: float) -> np.ndarray:
    """Unit vector toward the light, camera frame."""
    if not (0.0 < slant_deg < 90.0):
        raise InputError("lights.slant_deg", f"slant must be in (0, 90) degrees, got {slant_deg}")
    s, t = np.radians(slant_deg), np.radians(tilt_deg)
    return np.array([np.sin(s) * np.cos(t), np.sin(s) * np.sin(t), np.cos(s)])


def slant_tilt_from_direction(d) -> tuple[float, float]:
    d = np.asarray(d, dtype=np.float64)
    d = d / np.linalg.norm(d)
    return float(np.degrees(np.arccos(np.clip(d[2], -1, 1)))), float(
        np.degrees(np.arctan2(d[1], d[0])) % 360.0)
