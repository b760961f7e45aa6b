"""Light directions from slant/tilt, and the paper's coloured-light setup.

Slant is the angle between the light direction and the view axis (+z); tilt is
the azimuth in the image plane measured from +x (image right) toward +y (up).
So tilt 0 lights the right side of the object, tilt 90 the top.
"""
from __future__ import annotations

import numpy as np

from msps_render.calibration import (PAPER_CROSSTALK, check_crosstalk, crosstalk_problem,  # noqa: F401
                                     direction_from_slant_tilt, slant_tilt_from_direction)
from msps_render.errors import InputError
from msps_render.scene.spec import LightSpec



def random_crosstalk(rng: np.random.Generator, diagonal: tuple[float, float] = (0.75, 0.95),
                     asymmetry: float = 0.5, n: int = 3) -> np.ndarray:
    """A crosstalk matrix of a random rig (columns sum to 1, as the sampler's convention).

    Column k: its own channel gets d ~ U(diagonal) (diagonal dominance); the rest 1 - d is
    split between the other two channels at a fraction f ~ U(0.5 - asymmetry/2, 0.5 + asymmetry/2)
    (asymmetry 0: the paper's symmetric leak; 1: anything from all-in-one to even).
    """
    M = np.zeros((3, n))
    for k in range(n):
        d = float(rng.uniform(*diagonal))
        f = float(rng.uniform(0.5 - asymmetry / 2, 0.5 + asymmetry / 2))
        others = [i for i in range(3) if i != k % 3]
        M[k % 3, k] = d
        M[others[0], k] = (1 - d) * f
        M[others[1], k] = (1 - d) * (1 - f)
    return M


def jitter_direction(d, jitter_deg: float, rng: np.random.Generator,
                     max_slant_deg: float = 89.0) -> tuple[np.ndarray, float, float]:
    """Direction drawn uniformly in the cone of half-angle `jitter_deg` around unit vector `d`.

    Returns (direction, slant, tilt). Uniform on the spherical cap: cos(angle) ~ U(cos j, 1),
    azimuth about `d` ~ U(0, 360) -- two draws from `rng`, as many as the old per-angle jitter,
    so the draws after it keep their stream. So the angle to `d` is <= j (what `jitter_deg`
    promises; perturbing slant and tilt by +-j each reached 1.1 j at slant 30). A slant past
    `max_slant_deg` is set back to it along its meridian (the nearest point of that cap, which
    contains `d`: the angle to `d` only shrinks) so no light grazes or goes below the horizon.
    """
    d = np.asarray(d, dtype=np.float64)
    d = d / np.linalg.norm(d)
    cos_a = 1.0 - float(rng.uniform()) * (1.0 - np.cos(np.radians(jitter_deg)))
    phi = 2 * np.pi * float(rng.uniform())
    # an orthonormal basis (u, v) of the plane normal to d (Frisvad / Duff et al. 2017)
    sign = 1.0 if d[2] >= 0 else -1.0
    a = -1.0 / (sign + d[2])
    b = d[0] * d[1] * a
    u = np.array([1.0 + sign * d[0] * d[0] * a, sign * b, -sign * d[0]])
    v = np.array([b, sign + d[1] * d[1] * a, -d[1]])
    sin_a = np.sqrt(max(0.0, 1.0 - cos_a * cos_a))
    out = cos_a * d + sin_a * (np.cos(phi) * u + np.sin(phi) * v)
    out /= np.linalg.norm(out)
    s, t = slant_tilt_from_direction(out)
    if s > max_slant_deg:
        s = float(max_slant_deg)
        out = direction_from_slant_tilt(s, t)
    return out, s, t


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
    Optional jitter (needs `rng`) turns each direction by up to `jitter_deg` (uniform in that
    cone, `jitter_direction`) and scales each intensity by U(1-intensity_jitter, 1+intensity_jitter).
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
        d = direction_from_slant_tilt(s, t)
        gain = 1.0
        if jitter_deg > 0:
            d, s, t = jitter_direction(d, jitter_deg, rng, max_slant_deg=max(89.0, s))
        if intensity_jitter > 0:
            gain = float(rng.uniform(1 - intensity_jitter, 1 + intensity_jitter))
        rgb = tuple(float(x) for x in irradiance * gain * M[:, k])
        lights.append(LightSpec(kind=kind, direction=tuple(d), rgb=rgb, distance=distance,
                                slant_deg=s, tilt_deg=t % 360.0))
    return tuple(lights)
