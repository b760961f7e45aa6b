"""The photometric-stereo rig as one value: N lights, M camera channels, a capture (numpy + pydantic only).

Why one home: scene sampling, the integrator, ground truth, the shard writer, exports, the
baseline and the networks all read the same three things -- where the lights are, how each
light registers in each camera channel, and which lights are on in which image.  Spelled once
here, a rig of 96 white lights seen one at a time (classic photometric stereo), 50 near LEDs on
a plane, or the seed paper's three coloured lights in one RGB shot are the same value.

Three pieces:
- `RigConfig` (the `[scene.rig]` table): a light *layout generator* (three, ring, hemisphere,
  grid, file), light kind and colour, camera channels, capture, calibration errors.
- `RigSpec` (in every `SceneSpec` of a rig dataset, pure data): the per-frame channels, the
  capture's shots, each light's LED anisotropy, and the *nominal* lights (what a user's
  calibration would say) next to the true ones (`SceneSpec.lights`, what was rendered).
- `Rig` (the numbers a solver needs): directions (N, 3), the channel-by-light matrix C (M, N)
  -- C[m, n] is channel m's reading of light n on a white surface facing it, today's
  "crosstalk" generalised --, the shots, the point lights' positions and anisotropy.

Image model (docs/rigs.md): shot s, channel m of a Lambertian pixel of albedo rho at x with
normal n reads  I[s, m] = rho/pi * sum_{n in s} C[m, n] * a_n(x) * max(0, n . l_n(x)),
with l_n(x) the unit vector from x to light n (constant for directional lights) and a_n(x) the
near-light factor (1 for directional; (d_n/|p_n - x|)^2 * cos^mu(angle off the LED axis) for a
point light at p_n of distance d_n from the origin, so C is its reading at the origin).

Spectral rigs (scene mode "spectral", `spectral_rig`): the lights are LED spectra e_n (`led_peaks_nm`,
`spectra`) and the camera's M channels are sensitivities S_m over wavelength (narrow-band `filters`, or
a measured `camera` table); then C[m, n] = E_n * Σ_λ e_n(λ) S_m(λ) / Σ_m' Σ_λ e_n(λ) S_m'(λ), the
closed-form spectral integral normalised as `spectral.effective_crosstalk` (E_n: the light's irradiance),
stored per frame in `RigSpec.crosstalk` (the shares) and the lights' `rgb` (their sums).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, field_validator, model_serializer, model_validator

from msps_render.config_io import FrozenModel, omit_defaults, StrictModel
from msps_render.errors import InputError

CAPTURES = ("multiplexed", "sequential")
LAYOUTS = ("three", "ring", "hemisphere", "grid", "file")
# Camera channels in RGB mode: rows = channels, columns = the renderer's R, G, B.
CHANNEL_SETS = {"rgb": ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
                "mono": ((1 / 3, 1 / 3, 1 / 3),)}
CHANNEL_NAMES = {"rgb": ("R", "G", "B"), "mono": ("Y",)}
COLOURS = {"white": (1.0, 1.0, 1.0), "red": (1.0, 0.0, 0.0), "green": (0.0, 1.0, 0.0), "blue": (0.0, 0.0, 1.0)}
MIN_LIGHT_DISTANCE = 1.0  # objects fit in the unit sphere: a point light must lie outside it
MAX_SLANT_DEG = 89.0
SPECTRAL_SPEC_FIELDS = ("filters", "camera", "crosstalk")  # RigSpec: left out of RGB rigs' JSON
SPECTRAL_CONFIG_FIELDS = ("filters", "camera", "led_peaks_nm", "led_fwhm_nm", "spectra")  # RigConfig: same
# The seed paper's rig: three lights at slant 30 deg, tilts 0/120/240, crosstalk 0.92 own / 0.04 others.
PAPER_SLANT_DEG = 30.0
PAPER_TILTS_DEG = (0.0, 120.0, 240.0)
PAPER_CROSSTALK = np.full((3, 3), 0.04) + np.eye(3) * 0.88
DEFAULT_SPECTRAL_CAMERA = "Nikon 5100 (NPL)"  # as msps_render.render.spectral.DEFAULT_CAMERA


# ================================================================ the per-frame value
class RigSpec(FrozenModel):
    """What a SceneSpec of a rig dataset carries beyond its lights (see the module docstring)."""

    name: str = Field("rig", description="layout name (provenance)")
    channels: tuple[tuple[float, float, float], ...] = Field(
        CHANNEL_SETS["rgb"], description="rgb mode: camera channel m = channels[m] . (R, G, B)")
    channel_names: tuple[str, ...] = CHANNEL_NAMES["rgb"]
    shots: tuple[tuple[int, ...], ...] = Field(description="light indices on in each image")
    anisotropy: tuple[float, ...] = Field((), description="per light: LED cos^mu exponent about its axis "
                                                          "(point lights; empty = all 0)")
    axes: tuple[tuple[float, float, float], ...] = Field((), description="per light: LED axis (unit, "
                                                                          "from the LED); empty = toward the origin")
    nominal_dirs: tuple[tuple[float, float, float], ...] = Field(description="the calibration's light directions")
    nominal_rgb: tuple[tuple[float, float, float], ...] = Field(description="the calibration's light RGB "
                                                                      "(irradiance; point lights: intensity)")
    allow_unseparable: bool = False
    # spectral rigs (scene mode "spectral"): the camera's channels are sensitivities over wavelength, the
    # lights carry spectra (`LightSpec.spectrum`; `LightSpec.rgb` then only counts by its sum, the light's
    # reading summed over the channels on a white surface facing it), and `channels` is empty
    filters: tuple[tuple[float, float], ...] = Field((), description="spectral rigs: channel m is a Gaussian "
                                                                    "filter [centre nm, FWHM nm]")
    camera: str | None = Field(None, description="spectral rigs without filters: the camera's sensitivities "
                                                 "(colour-science name or CSV, msps_render.spectral)")
    crosstalk: tuple[tuple[float, ...], ...] | None = Field(
        None, description="spectral rigs: (M, N) share of light n's camera signal in channel m on a white "
                          "surface facing it (columns sum to 1), the closed-form integral of its spectrum "
                          "times the channel's sensitivity")

    @model_serializer(mode="wrap")
    def _without_absent_spectral(self, handler):
        """RGB rigs serialise without the spectral fields: their stored scenes keep their bytes."""
        return omit_defaults(self, handler(self), SPECTRAL_SPEC_FIELDS)

    @model_validator(mode="after")
    def _check(self) -> "RigSpec":
        n = len(self.nominal_dirs)
        if self.crosstalk is None:
            if self.filters or self.camera is not None:
                raise ValueError("a spectral rig (filters or camera) needs its crosstalk")
            if len(self.channel_names) != len(self.channels):
                raise ValueError(f"{len(self.channel_names)} channel names for {len(self.channels)} channels")
        else:
            m = len(self.crosstalk)
            if self.channels:
                raise ValueError("a spectral rig's channels are its filters or camera, not rows on R, G, B")
            if bool(self.filters) == (self.camera is not None):
                raise ValueError("a spectral rig needs either filters or a camera")
            if self.filters and len(self.filters) != m:
                raise ValueError(f"{len(self.filters)} filters for {m} crosstalk rows")
            if len(self.channel_names) != m or any(len(row) != n for row in self.crosstalk):
                raise ValueError(f"crosstalk must be (channels {len(self.channel_names)}, lights {n})")
        if len(self.nominal_rgb) != n:
            raise ValueError(f"{len(self.nominal_rgb)} nominal colours for {n} lights")
        if self.anisotropy and len(self.anisotropy) != n:
            raise ValueError(f"{len(self.anisotropy)} anisotropy exponents for {n} lights")
        for s, shot in enumerate(self.shots):
            bad = [k for k in shot if not 0 <= k < n]
            if bad or not shot:
                raise ValueError(f"shot {s} names light {bad[0] if bad else '(none)'}; lights are 0..{n - 1}")
        return self

    @property
    def n_channels(self) -> int:
        return len(self.channel_names)

    @property
    def is_spectral(self) -> bool:
        """Rendered in spectral mode: channels are sensitivities over wavelength, lights carry spectra."""
        return self.crosstalk is not None


# ================================================================ the numbers a solver reads
@dataclass(frozen=True, eq=False)
class Rig:
    """Lights (directions toward them, camera frame), the channel-by-light matrix and the capture.

    The three-light, one-shot, three-channel case is the seed paper's rig (`Rig.paper()`), read by
    the dual-cue network and its test-time steps as c = diag(rho) A n with A = crosstalk @ light_dirs
    (`matrix`).  `assumed`: no calibration was given, the paper's rig stands in."""

    light_dirs: np.ndarray  # (N, 3)
    crosstalk: np.ndarray  # (M, N): C[m, n], channel m's response to light n on a white surface
    assumed: bool = False
    shots: tuple[tuple[int, ...], ...] | None = None  # None: one multiplexed shot of every light
    positions: np.ndarray | None = None  # (N, 3) point lights' positions (NaN rows: directional)
    anisotropy: np.ndarray | None = None  # (N,) LED exponent mu (point lights)

    @property
    def n_lights(self) -> int:
        return int(np.asarray(self.light_dirs).shape[0])

    @property
    def n_channels(self) -> int:
        return int(np.asarray(self.crosstalk).shape[0])

    @property
    def shot_list(self) -> tuple[tuple[int, ...], ...]:
        return self.shots if self.shots is not None else (tuple(range(self.n_lights)),)

    @property
    def n_shots(self) -> int:
        return len(self.shot_list)

    @property
    def is_three_light(self) -> bool:
        """The seed paper's kind of rig: three directional lights, three channels, one shot."""
        return (self.n_lights == 3 and self.n_channels == 3 and self.n_shots == 1
                and not self.has_point_lights)

    @property
    def has_point_lights(self) -> bool:
        return self.positions is not None and bool(np.isfinite(np.asarray(self.positions)).all(-1).any())

    def require_three(self, what: str) -> "Rig":
        """This rig, or one InputError line saying `what` needs the three-light rig."""
        if not self.is_three_light:
            raise InputError(what, f"needs the three-light rig (3 directional lights, 3 channels, one shot); "
                                   f"got {self.describe()}")
        return self

    def describe(self) -> str:
        kind = "near point" if self.has_point_lights else "directional"
        cap = "multiplexed" if self.n_shots == 1 and self.n_lights > 1 else (
            "sequential" if self.n_shots == self.n_lights else f"{self.n_shots} shots")
        return f"{self.n_lights} {kind} lights x {self.n_channels} channels, {cap}"

    @property
    def matrix(self) -> np.ndarray:
        """A = crosstalk @ light_dirs (M, 3): a white pixel of one multiplexed shot is A n."""
        return np.asarray(self.crosstalk, np.float64) @ np.asarray(self.light_dirs, np.float64)

    def observation_matrix(self) -> np.ndarray:
        """(S*M, 3): row (s, m) = sum_{n in shot s} C[m, n] l_n -- the unshadowed Lambertian model
        of every reading of one pixel (directional lights), I = rho * row . n."""
        C = np.asarray(self.crosstalk, np.float64)
        L = np.asarray(self.light_dirs, np.float64)
        return np.concatenate([C[:, list(s)] @ L[list(s)] for s in self.shot_list])

    @classmethod
    def of(cls, obj) -> "Rig":
        """The rig of anything that carries `light_dirs` and `crosstalk` (a frame, a real capture)."""
        rig = getattr(obj, "rig", None)
        if isinstance(rig, Rig):
            return rig
        return cls(obj.light_dirs, obj.crosstalk)

    @classmethod
    def paper(cls) -> "Rig":
        """The paper's rig (slant 30 deg, tilts 0/120/240, crosstalk 0.92/0.04), assumed."""
        s = math.radians(PAPER_SLANT_DEG)
        L = np.array([[math.sin(s) * math.cos(math.radians(t)), math.sin(s) * math.sin(math.radians(t)),
                       math.cos(s)] for t in PAPER_TILTS_DEG])
        return cls(L, PAPER_CROSSTALK.copy(), assumed=True)


