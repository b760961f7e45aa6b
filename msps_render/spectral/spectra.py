"""Light spectra and camera sensitivities as colour-science objects on one 1 nm grid.

Ids (strings, so a SceneSpec stays plain JSON):

* light spectra: ``led:PEAK:FWHM`` (Gaussian LED, nm, e.g. ``led:630:20``), ``flat``
  (equal energy), ``d65`` (CIE D65), or a path to a CSV file ``wavelength_nm,value``;
* cameras: a name from ``colour.MSDS_CAMERA_SENSITIVITIES`` (e.g. ``Nikon 5100 (NPL)``)
  or a path to a CSV file ``wavelength_nm,red,green,blue``.

Everything is resampled (linear interpolation, zero outside the data) to the grid
GRID = 360..830 nm step 1 nm, which is the wavelength range Mitsuba's spectral
variants sample (MI_CIE_MIN..MI_CIE_MAX).  The renderer receives exactly these
arrays, so the crosstalk computed here and the film's integral agree.
Spectra are returned with unit peak; absolute scale is set by the renderer.
"""
from __future__ import annotations

import re
from functools import lru_cache
from pathlib import Path

import numpy as np

from msps_render.errors import InputError, closest

WL_MIN, WL_MAX, WL_STEP = 360.0, 830.0, 1.0
GRID = np.arange(WL_MIN, WL_MAX + 0.5 * WL_STEP, WL_STEP)
LIGHT_ID_FORMS = "'led:PEAK:FWHM', 'flat', 'd65' or a path to a .csv file"
_LED = re.compile(r"^led:\s*([0-9.]+)\s*:\s*([0-9.]+)\s*$")


def _shape():
    import colour

    return colour.SpectralShape(WL_MIN, WL_MAX, WL_STEP)


