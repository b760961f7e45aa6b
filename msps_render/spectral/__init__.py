"""Spectral model (numpy): light spectra, camera sensitivities, effective crosstalk, and the
spectral config.  Rendering with them is `msps_render.render.spectral`."""
from msps_render.spectral.config import SpectralConfig
from msps_render.spectral.crosstalk import effective_crosstalk, response_matrix, rig_crosstalk
from msps_render.spectral.spectra import (WL_MAX, WL_MIN, camera_sensitivities, filter_sensitivities,
                                          known_cameras, light_spectrum, sensitivity_table)

__all__ = ["SpectralConfig", "effective_crosstalk", "response_matrix", "rig_crosstalk", "light_spectrum",
           "camera_sensitivities", "filter_sensitivities", "sensitivity_table", "known_cameras", "WL_MIN",
           "WL_MAX"]
