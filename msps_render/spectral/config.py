"""Pydantic configs for the spectral mode and the optional sensor model.

They live inside `SceneConfig` (`scene.spectral`, `scene.sensor` in TOML).
"""
from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator

from msps_render.config_io import StrictModel
from msps_render.spectral.spectra import validate_camera_id, validate_light_id


class SpectralConfig(StrictModel):
    """Light spectra (one id per light, in tilt order) and the camera.

    Ids: see `msps_render.spectral.spectra` (``led:PEAK:FWHM``, ``flat``, ``d65``,
    a CSV path; camera: a colour-science dataset name or a CSV path).
    """

    lights: list[str] = Field(default_factory=lambda: ["led:630:20", "led:530:30", "led:465:20"])
    camera: str = "Nikon 5100 (NPL)"

    @field_validator("lights")
    @classmethod
    def _lights(cls, v):
        if not v:
            raise ValueError("need at least one light spectrum")
        for s in v:
            validate_light_id(s)  # raises InputError (a ValueError) with a clear message
        return v

    @field_validator("camera")
    @classmethod
    def _camera(cls, v):
        return validate_camera_id(v)


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
    bits: Literal[8, 12, 16] = 12

    @field_validator("exposure")
    @classmethod
    def _exp(cls, v):
        if v != "auto" and not (v > 0):
            raise ValueError("exposure must be > 0 or 'auto'")
        return v