def rig_of_spec(spec) -> Rig:
    """The true rig of a SceneSpec (what was rendered); the three-light rig when it has no RigSpec."""
    dirs = np.array([l.direction for l in spec.lights], np.float64).reshape(-1, 3)
    pos = np.array([[c * l.distance for c in l.direction] if l.kind == "point" else [np.nan] * 3
                    for l in spec.lights], np.float64).reshape(-1, 3)
    rgb = np.array([l.rgb for l in spec.lights], np.float64).reshape(-1, 3)
    r = spec.rig
    if r is None:
        C = np.array(spec.crosstalk, np.float64) if spec.crosstalk is not None else _unit_columns(rgb.T)
        return Rig(dirs, C, positions=pos if np.isfinite(pos).any() else None)
    C = _channel_by_light(r, rgb, spec.lights)  # (M, N)
    mu = np.asarray(r.anisotropy, np.float64) if r.anisotropy else None
    return Rig(dirs, C, shots=r.shots, positions=pos if np.isfinite(pos).any() else None, anisotropy=mu)


def nominal_rig_of_spec(spec) -> Rig:
    """The rig a user's calibration would give for this frame (before calibration errors)."""
    true = rig_of_spec(spec)
    r = spec.rig
    if r is None:
        return true
    C = _channel_by_light(r, np.asarray(r.nominal_rgb, np.float64), spec.lights)
    pos = None
    if true.positions is not None:  # a point light's nominal position: its true distance along the nominal direction
        d = np.linalg.norm(np.nan_to_num(true.positions), axis=1)
        pos = np.where(np.isfinite(true.positions), np.asarray(r.nominal_dirs) * d[:, None], np.nan)
    return Rig(np.asarray(r.nominal_dirs, np.float64), C, shots=r.shots, positions=pos,
               anisotropy=true.anisotropy)


