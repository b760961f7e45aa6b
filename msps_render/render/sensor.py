"""Optional sensor model: exposure, Poisson-Gaussian noise, saturation, quantisation.

`apply_sensor(frame, cfg, rng)` returns a new Frame whose `image` is what a
camera would record (in radiance units, see `SensorConfig`), with the noiseless
radiance kept in `clean_image`.  Per-light and environment images stay clean
(they are components of the radiance, not separate exposures).  Deterministic
for a given `rng` state; the paper presets leave it off.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from msps_render.frame import Frame
from msps_render.spectral.config import SensorConfig


def auto_exposure(image: np.ndarray, mask: np.ndarray | None, cfg: SensorConfig) -> float:
    px = image[mask] if mask is not None and mask.any() else image.reshape(-1, image.shape[-1])
    ref = float(np.percentile(px, cfg.auto_percentile)) if px.size else 0.0
    return cfg.auto_level / ref if ref > 0 else 1.0


def sensor_response(image: np.ndarray, cfg: SensorConfig, exposure: float,
                    rng: np.random.Generator) -> np.ndarray:
    """Radiance -> recorded radiance (float32), the model of `SensorConfig`."""
    s = np.clip(np.asarray(image, dtype=np.float64) * exposure, 0.0, 1.0)
    e = s * cfg.full_well_e
    if cfg.poisson:
        e = rng.poisson(e).astype(np.float64)
    if cfg.read_noise_e > 0:
        e = e + rng.normal(0.0, cfg.read_noise_e, size=e.shape)
    e = np.clip(e, 0.0, cfg.full_well_e)
    levels = float(2 ** cfg.bits - 1)
    dn = np.round(e / cfg.full_well_e * levels)
    return (dn / levels / exposure).astype(np.float32)


def apply_sensor(frame: Frame, cfg: SensorConfig | None, rng: np.random.Generator) -> Frame:
    """The frame as recorded by the sensor (`cfg None` or disabled: the frame unchanged)."""
    if cfg is None or not cfg.enabled:
        return frame
    clean = frame.clean_image if frame.clean_image is not None else frame.image
    exposure = auto_exposure(clean, frame.mask, cfg) if cfg.exposure == "auto" else float(cfg.exposure)
    image = sensor_response(clean, cfg, exposure, rng)
    meta = dict(frame.meta)
    meta["sensor"] = {**cfg.model_dump(), "exposure_used": exposure,
                      "saturation_radiance": 1.0 / exposure,
                      "saturated_fraction": float((clean * exposure >= 1.0).mean())}
    return dataclasses.replace(frame, image=image, clean_image=np.asarray(clean, dtype=np.float32), meta=meta)
