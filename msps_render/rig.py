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

from msps_render.config_io import FrozenModel, StrictModel
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
        d = handler(self)
        if isinstance(d, dict):
            for k in SPECTRAL_SPEC_FIELDS:
                if d.get(k) in ((), [], None):
                    d.pop(k, None)
        return d

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
        from msps_render.calibration import parse_calibration

        L, M = parse_calibration({}, "the paper's rig")
        return cls(L, M, assumed=True)


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


# ================================================================ config: `[scene.rig]`
class GridLayout(StrictModel):
    rows: int = Field(7, ge=1, le=64, description="LED rows")
    cols: int = Field(7, ge=1, le=64, description="LED columns")
    pitch: float = Field(0.5, gt=0, description="LED spacing on the plane (scene units; the object fits in radius 1)")
    plane_distance: float = Field(4.0, gt=MIN_LIGHT_DISTANCE, description="distance of the LED plane from the "
                                                                          "object centre, toward the camera")


class CalibrationErrors(StrictModel):
    """Deliberate differences between the rendered lights (truth) and the nominal rig (the calibration)."""

    jitter_deg: float = Field(0.0, ge=0.0, le=20.0, description="each light's direction turned by up to this "
                                                                "angle (uniform in the cone)")
    intensity_error: float = Field(0.0, ge=0.0, lt=1.0, description="each light's intensity x U(1-e, 1+e)")
    colour_error: float = Field(0.0, ge=0.0, lt=1.0, description="each light's R, G, B x U(1-e, 1+e) apiece")


