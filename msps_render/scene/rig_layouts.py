"""`[scene.rig]`: the rig as a preset describes it, and the per-frame draw of its lights (scene stage).

`RigConfig` is what a user writes (a light layout generator -- three, ring, hemisphere, grid, file --,
light kind and colour, camera channels or narrow-band filters, capture, calibration errors);
`sample_rig(cfg, rng)` turns it into one frame's true `LightSpec`s and its `RigSpec` (the nominal
lights beside them).  The rig's values and maths live in `msps_render.rig` (no scene imports), so
every stage can read a rig without the sampler.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, field_validator, model_serializer, model_validator

from msps_render.config_io import StrictModel, omit_defaults
from msps_render.errors import InputError
from msps_render.rig import (CAPTURES, COLOURS, DEFAULT_SPECTRAL_CAMERA, LAYOUTS, MAX_SLANT_DEG, MIN_LIGHT_DISTANCE,
                             SPECTRAL_CONFIG_FIELDS,
                             RigSpec, channel_matrix, channel_names, read_light_file)
from msps_render.scene.envmap import expand_path, missing_asset
from msps_render.scene.lights import jitter_direction
from msps_render.scene.spec import LightSpec


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
        return omit_defaults(self, handler(self), SPECTRAL_CONFIG_FIELDS)

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
        """Checks of the table itself; those that need the number of lights wait for the file of a 'file'
        layout until a frame is drawn (a preset naming $MSPS_TEST_DATA validates without the data)."""
        if self.layout == "file" and not self.file:
            raise ValueError("layout 'file' needs file = 'light_directions.txt'")
        if self.filters is not None and self.camera is not None:
            raise ValueError("give the camera's channels as filters or as camera, not both")
        if self.led_peaks_nm is not None and self.spectra is not None:
            raise ValueError("give the lights' spectra as led_peaks_nm or as spectra, not both")
        if self.layout != "file":
            self.check_count(self.count())
        return self

    def check_count(self, n: int) -> None:
        """What must agree with the number of lights `n` (ValueError otherwise)."""
        if isinstance(self.colours, list) and len(self.colours) != n:
            raise ValueError(f"colours has {len(self.colours)} entries for {n} lights")
        if isinstance(self.colours, list) and any(min(c) < 0 or not math.isfinite(sum(c)) for c in self.colours):
            raise ValueError("colours must be finite and >= 0")
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

        if not self.file:
            raise InputError("scene.rig.file", "layout 'file' needs file = 'light_directions.txt'")
        path = expand_path(self.file)
        if not Path(path).is_file():
            raise missing_asset(self.file, path, "light directions file not found")
        return Path(path)



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


def _layout(cfg: RigConfig, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
        D, E = read_light_file(cfg._file_path(), Path(expand_path(cfg.intensities_file)) if cfg.intensities_file
                               else None)
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

    D, P, E = _layout(cfg, rng)
    n = len(D)
    if cfg.layout == "file":
        try:
            cfg.check_count(n)
        except ValueError as e:
            raise InputError(source, f"{e} (light file {cfg.file})") from None
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


