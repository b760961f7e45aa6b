"""HDR environment maps: reading EXR/HDR files and a procedural sky.

Maps are equirectangular float32 (H, 2H, 3) linear radiance.  Files are
validated on load (NaN/inf/negative values are errors naming the file) so a bad
map fails before any rendering starts.
"""
from __future__ import annotations

import os
import re
from functools import lru_cache
from pathlib import Path

import numpy as np

from msps_render.errors import InputError
from msps_render.io.images import FORMATS, HDR_SUFFIXES


def expand_path(pattern: str) -> str:
    """`$VARS` and `~` of a config path expanded.  Why: a preset that names third-party assets (the
    unseen-* test sets: `$MSPS_TEST_DATA/meshes/...`) cannot know where a user keeps them, and a path
    relative to the working directory breaks from any other folder."""
    return os.path.expanduser(os.path.expandvars(pattern))


def missing_asset(pattern: str, path: str, problem: str) -> InputError:
    """The error for a config path that names no file: an unset variable is named as the cause."""
    unset = re.search(r"\$\{?(\w+)", path)  # expandvars leaves unset variables as written
    if unset:
        return InputError(pattern, f"environment variable {unset.group(1)} is not set (the folder this path is "
                                   "read from; the unseen-* presets need the third-party test assets: "
                                   "export MSPS_TEST_DATA=FOLDER holding meshes/ and envmaps/, e.g. ../shared/data)")
    return InputError(path, problem + (f" (from '{pattern}' in the config)" if path != pattern else ""))


@lru_cache(maxsize=4)
def load_envmap(path: str) -> np.ndarray:
    """Read and validate an environment map (cached per process: maps are read-only); `$VARS` expanded."""
    p = Path(expand_path(path))
    if not p.is_file():
        raise missing_asset(path, str(p), "environment map not found")
    fmt = FORMATS.get(p.suffix.lower())
    if fmt is None or not fmt.hdr:
        raise InputError(p, f"unsupported environment map format '{p.suffix}' (use {' or '.join(HDR_SUFFIXES)})")
    img = fmt.read(p)
    if img.ndim != 3 or img.shape[0] < 2 or img.shape[1] < 2:
        raise InputError(p, f"environment map has unusable shape {img.shape}")
    bad_nan = int((~np.isfinite(img)).sum())
    if bad_nan:
        raise InputError(p, f"environment map has {bad_nan} NaN/inf values")
    neg = int((img < 0).sum())
    if neg:
        raise InputError(p, f"environment map has {neg} negative values")
    img.setflags(write=False)
    return img


def procedural_sky(seed: int = 0, height: int = 128) -> np.ndarray:
    """A deterministic HDR sky: vertical gradient, warm ground, and 1–3 sun-like blobs.

    Why: test sets need a plausible, high-dynamic-range surround without
    downloading anything; the blobs give the hard directional component real
    maps have.
    """
    rng = np.random.default_rng(seed)
    H, W = height, 2 * height
    v = (np.arange(H) + 0.5) / H  # 0 top (zenith) .. 1 bottom
    u = (np.arange(W) + 0.5) / W
    theta = np.pi * v[:, None] * np.ones((1, W))
    phi = 2 * np.pi * u[None, :] * np.ones((H, 1))
    up = np.cos(theta)  # 1 at zenith
    zenith = np.array([0.25, 0.45, 0.9]) * rng.uniform(0.6, 1.2)
    horizon = np.array([0.9, 0.85, 0.8]) * rng.uniform(0.6, 1.2)
    ground = np.array([0.25, 0.2, 0.15]) * rng.uniform(0.3, 1.0)
    t = np.clip(up, 0, 1)[..., None]
    sky = horizon * (1 - t) + zenith * t
    img = np.where(up[..., None] > 0, sky, ground * np.ones_like(sky))
    # sun-like blobs: direction in the upper hemisphere, angular radius a few degrees
    dirs = np.stack([np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)], -1)
    for _ in range(int(rng.integers(1, 4))):
        th = rng.uniform(0.1, 1.3)
        ph = rng.uniform(0, 2 * np.pi)
        d = np.array([np.sin(th) * np.cos(ph), np.cos(th), np.sin(th) * np.sin(ph)])
        ang = np.arccos(np.clip(dirs @ d, -1, 1))
        width = np.radians(rng.uniform(2.0, 6.0))
        power = rng.uniform(20.0, 200.0)
        color = np.array([1.0, 0.95, 0.85]) * rng.uniform(0.8, 1.2, 3)
        img = img + power * np.exp(-0.5 * (ang / width) ** 2)[..., None] * color
    return img.astype(np.float32)


def envmap_pixels(source: str, seed: int = 0) -> np.ndarray:
    return procedural_sky(seed) if source == "procedural" else load_envmap(source)


