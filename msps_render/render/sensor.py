"""Optional sensor model: exposure, Poisson-Gaussian noise, saturation, quantisation.

Configured here (`SensorConfig`, the top-level `[sensor]` table of a preset) and
applied here: the pipeline runs it after rendering, on each frame's own noise
stream (`pipeline.plan.sensor_rng`).  It is not part of the scene: the same
scene recorded by another camera is the same scene.

`apply_sensor(frame, cfg, rng)` returns a new Frame whose `image` is what a
camera would record (in radiance units, see `SensorConfig`), with the noiseless
radiance kept in `clean_image`.  Per-light and environment images stay clean
(they are components of the radiance, not separate exposures).  Deterministic
for a given `rng` state; the paper presets leave it off.
"""
from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from msps_render.config_io import StrictModel
from msps_render.frame import Frame


class SensorConfig(StrictModel):
    """Camera sensor: exposure, Poisson-Gaussian noise, saturation, quantisation.

    Model (per pixel and channel, x = radiance): s = clip(exposure*x, 0, 1) is the
    fraction of full well; electrons ~ Poisson(s*full_well_e) + Normal(0, read_noise_e);
    clipped to [0, full_well_e]; digitised to `bits` (DN = round(e/full_well_e*(2^bits-1)));
    the stored image is DN converted back to radiance units (DN/(2^bits-1)/exposure),
    so it saturates at 1/exposure.  `exposure = "auto"` picks exposure so the
    `auto_percentile` of object pixels lands at `auto_level` of full well.
    """

    enabled: bool = True
    exposure: float | Literal["auto"] = "auto"
    auto_percentile: float = Field(99.0, gt=0, le=100)
    auto_level: float = Field(0.8, gt=0, le=1.0)
    full_well_e: float = Field(10000.0, gt=0)
    read_noise_e: float = Field(3.0, ge=0)
    poisson: bool = True
    bits: Literal[8, 10, 12, 16] = 12
    bits_choices: list[Literal[8, 10, 12, 16]] | None = Field(
        None, description="draw the bit depth per frame from these (overrides bits)")
    response: Literal["linear", "gamma", "srgb"] = Field(
        "linear", description="camera response applied before digitising: linear (raw), a power law "
                              "x^(1/gamma), or the sRGB curve; the stored image is NOT linearised")
    gamma: float = Field(2.2, gt=0.0, description="response = 'gamma': the exponent's denominator")

    @field_validator("exposure")
    @classmethod
    def _exp(cls, v):
        if v != "auto" and not (v > 0):
            raise ValueError("exposure must be > 0 or 'auto'")
        return v


def auto_exposure(image: np.ndarray, mask: np.ndarray | None, cfg: SensorConfig) -> float:
    px = image[mask] if mask is not None and mask.any() else image.reshape(-1, image.shape[-1])
    ref = float(np.percentile(px, cfg.auto_percentile)) if px.size else 0.0
    return cfg.auto_level / ref if ref > 0 else 1.0


def sensor_response(image: np.ndarray, cfg: SensorConfig, exposure: float,
                    rng: np.random.Generator, bits: int | None = None) -> np.ndarray:
    """Radiance -> recorded radiance (float32), the model of `SensorConfig`."""
    s = np.clip(np.asarray(image, dtype=np.float64) * exposure, 0.0, 1.0)
    e = s * cfg.full_well_e
    if cfg.poisson:
        e = rng.poisson(e).astype(np.float64)
    if cfg.read_noise_e > 0:
        e = e + rng.normal(0.0, cfg.read_noise_e, size=e.shape)
    e = np.clip(e, 0.0, cfg.full_well_e)
    levels = float(2 ** (bits or cfg.bits) - 1)
    dn = np.round(camera_response(e / cfg.full_well_e, cfg) * levels)
    return (dn / levels / exposure).astype(np.float32)


def camera_response(s: np.ndarray, cfg: SensorConfig) -> np.ndarray:
    """Fraction of full well (linear, [0, 1]) -> the camera's encoded value in [0, 1]."""
    if cfg.response == "gamma":
        return np.power(s, 1.0 / cfg.gamma)
    if cfg.response == "srgb":
        return np.where(s <= 0.0031308, 12.92 * s, 1.055 * np.power(s, 1 / 2.4) - 0.055)
    return s


def apply_sensor(frame: Frame, cfg: SensorConfig | None, rng: np.random.Generator) -> Frame:
    """The frame as recorded by the sensor (`cfg None` or disabled: the frame unchanged)."""
    if cfg is None or not cfg.enabled:
        return frame
    clean = frame.clean_image if frame.clean_image is not None else frame.image
    exposure = auto_exposure(clean, frame.mask, cfg) if cfg.exposure == "auto" else float(cfg.exposure)
    # drawn only when asked, so configs without bits_choices keep their noise stream
    bits = int(rng.choice(cfg.bits_choices)) if cfg.bits_choices else cfg.bits
    image = sensor_response(clean, cfg, exposure, rng, bits)
    meta = dict(frame.meta)
    meta["sensor"] = {**cfg.model_dump(), "bits_used": bits, "exposure_used": exposure,
                      "saturation_radiance": 1.0 / exposure,
                      "saturated_fraction": float((clean * exposure >= 1.0).mean())}
    shots = frame.shots
    if shots is not None:  # a rig: every shot recorded by the same camera at one exposure (drawn after the image)
        shot_exp = auto_exposure(shots.reshape((-1,) + shots.shape[2:]), np.tile(frame.mask, (len(shots), 1)), cfg) \
            if cfg.exposure == "auto" else float(cfg.exposure)
        shots = sensor_response(shots, cfg, shot_exp, rng, bits)
        meta["sensor"]["shots_exposure_used"] = shot_exp
    return dataclasses.replace(frame, image=image, clean_image=np.asarray(clean, dtype=np.float32), meta=meta,
                               shots=shots)
