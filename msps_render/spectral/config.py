"""Pydantic config for the spectral mode; it lives inside `SceneConfig` (`scene.spectral` in TOML).

The sensor model's config is `render.sensor.SensorConfig`, next to the code that applies it.
"""
from __future__ import annotations

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
