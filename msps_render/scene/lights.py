"""Light directions from slant/tilt, and the paper's coloured-light setup.

Slant is the angle between the light direction and the view axis (+z); tilt is
the azimuth in the image plane measured from +x (image right) toward +y (up).
So tilt 0 lights the right side of the object, tilt 90 the top.
"""
from __future__ import annotations

import numpy as np

from msps_render.errors import InputError
from msps_render.scene.spec import LightSpec

PAPER_CROSSTALK = np.full((3, 3), 0.04) + np.eye(3) * 0.88  # 0.92 diagonal, 0.04 elsewhere


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


def three_lights(
    slant_deg: float = 30.0,
    tilts_deg=(0.0, 120.0, 240.0),
    crosstalk=PAPER_CROSSTALK,
    irradiance: float = 1.0,
    kind: str = "directional",
    distance: float | None = None,
    rng: np.random.Generator | None = None,
    jitter_deg: float = 0.0,
    intensity_jitter: float = 0.0,
) -> tuple[LightSpec, ...]:
    """Light k has direction (slant, tilt_k) and RGB = irradiance * crosstalk[:, k].

    Column k of the crosstalk matrix is how light k registers in the camera's
    R, G, B channels on a white surface (paper: 0.92 own channel, 0.04 others).
    Optional jitter (needs `rng`) perturbs each direction by up to `jitter_deg`
    and each intensity by a factor in [1-intensity_jitter, 1+intensity_jitter].
    """
    M = np.asarray(crosstalk, dtype=np.float64)
    if M.shape != (3, len(tilts_deg)):
        raise InputError("lights.crosstalk", f"crosstalk must be 3x{len(tilts_deg)}, got {M.shape}")
    check_crosstalk(M)
    if (jitter_deg > 0 or intensity_jitter > 0) and rng is None:
        raise ValueError("jitter needs an rng")
    lights = []
    for k, tilt in enumerate(tilts_deg):
        s, t = float(slant_deg), float(tilt)
        gain = 1.0
        if jitter_deg > 0:
            s = float(np.clip(s + rng.uniform(-jitter_deg, jitter_deg), 1.0, 89.0))
            t = t + float(rng.uniform(-jitter_deg, jitter_deg))
        if intensity_jitter > 0:
            gain = float(rng.uniform(1 - intensity_jitter, 1 + intensity_jitter))
        d = direction_from_slant_tilt(s, t)
        rgb = tuple(float(x) for x in irradiance * gain * M[:, k])
        lights.append(LightSpec(kind=kind, direction=tuple(d), rgb=rgb, distance=distance,
                                slant_deg=s, tilt_deg=t % 360.0))
    return tuple(lights)