class RigConfig(StrictModel):
    """`[scene.rig]`: any photometric-stereo rig (docs/rigs.md).  Absent: the three-light
    `[scene.lights]` rig of the seed paper, unchanged."""

    layout: Literal[LAYOUTS] = Field("hemisphere", description="where the lights are: three (the paper's "
                                     "tilted lights), ring (n_lights at one slant), hemisphere (n_lights over "
                                     "the upper hemisphere within slant_range_deg), grid (LEDs on a plane), "
                                     "file (DiLiGenT's light_directions.txt)")
    n_lights: int = Field(32, ge=1, le=1024, description="ring/hemisphere: number of lights")
    slant_deg: float = Field(30.0, gt=0.0, lt=90.0, description="three/ring: slant of every light (deg)")
    tilts_deg: list[float] = Field(default_factory=lambda: [0.0, 120.0, 240.0],
                                   description="three: tilt of each light (deg)")
    slant_range_deg: tuple[float, float] = Field((0.0, 70.0), description="hemisphere: [lo, hi] slant (deg)")
    sampling: Literal["uniform", "random"] = Field(
        "uniform", description="hemisphere: a fixed even spread (Fibonacci spiral, same every frame) or "
                               "new directions drawn uniformly in solid angle every frame")
    file: str | None = Field(None, description="file: light_directions.txt (one 'x y z' row per light, "
                                               "camera frame; $VARS and ~ expanded)")
    intensities_file: str | None = Field(None, description="file: light_intensities.txt (one 'r g b' row per "
                                                            "light; default: the one beside `file` if present)")
    kind: Literal["directional", "point"] = Field("directional", description="far (directional) or near "
                                                                            "(point) lights; grid: always point")
    distance: float = Field(3.0, gt=MIN_LIGHT_DISTANCE, description="point lights (not grid): distance from "
                                                                     "the object centre")
    anisotropy_mu: float = Field(0.0, ge=0.0, le=100.0, description="point lights: LED radiant intensity "
                                                                    "cos^mu of the angle off its axis (axis "
                                                                    "toward the object centre; 0 = isotropic)")
    grid: GridLayout = Field(default_factory=GridLayout)
    colours: Literal["white", "rgb-cycle"] | list[tuple[float, float, float]] = Field(
        "white", description="light colours: white, rgb-cycle (red, green, blue, red, ...) or one [r, g, b] per light")
    irradiance: float = Field(3.0, gt=0.0, description="each light's irradiance on a surface facing it at "
                                                       "the object centre (linear units; x file intensities)")
    channels: Literal["rgb", "mono"] | list[tuple[float, float, float]] = Field(
        "rgb", description="camera channels: rgb, mono (the mean of R, G, B) or rows [wR, wG, wB], one per channel")
    capture: Literal[CAPTURES] | list[list[int]] = Field(
        "sequential", description="multiplexed (all lights in one image), sequential (one image per light) "
                                  "or a list of shots, each a list of light indices")
    allow_unseparable: bool = Field(False, description="allow a shot with more lights than camera channels "
                                                       "(universal methods; it cannot be demultiplexed)")
    errors: CalibrationErrors = Field(default_factory=CalibrationErrors)
    # ---- spectral mode (scene.mode = "spectral"): narrow-band rigs, N LED spectra x an M-channel camera
    filters: list[tuple[float, float]] | None = Field(
        None, description="spectral mode: the camera's channels as narrow-band filters, one [centre_nm, "
                          "fwhm_nm] per channel (Gaussian, unit peak; centre +- 2 FWHM inside 360-830 nm); "
                          "replaces channels")
    camera: str | None = Field(None, description="spectral mode, instead of filters: measured sensitivities, a "
                                                 "colour-science camera (3 channels) or a CSV 'wavelength, "
                                                 "s1..sM' (default without filters: Nikon 5100 (NPL))")
    led_peaks_nm: list[float] | None = Field(None, description="spectral mode: one Gaussian LED per light, its "
                                                               "peak wavelength (nm); replaces colours")
    led_fwhm_nm: float = Field(20.0, ge=1.0, le=400.0, description="spectral mode: FWHM of every led_peaks_nm "
                                                                   "LED (nm)")
    spectra: list[str] | None = Field(None, description="spectral mode, instead of led_peaks_nm: one emission "
                                                        "spectrum per light ('led:PEAK:FWHM', 'flat', 'd65' "
                                                        "or a CSV path); default: 'flat' (white)")

    @model_serializer(mode="wrap")
    def _without_absent_spectral(self, handler):
        """RGB rigs serialise (and hash) as before spectral rigs existed: same configs, same shards."""
        d = handler(self)
        if isinstance(d, dict):
            for k in SPECTRAL_CONFIG_FIELDS:
                if k in d and getattr(self, k) == type(self).model_fields[k].default:
                    d.pop(k)
        return d

    @field_validator("slant_range_deg")
    @classmethod
    def _range(cls, v):
        if not 0.0 <= v[0] <= v[1] <= MAX_SLANT_DEG:
            raise ValueError(f"slant_range_deg must satisfy 0 <= lo <= hi <= {MAX_SLANT_DEG:g}, got {list(v)}")
        return v

    @field_validator("filters")
    @classmethod
    def _filters(cls, v):
        from msps_render.spectral.spectra import band_problem

        if v is None:
            return v
        if not 1 <= len(v) <= 64:
            raise ValueError(f"filters must list 1 to 64 channels, got {len(v)}")
        for m, (c, w) in enumerate(v):
            problem = band_problem(c, w)
            if problem:
                raise ValueError(f"filters[{m}] = [{c:g}, {w:g}]: {problem}")
        return v

    @field_validator("camera")
    @classmethod
    def _camera(cls, v):
        from msps_render.spectral.spectra import sensitivity_table

        if v is not None:
            sensitivity_table(v)  # InputError (a ValueError) naming the camera or file
        return v

    @field_validator("spectra")
    @classmethod
    def _spectra(cls, v):
        from msps_render.spectral.spectra import validate_light_id

        for sid in v or ():
            validate_light_id(sid)
        return v

    @model_validator(mode="after")
    def _check(self) -> "RigConfig":
        n = self.count()
        if isinstance(self.colours, list) and len(self.colours) != n:
            raise ValueError(f"colours has {len(self.colours)} entries for {n} lights")
        if isinstance(self.colours, list) and any(min(c) < 0 or not math.isfinite(sum(c)) for c in self.colours):
            raise ValueError("colours must be finite and >= 0")
        if self.filters is not None and self.camera is not None:
            raise ValueError("give the camera's channels as filters or as camera, not both")
        if self.led_peaks_nm is not None and self.spectra is not None:
            raise ValueError("give the lights' spectra as led_peaks_nm or as spectra, not both")
        for key in ("led_peaks_nm", "spectra"):
            v = getattr(self, key)
            if v is not None and len(v) != n:
                raise ValueError(f"{key} has {len(v)} entries for {n} lights")
        if self.led_peaks_nm is not None:
            from msps_render.spectral.spectra import band_problem

            for k, peak in enumerate(self.led_peaks_nm):
                problem = band_problem(peak, self.led_fwhm_nm)
                if problem:
                    raise ValueError(f"led_peaks_nm[{k}] = {peak:g} with led_fwhm_nm {self.led_fwhm_nm:g}: {problem}")
        m = self.n_channels()
        for s, shot in enumerate(self.shot_list(n)):
            bad = [k for k in shot if not 0 <= k < n]
            if bad or not shot:
                raise ValueError(f"capture shot {s} names light {bad[0] if bad else '(none)'}; lights are 0..{n - 1}")
            if len(shot) > m and not self.allow_unseparable:
                raise ValueError(f"capture shot {s} has {len(shot)} lights but the camera has {m} channel(s): the "
                                 f"lights cannot be separated (set allow_unseparable = true for universal methods)")
        return self

    def count(self) -> int:
        """Number of lights (the file layout reads its file)."""
        if self.layout == "three":
            return len(self.tilts_deg)
        if self.layout == "grid":
            return self.grid.rows * self.grid.cols
        if self.layout == "file":
            return len(read_light_file(self._file_path())[0]) if self.file else 0
        return self.n_lights

    def image_shape(self) -> tuple[int, int, int, bool]:
        """(lights, images per patch, channels, near lights?) of this rig: what storage depends on."""
        n = self.count()
        return n, len(self.shot_list(n)), self.n_channels(), (
            self.layout == "grid" or self.kind == "point")

    def describe(self) -> str:
        n, s, m, near = self.image_shape()
        cap = "multiplexed (one image)" if self.capture == "multiplexed" else (
            "sequential (one image per light)" if self.capture == "sequential" else f"{s} shots")
        return f"{self.layout}: {n} {'near point' if near else 'directional'} lights x {m} channel(s), {cap}"

    def n_channels(self) -> int:
        """Camera channels: the filters or the camera's in a spectral rig, else the rows of `channels`."""
        if self.filters is not None:
            return len(self.filters)
        if self.camera is not None:
            from msps_render.spectral.spectra import sensitivity_table

            return int(sensitivity_table(self.camera).shape[1])
        return len(channel_matrix(self.channels))

    def spectral_keys(self) -> list[str]:
        """The spectral-mode keys this table sets (empty: an RGB rig's table)."""
        return [k for k in SPECTRAL_CONFIG_FIELDS
                if getattr(self, k) != type(self).model_fields[k].default]

    def check_mode(self, mode: str, source: str = "scene.rig") -> None:
        """One InputError line naming the key when this table does not fit the scene's `mode`."""
        if mode != "spectral":
            keys = self.spectral_keys()
            if keys:
                raise InputError(f"{source}.{keys[0]}", f"{keys[0]} is for scene mode 'spectral' (camera filters "
                                                         f"and light spectra); this scene renders in mode '{mode}' "
                                                         f"(set scene.mode = \"spectral\", or use channels/colours)")
            return
        if self.channels != "rgb":
            raise InputError(f"{source}.channels", "channels (weights on R, G, B) is for mode 'rgb'; a spectral "
                                                   "rig's camera channels are its filters or camera")
        if self.colours != "white":
            raise InputError(f"{source}.colours", "colours (R, G, B) is for mode 'rgb'; a spectral rig's lights "
                                                  "take led_peaks_nm or spectra")
        if self.errors.colour_error > 0:
            raise InputError(f"{source}.errors.colour_error", "colour_error (R, G, B gains) is for mode 'rgb'; a "
                                                              "spectral rig's lights have spectra (use "
                                                              "intensity_error)")

    def light_spectra(self, n: int) -> list[str]:
        """Spectral mode: one spectrum id per light (led_peaks_nm, spectra, else flat white)."""
        if self.led_peaks_nm is not None:
            return [f"led:{p:g}:{self.led_fwhm_nm:g}" for p in self.led_peaks_nm]
        return list(self.spectra) if self.spectra is not None else ["flat"] * n

    def shot_list(self, n: int) -> tuple[tuple[int, ...], ...]:
        if self.capture == "multiplexed":
            return (tuple(range(n)),)
        if self.capture == "sequential":
            return tuple((k,) for k in range(n))
        return tuple(tuple(int(k) for k in s) for s in self.capture)

    def _file_path(self) -> Path:
        from msps_render.scene.envmap import expand_path, missing_asset

        if not self.file:
            raise InputError("scene.rig.file", "layout 'file' needs file = 'light_directions.txt'")
        path = expand_path(self.file)
        if not Path(path).is_file():
            raise missing_asset(self.file, path, "light directions file not found")
        return Path(path)


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