def _pixel_directions(H: int, W: int, rotation_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """((H, W, 3) world direction each pixel looks along, (H, 1) solid angle per pixel of each row)."""
    v = (np.arange(H) + 0.5) / H
    u = (np.arange(W) + 0.5) / W
    theta = np.pi * v
    phi = 2 * np.pi * u - np.radians(rotation_deg)
    st = np.sin(theta)[:, None]
    d = np.stack([st * np.sin(phi)[None, :], np.cos(theta)[:, None] * np.ones((1, W)),
                  -st * np.cos(phi)[None, :]], -1)
    return d, (np.pi / H) * (2 * np.pi / W) * st


def irradiance_on_axis(img: np.ndarray, axis=(0.0, 0.0, 1.0), rotation_deg: float = 0.0) -> np.ndarray:
    """Per-channel (3,) cosine-weighted irradiance of the map on a plane facing `axis` (world frame).

    Equirect convention of Mitsuba's `envmap`: pixel (row v, column u) looks along
    (sin θ sin φ, cos θ, -sin θ cos φ) with θ = π v, φ = 2π u (+y up), and
    `to_world = rotate(+y, rotation_deg)` turns that into φ - rotation.
    Verified by rendering (tests/test_robust_env.py: a white Lambertian sphere under
    the env only matches π·L = E(n) per pixel within MC noise, mean ratio 1.00 ± 0.01;
    mirrored conventions are off by factors of 2-5).  Pixel centres are taken at
    (i + 0.5)/W, (j + 0.5)/H; Mitsuba's bilinear lookup differs by < 1%.
    """
    H, W = img.shape[:2]
    d, dA = _pixel_directions(H, W, rotation_deg)
    cos = np.clip(d @ np.asarray(axis, dtype=np.float64), 0, None)
    w = cos * dA
    return np.einsum("hw,hwc->c", w, img[..., :3].astype(np.float64))


# `environment_for_ratio` scales a map by ratio x lights / E(+z), E = its channel-summed irradiance on the
# camera-facing plane.  A surface of normal n then receives ratio x lights x E(n) / E(+z) from it.  Below this
# fraction E(+z) / max E(n) over camera-facing normals, some visible surface would get more than 100 x the
# asked ratio of the lights' irradiance: the "ambient" term would swamp the photometric cue it is meant to
# perturb, and as E(+z) -> 0 the scale diverges.  Real maps sit far above it (venice_sunset_1k: >= 0.49 at
# every rotation; the procedural sky: >= 0.3).
MIN_FRONT_FRACTION = 0.01
_CHECK_ROWS = 64  # maps are box-averaged to at most this many rows for the check (irradiance is an integral)


def _fibonacci_hemisphere(n: int = 64) -> np.ndarray:
    """n roughly uniform unit vectors with z >= 0 (camera-facing normals)."""
    i = np.arange(n) + 0.5
    z = 1.0 - i / n
    r = np.sqrt(1.0 - z * z)
    a = np.pi * (1 + 5 ** 0.5) * i
    return np.stack([r * np.cos(a), r * np.sin(a), z], -1)


def _downsample(img: np.ndarray, rows: int = _CHECK_ROWS) -> np.ndarray:
    H, W = img.shape[:2]
    f = max(1, H // rows)
    g = max(1, W // (2 * rows)) if W >= 2 * rows else 1
    H2, W2 = H // f, W // g
    a = img[:H2 * f, :W2 * g, :3].astype(np.float64)
    return a.reshape(H2, f, W2, g, 3).mean(axis=(1, 3))


def front_fraction(img: np.ndarray, rotations=(0.0,)) -> tuple[float, float]:
    """(smallest E(+z) / max over camera-facing normals n of E(n), the rotation where it occurs).

    E is channel-summed irradiance; 0 for a map that sheds no light on the camera-facing plane."""
    a = _downsample(img)
    H, W = a.shape[:2]
    normals = _fibonacci_hemisphere()
    worst, at = np.inf, float(rotations[0])
    for rot in rotations:
        d, dA = _pixel_directions(H, W, float(rot))
        rad = (a.sum(-1) * dA).reshape(-1)  # channel-summed radiance x solid angle
        E = np.clip(d.reshape(-1, 3) @ np.vstack([[0.0, 0.0, 1.0], normals]).T, 0, None).T @ rad
        top = float(E.max())
        frac = float(E[0] / top) if top > 0 else 0.0
        if frac < worst:
            worst, at = frac, float(rot)
    return worst, at


def check_front_irradiance(img: np.ndarray, source: str | Path, random_rotation: bool) -> None:
    """`InputError` naming `source` when the map (at any rotation it may be drawn at) lights the
    camera-facing plane too little to be scaled to an irradiance ratio (see `MIN_FRONT_FRACTION`)."""
    rotations = np.arange(0.0, 360.0, 10.0) if random_rotation else (0.0,)
    frac, rot = front_fraction(img, rotations)
    if frac < MIN_FRONT_FRACTION:
        where = f" at rotation {rot:g} deg (environment.random_rotation)" if random_rotation else ""
        raise InputError(source, f"environment map gives almost no light on the camera-facing hemisphere{where}: "
                                 f"its irradiance there is {frac:.2g} of its maximum on a visible surface "
                                 f"(needs >= {MIN_FRONT_FRACTION:g}), so scaling it to the requested ratio "
                                 f"would let it swamp the lights elsewhere")
