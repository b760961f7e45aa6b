"""Pydantic config for the spectral mode; it lives inside `SceneConfig` (`scene.spectral` in TOML).

The sensor model's config is `render.sensor.SensorConfig`, next to the code that applies it.
"""
from __future__ import annotations

from pydantic import Field, field_validator

from msps_render.config_io import StrictModel
from msps_render.spectral.spectra import validate_camera_id, validate_light_id


class RandomRig(StrictModel):
    """`[scene.spectral.random_rig]`: a random LED x camera pair per frame (rig variation).

    LED k gets a Gaussian spectrum whose peak is drawn in `peaks_nm[k]` and FWHM in `fwhm_nm`;
    the camera is drawn from `cameras`.  The effective crosstalk of each frame follows from the pair
    (stored per frame, as in fixed spectral mode)."""

    peaks_nm: list[tuple[float, float]] = Field(
        default_factory=lambda: [(615.0, 645.0), (515.0, 545.0), (455.0, 475.0)],
        description="per light: [lo, hi] of its LED peak wavelength (nm)")
    fwhm_nm: tuple[float, float] = Field((15.0, 35.0), description="[lo, hi] of each LED's FWHM (nm)")
    cameras: list[str] = Field(default_factory=lambda: ["Nikon 5100 (NPL)", "Sigma SDMerill (NPL)"],
                               description="camera sensitivities to draw from (ids as `camera`)")

    @field_validator("cameras")
    @classmethod
    def _cams(cls, v):
        if not v:
            raise ValueError("random_rig.cameras must name at least one camera")
        return [validate_camera_id(c) for c in v]

    @field_validator("peaks_nm")
    @classmethod
    def _peaks(cls, v):
        for lo, hi in v:
            if not 360.0 <= lo <= hi <= 830.0:
                raise ValueError(f"random_rig.peaks_nm: need 360 <= lo <= hi <= 830, got {[lo, hi]}")
        return v

    def draw(self, rng) -> tuple[list[str], str]:
        """(light spectrum ids, camera id) of one frame's rig."""
        lights = [f"led:{rng.uniform(lo, hi):.1f}:{rng.uniform(*self.fwhm_nm):.1f}" for lo, hi in self.peaks_nm]
        return lights, self.cameras[int(rng.integers(len(self.cameras)))]


class SpectralConfig(StrictModel):
    """Light spectra (one id per light, in tilt order) and the camera.

    Ids: see `msps_render.spectral.spectra` (``led:PEAK:FWHM``, ``flat``, ``d65``,
    a CSV path; camera: a colour-science dataset name or a CSV path).
    """

    lights: list[str] = Field(default_factory=lambda: ["led:630:20", "led:530:30", "led:465:20"])
    camera: str = "Nikon 5100 (NPL)"
    random_rig: RandomRig | None = Field(None, description="draw an LED x camera pair per frame instead of "
                                                           "`lights` and `camera`")

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