# ================================================================ layouts: the generators
def _slant_tilt_dir(slant_deg: float, tilt_deg: float) -> np.ndarray:
    s, t = math.radians(slant_deg), math.radians(tilt_deg)
    return np.array([math.sin(s) * math.cos(t), math.sin(s) * math.sin(t), math.cos(s)])


def hemisphere_directions(n: int, slant_range_deg=(0.0, 70.0), rng: np.random.Generator | None = None) -> np.ndarray:
    """n unit directions spread over the cap slant in [lo, hi], uniform in solid angle: a Fibonacci
    spiral (fixed, `rng` None) or independent draws (`rng`)."""
    c_hi, c_lo = math.cos(math.radians(slant_range_deg[0])), math.cos(math.radians(slant_range_deg[1]))
    if rng is None:
        i = np.arange(n) + 0.5
        z = c_hi - (c_hi - c_lo) * i / n
        phi = np.pi * (3.0 - math.sqrt(5.0)) * np.arange(n)
    else:
        z = rng.uniform(c_lo, c_hi, n)
        phi = rng.uniform(0.0, 2 * np.pi, n)
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _layout(cfg: RigConfig, rng: np.random.Generator, source: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(directions (N, 3), positions (N, 3) or NaN rows, relative intensities (N, 3)) of the nominal layout."""
    if cfg.layout == "three":
        D = np.stack([_slant_tilt_dir(cfg.slant_deg, t) for t in cfg.tilts_deg])
        E = np.ones_like(D)
    elif cfg.layout == "ring":
        D = np.stack([_slant_tilt_dir(cfg.slant_deg, 360.0 * k / cfg.n_lights) for k in range(cfg.n_lights)])
        E = np.ones_like(D)
    elif cfg.layout == "hemisphere":
        D = hemisphere_directions(cfg.n_lights, cfg.slant_range_deg, rng if cfg.sampling == "random" else None)
        E = np.ones_like(D)
    elif cfg.layout == "file":
        D, E = read_light_file(cfg._file_path(), Path(cfg.intensities_file) if cfg.intensities_file else None)
    else:  # grid: LEDs on the plane z = plane_distance, centred on the view axis
        g = cfg.grid
        xs = (np.arange(g.cols) - (g.cols - 1) / 2) * g.pitch
        ys = ((g.rows - 1) / 2 - np.arange(g.rows)) * g.pitch
        P = np.array([[x, y, g.plane_distance] for y in ys for x in xs], np.float64)
        D = P / np.linalg.norm(P, axis=1, keepdims=True)
        return D, P, np.ones_like(D)
    if cfg.kind == "point":
        return D, D * cfg.distance, E
    return D, np.full_like(D, np.nan), E


def _colours(cfg: RigConfig, n: int) -> np.ndarray:
    if isinstance(cfg.colours, list):
        return np.asarray(cfg.colours, np.float64)
    if cfg.colours == "white":
        return np.ones((n, 3))
    cyc = [COLOURS["red"], COLOURS["green"], COLOURS["blue"]]
    return np.array([cyc[k % 3] for k in range(n)], np.float64)


def sample_rig(cfg: RigConfig, rng: np.random.Generator, source: str = "scene.rig"):
    """(true LightSpecs, RigSpec) of one frame.  Draws from `rng` only what the config asks for, in a
    fixed order: random hemisphere directions, then per light direction jitter, intensity, colour."""
    from msps_render.scene.lights import jitter_direction
    from msps_render.scene.spec import LightSpec

    D, P, E = _layout(cfg, rng, source)
    n = len(D)
    point = np.isfinite(P).all(axis=1)
    if point.any():
        r = np.linalg.norm(P[point], axis=1)
        if (r <= MIN_LIGHT_DISTANCE).any():
            k = int(np.flatnonzero(point)[np.argmin(r)])
            raise InputError(source, f"point light {k} at distance {np.linalg.norm(P[k]):.3g} is inside the "
                                     f"object's bounding sphere (radius {MIN_LIGHT_DISTANCE:g})")
    # point lights: `rgb` is the intensity whose irradiance at the object centre is `irradiance` (x d^2)
    d2 = np.where(point, (np.nan_to_num(P) ** 2).sum(axis=1), 1.0)
    rgb_nominal = cfg.irradiance * E * _colours(cfg, n) * d2[:, None]
    e = cfg.errors
    lights = []
    for k in range(n):
        d = D[k]
        dist = float(np.linalg.norm(P[k])) if point[k] else None
        if e.jitter_deg > 0:
            d, _, _ = jitter_direction(d, e.jitter_deg, rng)
        gain = float(rng.uniform(1 - e.intensity_error, 1 + e.intensity_error)) if e.intensity_error > 0 else 1.0
        tint = rng.uniform(1 - e.colour_error, 1 + e.colour_error, 3) if e.colour_error > 0 else np.ones(3)
        rgb = rgb_nominal[k] * gain * tint
        slant = math.degrees(math.acos(max(-1.0, min(1.0, float(d[2])))))
        tilt = math.degrees(math.atan2(float(d[1]), float(d[0]))) % 360.0
        lights.append(LightSpec(kind="point" if point[k] else "directional", direction=tuple(float(x) for x in d),
                                rgb=tuple(float(x) for x in rgb), distance=dist, slant_deg=slant, tilt_deg=tilt))
    spec = RigSpec(name=cfg.layout, channels=channel_matrix(cfg.channels), channel_names=channel_names(cfg.channels),
                   shots=cfg.shot_list(n),
                   anisotropy=tuple([float(cfg.anisotropy_mu)] * n) if cfg.anisotropy_mu and point.any() else (),
                   nominal_dirs=tuple(tuple(float(x) for x in d) for d in D),
                   nominal_rgb=tuple(tuple(float(x) for x in c) for c in rgb_nominal),
                   allow_unseparable=cfg.allow_unseparable)
    return tuple(lights), spec


# ================================================================ spectral rigs
def spectral_rig(cfg: RigConfig, lights, spec: RigSpec, source: str = "scene.rig"):
    """(lights, RigSpec) of `sample_rig` made spectral (scene mode "spectral"; draws nothing more).

    Light n gets its spectrum (`RigConfig.light_spectra`); the camera its M channels (filters, or a
    measured camera); C[m, n] = E_n * Σ_λ e_n(λ) S_m(λ) / Σ_m' Σ_λ e_n(λ) S_m'(λ) with E_n the light's
    irradiance (x its calibration gain): the closed-form spectral integral, columns normalised as
    `spectral.effective_crosstalk`, stored as the shares `RigSpec.crosstalk` and the sums
    `LightSpec.rgb` (three equal thirds; the renderer scales light n's spectrum so that its reading,
    summed over the channels, on a white surface facing it is sum(rgb), as spectral mode does)."""
    from msps_render.spectral.crosstalk import rig_crosstalk

    cfg.check_mode("spectral", source)
    ids = cfg.light_spectra(len(lights))
    S = config_sensitivities(cfg)
    key = "led_peaks_nm" if cfg.led_peaks_nm is not None else "spectra"
    shares = rig_crosstalk(ids, S, f"{source}.{key}")
    camera = None if cfg.filters is not None else (cfg.camera or DEFAULT_SPECTRAL_CAMERA)
    if cfg.filters is not None:
        names = tuple(f"{c:g}nm" for c, _ in cfg.filters)
    else:
        names = ("R", "G", "B") if S.shape[1] == 3 else tuple(f"C{m}" for m in range(S.shape[1]))

    def grey(rgb):  # white light of `irradiance`: R, G, B each irradiance in RGB mode, sum irradiance here
        t = float(sum(rgb)) / 9.0
        return (t, t, t)

    lights = tuple(l.model_copy(update={"rgb": grey(l.rgb), "spectrum": sid}) for l, sid in zip(lights, ids))
    spec = spec.model_copy(update={
        "channels": (), "channel_names": names, "filters": tuple(tuple(float(x) for x in f) for f in cfg.filters or ()),
        "camera": camera, "crosstalk": tuple(tuple(float(x) for x in row) for row in shares),
        "nominal_rgb": tuple(grey(c) for c in spec.nominal_rgb)})
    return lights, RigSpec.model_validate(spec.model_dump())


def config_sensitivities(cfg: RigConfig) -> np.ndarray:
    """(len(GRID), M) channel sensitivities of a spectral `[scene.rig]` table."""
    from msps_render.spectral.spectra import filter_sensitivities, sensitivity_table

    if cfg.filters is not None:
        return filter_sensitivities(cfg.filters)
    return sensitivity_table(cfg.camera or DEFAULT_SPECTRAL_CAMERA)


def rig_sensitivities(rig: RigSpec) -> np.ndarray:
    """(len(GRID), M) channel sensitivities of a spectral rig (what the renderer's film integrates)."""
    from msps_render.spectral.spectra import filter_sensitivities, sensitivity_table

    if not rig.is_spectral:
        raise ValueError("an RGB rig has no sensitivities (its channels are weights on R, G, B)")
    return filter_sensitivities(rig.filters) if rig.filters else sensitivity_table(rig.camera)