def _channel_by_light(r: RigSpec, rgb: np.ndarray, lights) -> np.ndarray:
    """(M, N) C: RGB rigs, channels @ (rgb / d^2); spectral rigs, each light's channel shares times its
    reading summed over the channels (sum(rgb) / d^2): C[m, n] = E_n * Σ_λ e_n(λ) S_m(λ) / Σ_m' (same)."""
    if r.crosstalk is not None:
        return np.asarray(r.crosstalk, np.float64) * (np.asarray(rgb, np.float64).sum(axis=1) / _dist2(lights))[None, :]
    return np.asarray(r.channels, np.float64) @ (np.asarray(rgb, np.float64) / _dist2(lights)[:, None]).T


def _dist2(lights) -> np.ndarray:
    """Per light: d^2 for a point light (its `rgb` is an intensity, its reading at the origin rgb / d^2), 1 far."""
    return np.array([l.distance ** 2 if l.kind == "point" else 1.0 for l in lights], np.float64)


def _unit_columns(a: np.ndarray) -> np.ndarray:
    s = a.sum(axis=0, keepdims=True)
    return np.divide(a, s, out=np.zeros_like(a), where=s > 0)


# ================================================================ per-pixel geometry of near lights
def pixel_light_dirs(rig: Rig, points: np.ndarray) -> np.ndarray:
    """(N, ..., 3) unit vectors from each surface point (..., 3) toward each light (camera frame)."""
    points = np.asarray(points, np.float64)
    out = np.empty((rig.n_lights,) + points.shape, np.float64)
    pos = rig.positions if rig.positions is not None else np.full((rig.n_lights, 3), np.nan)
    for n in range(rig.n_lights):
        if np.isfinite(pos[n]).all():
            v = pos[n] - points
            out[n] = v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)
        else:
            out[n] = np.asarray(rig.light_dirs[n], np.float64)
    return out


