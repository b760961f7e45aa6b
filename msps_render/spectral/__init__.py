"""Spectral model: light spectra, camera sensitivities, effective crosstalk, spectral
rendering (Mitsuba `specfilm`) and an optional sensor model.

Importing this package does not import Mitsuba; `render.py` imports it lazily.
"""
from msps_render.spectral.config import SensorConfig, SpectralConfig
from msps_render.spectral.crosstalk import effective_crosstalk, response_matrix
from msps_render.spectral.spectra import (WL_MAX, WL_MIN, camera_sensitivities, known_cameras,
                                          light_spectrum)

__all__ = ["SpectralConfig", "SensorConfig", "effective_crosstalk", "response_matrix", "light_spectrum",
           "camera_sensitivities", "known_cameras", "WL_MIN", "WL_MAX"]
