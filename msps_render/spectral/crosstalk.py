"""Effective 3x3 crosstalk from light spectra x white reflector x camera sensitivities.

R[i, k] = Σ_λ E_k(λ) · ρ_white(λ) · S_i(λ) · Δλ   (paper eq. 5 with ρ = 1, n = l)

with E_k the unit-peak emission of light k and S_i the max-normalised camera
sensitivity, all colour-science distributions on the same 1 nm grid.  The
*effective crosstalk* M is R with each column normalised to sum 1: M[i, k] is
the share of light k's camera signal that lands in channel i, the same meaning
as the paper's (0.92, 0.04, 0.04) columns.  The renderer scales light k's
spectrum by 1 / Σ_i R[i, k] times the light's `sum(rgb)`, so in both modes
`LightSpec.rgb` is the light's camera response on a white reflector at normal
incidence.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from msps_render.errors import InputError
from msps_render.spectral.spectra import GRID, WL_STEP, camera_sensitivities, light_spectrum


def white_reflector():
    import colour

    return colour.SpectralDistribution(np.ones_like(GRID), GRID, name="white")


def response(light_id: str, camera_id: str, reflectance=None) -> np.ndarray:
    """(3,) camera response Σ_λ E(λ) ρ(λ) S_i(λ) Δλ of one unit-peak light on a reflector."""
    E = light_spectrum(light_id)
    S = camera_sensitivities(camera_id)
    rho = reflectance if reflectance is not None else white_reflector()
    if not (np.array_equal(E.wavelengths, S.wavelengths) and np.array_equal(rho.wavelengths, S.wavelengths)):
        raise ValueError("spectra are not on the same grid")
    return (E.values * rho.values) @ S.values * WL_STEP


@lru_cache(maxsize=64)
def _response_matrix(light_ids: tuple[str, ...], camera_id: str) -> np.ndarray:
    R = np.stack([response(l, camera_id) for l in light_ids], axis=1)
    R.setflags(write=False)
    return R


def response_matrix(light_ids, camera_id: str) -> np.ndarray:
    """(3, K) raw responses R[i, k] of the unit-peak light spectra (white reflector)."""
    return _response_matrix(tuple(light_ids), camera_id).copy()


def effective_crosstalk(light_ids, camera_id: str) -> np.ndarray:
    """(3, K) M = R with columns normalised to sum 1 (see module docstring)."""
    R = response_matrix(light_ids, camera_id)
    s = R.sum(axis=0)
    if (s <= 0).any():
        k = int(np.argmax(s <= 0))
        raise InputError("spectral.lights", f"light '{list(light_ids)[k]}' gives no signal in camera "
                                            f"'{camera_id}' (spectra do not overlap)")
    return R / s


def offdiagonal_share(M: np.ndarray) -> float:
    """Mean fraction of each light's signal outside its own channel (0 = diagonal)."""
    M = np.asarray(M, dtype=np.float64)
    M = M / M.sum(axis=0, keepdims=True)
    k = min(M.shape)
    return float(1.0 - np.diag(M[:k, :k]).mean())


def channel_responses(light_ids, S: np.ndarray) -> np.ndarray:
    """(M, N) raw responses R[m, n] = Σ_λ E_n(λ) S_m(λ) Δλ of unit-peak light spectra in a camera of any
    number of channels (sensitivities S (len(GRID), M), e.g. `spectra.filter_sensitivities`)."""
    E = np.stack([light_spectrum(l).values for l in light_ids], axis=1)  # (G, N)
    return np.asarray(S, np.float64).T @ E * WL_STEP


def rig_crosstalk(light_ids, S: np.ndarray, source: str = "scene.rig") -> np.ndarray:
    """(M, N) effective crosstalk of N light spectra in an M-channel camera: `channel_responses` with
    each column normalised to sum 1, as `effective_crosstalk` does for three channels.  A light that
    the camera all but misses (under a millionth of its emission weighted by the peak sensitivity) is
    one InputError line naming `source`: its column would be the noise of far Gaussian tails."""
    R = channel_responses(light_ids, S)
    s = R.sum(axis=0)
    own = np.array([light_spectrum(l).values.sum() * WL_STEP for l in light_ids])
    dark = s <= 1e-6 * own * float(np.max(S))
    if dark.any():
        k = int(np.argmax(dark))
        raise InputError(source, f"light {k} ('{list(light_ids)[k]}') gives no signal in any camera channel "
                                 f"(its spectrum does not overlap the filters)")
    return R / s