def pixel_light_factors(rig: Rig, points: np.ndarray) -> np.ndarray:
    """(N, ...) near-light factor a_n(x): (d_n / |p_n - x|)^2 cos^mu (axis toward the origin); 1 far."""
    points = np.asarray(points, np.float64)
    out = np.ones((rig.n_lights,) + points.shape[:-1], np.float64)
    if rig.positions is None:
        return out
    for n in range(rig.n_lights):
        p = np.asarray(rig.positions[n], np.float64)
        if not np.isfinite(p).all():
            continue
        v = points - p  # from the light to the point
        r = np.maximum(np.linalg.norm(v, axis=-1), 1e-12)
        d = np.linalg.norm(p)
        f = (d / r) ** 2
        mu = float(rig.anisotropy[n]) if rig.anisotropy is not None else 0.0
        if mu:
            axis = -p / d
            f = f * np.maximum((v @ axis) / r, 0.0) ** mu
        out[n] = f
    return out


def pixel_factors_dirs(rig: Rig, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(`pixel_light_dirs`, `pixel_light_factors`) of the same points."""
    return pixel_light_dirs(rig, points), pixel_light_factors(rig, points)


def lambertian_shots(rig: Rig, normal: np.ndarray, albedo, points: np.ndarray | None = None) -> np.ndarray:
    """The closed-form image (S, ..., M) of a Lambertian surface (albedo per channel or grey) under
    this rig, direct light only (no shadows cast by other parts): the physics tests' reference."""
    normal = np.asarray(normal, np.float64)
    pts = np.zeros_like(normal) if points is None else np.asarray(points, np.float64)
    L = pixel_light_dirs(rig, pts)  # (N, ..., 3)
    a = pixel_light_factors(rig, pts)  # (N, ...)
    shade = np.maximum((L * normal[None]).sum(-1), 0.0) * a / np.pi  # (N, ...)
    C = np.asarray(rig.crosstalk, np.float64)  # (M, N)
    rho = np.asarray(albedo, np.float64)
    out = [np.einsum("n...,mn->...m", shade[list(s)], C[:, list(s)]) for s in rig.shot_list]
    return np.stack(out) * rho


# ================================================================ composing the camera's images
def compose_shots(rig: RigSpec, per_light: np.ndarray, env: np.ndarray | None = None) -> np.ndarray:
    """(S, H, W, M) camera images from (N, H, W, 3) per-light RGB radiance (+ the environment in every shot);
    spectral rigs: from (N, H, W, M) per-light camera channels (the renderer integrates them already).

    Linear in the per-light images by construction: shots are sums of lights, channels are linear
    maps of R, G, B -- so a sequential capture sums to the multiplexed one exactly (before noise)."""
    if rig.is_spectral:
        C = np.eye(rig.n_channels, dtype=np.float32)
        if per_light.shape[-1] != len(C):
            raise ValueError(f"a spectral rig of {len(C)} channels got per-light images of {per_light.shape[-1]}")
    else:
        C = np.asarray(rig.channels, np.float32)  # (M, 3)
    if (env is None and rig.shots == tuple((k,) for k in range(len(per_light))) and per_light.dtype == np.float32
            and np.array_equal(C, np.eye(per_light.shape[-1], dtype=np.float32))):
        return per_light  # one image per light through identity channels: the shots ARE the images (no copy)
    out = np.empty((len(rig.shots),) + per_light.shape[1:3] + (len(C),), np.float32)
    base = env.astype(np.float32) if env is not None else None
    for s, shot in enumerate(rig.shots):
        acc = per_light[shot[0]].astype(np.float32).copy()
        for k in shot[1:]:
            acc += per_light[k]
        if base is not None:
            acc += base
        out[s] = acc if rig.is_spectral else acc @ C.T
    return out


def channel_matrix(channels) -> tuple[tuple[float, float, float], ...]:
    if isinstance(channels, str):
        return CHANNEL_SETS[channels]
    rows = tuple(tuple(float(x) for x in r) for r in channels)
    if not rows or any(len(r) != 3 or min(r) < 0 or not math.isfinite(sum(r)) or sum(r) <= 0 for r in rows):
        raise ValueError("channels rows must each be three finite weights >= 0 on R, G, B, not all zero")
    return rows


def channel_names(channels) -> tuple[str, ...]:
    return CHANNEL_NAMES[channels] if isinstance(channels, str) else tuple(f"C{m}" for m in range(len(channels)))


# ================================================================ light files (DiLiGenT layout)
def read_light_file(directions: str | Path, intensities: str | Path | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(directions (N, 3) unit, intensities (N, 3)) from DiLiGenT's text files; InputError naming the file.

    Directions: one 'x y z' row per light, camera frame (x right, y up, z toward the camera), toward
    the light, unit length within 1e-3 and above the horizon (z > 0).  Intensities: one 'r g b' row per
    light, > 0; absent: light_intensities.txt beside the directions, else all ones."""
    p = Path(directions)
    D = _read_rows(p, "light directions")
    norms = np.linalg.norm(D, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-3)
    if len(bad):
        raise InputError(p, f"row {bad[0] + 1}: direction {D[bad[0]].tolist()} is not unit length "
                            f"(|d| = {norms[bad[0]]:.4f})")
    below = np.flatnonzero(D[:, 2] <= 0)
    if len(below):
        raise InputError(p, f"row {below[0] + 1}: direction {D[below[0]].tolist()} is below the horizon "
                            "(z <= 0; camera frame: z toward the camera)")
    D = D / norms[:, None]
    q = Path(intensities) if intensities else p.with_name("light_intensities.txt")
    if intensities or q.exists():
        E = _read_rows(q, "light intensities")
        if len(E) != len(D):
            raise InputError(q, f"{len(E)} intensity rows for {len(D)} light directions in {p.name}")
        if (E <= 0).any():
            i = int(np.argwhere(E <= 0)[0, 0])
            raise InputError(q, f"row {i + 1}: intensities must be > 0, got {E[i].tolist()}")
    else:
        E = np.ones_like(D)
    return D, E


def _read_rows(p: Path, what: str) -> np.ndarray:
    try:
        lines = [ln.split() for ln in p.read_text().splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    except FileNotFoundError:
        raise InputError(p, f"{what} file not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(p, f"cannot read {what} ({getattr(e, 'strerror', None) or e})") from None
    if not lines:
        raise InputError(p, f"no {what} in the file")
    for i, row in enumerate(lines):
        if len(row) != 3:
            raise InputError(p, f"row {i + 1} has {len(row)} columns, expected 3 ({what}: x y z / r g b)")
    try:
        a = np.array(lines, dtype=np.float64)
    except ValueError:
        raise InputError(p, f"{what} must be numbers") from None
    if not np.isfinite(a).all():
        raise InputError(p, f"{what} has NaN/inf entries")
    return a


def write_light_files(out_dir: str | Path, directions: np.ndarray, intensities: np.ndarray) -> list[Path]:
    """DiLiGenT's light_directions.txt and light_intensities.txt (one row per light)."""
    out = Path(out_dir)
    a = out / "light_directions.txt"
    b = out / "light_intensities.txt"
    a.write_text("".join(f"{x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in np.asarray(directions, np.float64)))
    b.write_text("".join(f"{x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in np.asarray(intensities, np.float64)))
    return [a, b]


def rig_sensitivities(rig: RigSpec) -> np.ndarray:
    """(len(GRID), M) channel sensitivities of a spectral rig (what the renderer's film integrates)."""
    from msps_render.spectral.spectra import filter_sensitivities, sensitivity_table

    if not rig.is_spectral:
        raise ValueError("an RGB rig has no sensitivities (its channels are weights on R, G, B)")
    return filter_sensitivities(rig.filters) if rig.filters else sensitivity_table(rig.camera)