def _to_grid(wl: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Linear resampling onto GRID, zero outside the data (no extrapolation)."""
    v = np.atleast_2d(values.T).T if values.ndim == 1 else values
    out = np.stack([np.interp(GRID, wl, v[:, j], left=0.0, right=0.0) for j in range(v.shape[1])], -1)
    return out[:, 0] if values.ndim == 1 else out


def _sd(values: np.ndarray, name: str):
    import colour

    return colour.SpectralDistribution(np.asarray(values, dtype=np.float64), GRID, name=name)


# ------------------------------------------------------------------------ CSV
def read_csv_table(path: str | Path, n_values: int | None, what: str) -> tuple[np.ndarray, np.ndarray]:
    """Read `wavelength, v1..vn` rows (a header line is allowed) and validate them.
    `n_values` None: as many value columns as the first data row has (at least one).

    Errors (one line naming the file): missing, unparsable, wrong column count,
    non-finite, wavelengths not strictly increasing, negative values, data
    outside the renderer's 360-830 nm range, fewer than 2 rows.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(p, f"{what} file not found")
    rows = []
    try:
        lines = p.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(p, f"cannot read {what} file ({e})") from None
    for ln, line in enumerate(lines, 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = [x for x in re.split(r"[,;\s]+", s) if x]
        try:
            vals = [float(x) for x in parts]
        except ValueError:
            if not rows:  # a header line
                continue
            raise InputError(p, f"line {ln}: not a number in '{s[:60]}'") from None
        if n_values is None:
            n_values = max(len(vals) - 1, 1)
        if len(vals) != n_values + 1:
            raise InputError(p, f"line {ln}: expected {n_values + 1} columns (wavelength + {n_values} "
                                f"values), got {len(vals)}")
        rows.append(vals)
    if len(rows) < 2:
        raise InputError(p, f"{what} needs at least 2 rows of data, found {len(rows)}")
    n_values = n_values or 1
    a = np.asarray(rows, dtype=np.float64)
    if not np.isfinite(a).all():
        raise InputError(p, f"{what} has NaN/inf values")
    wl, v = a[:, 0], a[:, 1:]
    d = np.diff(wl)
    if (d <= 0).any():
        i = int(np.argmax(d <= 0))
        raise InputError(p, f"wavelengths must be strictly increasing (row {i + 2}: {wl[i + 1]:g} nm "
                            f"after {wl[i]:g} nm)")
    if (v < 0).any():
        i = int(np.argmax((v < 0).any(axis=1)))
        raise InputError(p, f"{what} has negative values (first at {wl[i]:g} nm)")
    if wl[0] < WL_MIN or wl[-1] > WL_MAX:
        raise InputError(p, f"wavelengths {wl[0]:g}-{wl[-1]:g} nm lie outside the renderer's range "
                            f"{WL_MIN:g}-{WL_MAX:g} nm")
    if wl[-1] - wl[0] < WL_STEP:
        raise InputError(p, f"{what} covers less than {WL_STEP:g} nm")
    if not (v.max(axis=0) > 0).all():
        raise InputError(p, f"{what} is zero everywhere (in at least one column)")
    return wl, v[:, 0] if n_values == 1 else v


# --------------------------------------------------------------------- lights
def gaussian_led(peak_nm: float, fwhm_nm: float):
    """Gaussian LED emission with unit peak, as a colour SpectralDistribution on GRID."""
    if not (WL_MIN <= peak_nm <= WL_MAX):
        raise InputError("spectral.lights", f"LED peak {peak_nm:g} nm is outside {WL_MIN:g}-{WL_MAX:g} nm")
    if not (1.0 <= fwhm_nm <= 400.0):
        raise InputError("spectral.lights", f"LED FWHM must be in [1, 400] nm, got {fwhm_nm:g}")
    sigma = fwhm_nm / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    return _sd(np.exp(-0.5 * ((GRID - peak_nm) / sigma) ** 2), f"led:{peak_nm:g}:{fwhm_nm:g}")


@lru_cache(maxsize=64)
def _light_values(sid: str) -> np.ndarray:
    import colour

    s = sid.strip()
    m = _LED.match(s.lower())
    if m:
        v = gaussian_led(float(m.group(1)), float(m.group(2))).values
    elif s.lower() == "flat":
        v = np.ones_like(GRID)
    elif s.lower() == "d65":
        d65 = colour.SDS_ILLUMINANTS["D65"]
        v = _to_grid(np.asarray(d65.wavelengths), np.asarray(d65.values))
    elif s.lower().endswith(".csv") or "/" in s or Path(s).suffix:
        wl, vals = read_csv_table(s, 1, "light spectrum")
        v = _to_grid(wl, vals)
    else:
        raise InputError("spectral.lights", f"unknown light spectrum '{sid}' (use {LIGHT_ID_FORMS})")
    if not (v.max() > 0):
        raise InputError(sid, "light spectrum is zero inside 360-830 nm")
    v = v / v.max()
    v.setflags(write=False)
    return v


def light_spectrum(sid: str):
    """Unit-peak emission spectrum for a light id (colour SpectralDistribution on GRID)."""
    return _sd(_light_values(sid).copy(), sid)


# -------------------------------------------------------------------- cameras
def known_cameras() -> list[str]:
    import colour

    return sorted(colour.MSDS_CAMERA_SENSITIVITIES.keys())


@lru_cache(maxsize=16)
def _camera_values(cid: str) -> np.ndarray:
    import colour

    if cid in colour.MSDS_CAMERA_SENSITIVITIES:
        msds = colour.MSDS_CAMERA_SENSITIVITIES[cid]
        wl, v = np.asarray(msds.wavelengths), np.asarray(msds.values)
        if v.shape[1] != 3:
            raise InputError("spectral.camera", f"camera '{cid}' has {v.shape[1]} channels, need 3")
    elif cid.lower().endswith(".csv") or "/" in cid:
        wl, v = read_csv_table(cid, 3, "camera sensitivity")
    else:
        known = known_cameras()
        raise InputError("spectral.camera", f"unknown camera '{cid}'{closest(cid, known)} (known: "
                                            f"{', '.join(known)}; or a CSV path wavelength,r,g,b)")
    out = _to_grid(wl, np.clip(v, 0, None))
    out = out / out.max()
    out.setflags(write=False)
    return out


def camera_sensitivities(cid: str):
    """(r, g, b) sensitivities, max-normalised to 1, as colour MultiSpectralDistributions on GRID."""
    import colour

    return colour.MultiSpectralDistributions(_camera_values(cid).copy(), GRID, name=cid,
                                             labels=("red", "green", "blue"))


def validate_light_id(sid: str) -> str:
    _light_values(sid)
    return sid


def validate_camera_id(cid: str) -> str:
    _camera_values(cid)
    return cid


# ------------------------------------------------------- narrow-band rigs (M channels)
BAND_REACH = 2.0  # a Gaussian band must fit in the grid out to centre +- BAND_REACH x FWHM (~4.7 sigma)


def band_problem(centre_nm: float, fwhm_nm: float) -> str | None:
    """Why a Gaussian band (a filter or an LED) of this centre and FWHM cannot be rendered, or None.

    Why +- 2 FWHM: beyond it a Gaussian holds < 1e-6 of its area, so cutting it at the renderer's
    range changes nothing; a band reaching past 360 or 830 nm would lose part of itself unseen."""
    c, w = float(centre_nm), float(fwhm_nm)
    if not (np.isfinite(c) and np.isfinite(w)):
        return f"centre and FWHM must be finite, got [{c:g}, {w:g}]"
    if not 1.0 <= w <= 400.0:
        return f"FWHM must be in [1, 400] nm, got {w:g}"
    lo, hi = c - BAND_REACH * w, c + BAND_REACH * w
    if lo < WL_MIN or hi > WL_MAX:
        return (f"centre {c:g} nm +- {BAND_REACH:g} x FWHM {w:g} nm = [{lo:g}, {hi:g}] nm lies outside the "
                f"renderer's spectral range {WL_MIN:g}-{WL_MAX:g} nm")
    return None


def gaussian_band(centre_nm: float, fwhm_nm: float) -> np.ndarray:
    """Unit-peak Gaussian on GRID (a narrow-band filter's transmission, an LED's emission)."""
    sigma = fwhm_nm / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    return np.exp(-0.5 * ((GRID - centre_nm) / sigma) ** 2)


def filter_sensitivities(filters) -> np.ndarray:
    """(len(GRID), M) sensitivities of a camera whose channel m is the Gaussian filter filters[m] =
    (centre nm, FWHM nm), each with unit peak (a bare sensor behind ideal narrow-band filters)."""
    out = np.stack([gaussian_band(c, w) for c, w in filters], axis=1)
    out.setflags(write=False)
    return out


@lru_cache(maxsize=16)
def _table_values(cid: str) -> np.ndarray:
    if cid.lower().endswith(".csv") or "/" in cid:
        wl, v = read_csv_table(cid, None, "camera sensitivity")
        out = _to_grid(wl, np.asarray(v, np.float64).reshape(len(wl), -1))
        out = out / out.max()
        out.setflags(write=False)
        return out
    return _camera_values(cid)  # a colour-science camera: three channels


def sensitivity_table(cid: str) -> np.ndarray:
    """(len(GRID), M) max-normalised sensitivities of a camera id: a colour-science camera (M = 3) or a
    CSV `wavelength, s1..sM` with any number of channels (measured filters, multispectral cameras)."""
    return _table_values(cid).copy()


def display_weights(S: np.ndarray) -> np.ndarray:
    """(M, 3) weights that show M camera channels (sensitivities S, (len(GRID), M)) as linear sRGB:
    row m is the colour of channel m's own sensitivity as the eye sees it (CIE 1931 2 deg, clipped to
    the sRGB gamut, unit row sum); a channel the eye cannot see (infrared, ultraviolet) shows grey.
    For previews only: the data are the M channels."""
    import colour

    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    xyz = _to_grid(np.asarray(cmfs.wavelengths, np.float64), np.asarray(cmfs.values, np.float64))
    to_srgb = np.array([[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]])
    rgb = np.clip((np.asarray(S, np.float64).T @ xyz) @ to_srgb.T, 0.0, None)
    s = rgb.sum(axis=1, keepdims=True)
    return np.where(s > 1e-9 * max(float(s.max()), 1e-300), rgb / np.where(s > 0, s, 1.0), 1.0 / 3.0)
