"""The photometric set-up as numbers, and the calibration JSON that carries it.

Light directions from slant/tilt (camera frame, pointing toward the light), the
paper's crosstalk matrix and the check that a crosstalk matrix is usable are
shared by the scene sampler, dataset verification and prediction (numpy only).

Calibration JSON: the three lights of one multispectral image, as `msps predict --calibration` reads it.

Schema (`msps-calibration-1`, documented in docs/recipes.md "Calibration JSON"):

    {
      "format": "msps-calibration-1",            optional
      "light_dirs": [[x, y, z], [..], [..]],     row k: toward light k, camera frame (x right, y up,
                                                 z toward the camera); normalised on read, z > 0
      -- or instead of light_dirs --
      "slant_deg": 30.0,                         all three lights at this slant ...
      "tilts_deg": [0, 120, 240],                ... and these tilts (default 0/120/240)
      -- or instead of both --
      "lights": [{"direction": [x, y, z]} | {"slant_deg": s, "tilt_deg": t}, ...] (3 entries;
                an "rgb" in every entry gives the crosstalk columns when "crosstalk" is absent)
      "crosstalk": [[..], [..], [..]],           M[i][k]: response of camera channel i to light k on a
                                                 white surface (default: the paper's 0.92 / 0.04)
      "source": "...", "info": {...}             optional, informational (ignored)
    }

Anything else is refused with one line naming the file and the key: a
calibration that is silently half-read gives wrong normals without a word.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from msps_render.errors import InputError, closest, read_text

FORMAT = "msps-calibration-1"
KEYS = ("format", "light_dirs", "slant_deg", "tilts_deg", "lights", "crosstalk", "source", "info")
from msps_render.rig import PAPER_CROSSTALK, PAPER_SLANT_DEG as DEFAULT_SLANT_DEG, PAPER_TILTS_DEG as DEFAULT_TILTS_DEG  # noqa: E402

# What a prediction may differ from the trained geometry by before `msps predict` warns.
SLANT_TOL_DEG = 5.0
TILT_TOL_DEG = 10.0
CROSSTALK_TOL = 0.05




def crosstalk_problem(M) -> str | None:
    """What is wrong with a crosstalk matrix (rows: camera channels, columns: lights), or None.

    It must be finite and non-negative, every light must reach at least one
    channel, and for three lights it must be invertible (well conditioned):
    a singular matrix makes the lights inseparable and demultiplexing impossible.
    """
    M = np.asarray(M, dtype=np.float64)
    if M.ndim != 2 or M.shape[0] < 1 or M.shape[1] < 1:
        return f"must be an MxK matrix (channels x lights), got shape {M.shape}"
    if not np.isfinite(M).all():
        return f"has {int((~np.isfinite(M)).sum())} NaN/inf entries"
    if (M < 0).any():
        i, j = (int(x) for x in np.argwhere(M < 0)[0])
        return f"has negative entries (row {i}, column {j}: {M[i, j]:g})"
    dead = [k for k in range(M.shape[1]) if M[:, k].sum() <= 0]
    if dead:
        return f"light {dead[0]} reaches no camera channel (column {dead[0]} is all zero)"
    if M.shape == (3, 3):
        sv = np.linalg.svd(M, compute_uv=False)
        if sv[-1] <= 1e-6 * sv[0]:
            return (f"is singular (rank {int((sv > 1e-6 * sv[0]).sum())}, condition number "
                    f"{'inf' if sv[-1] == 0 else f'{sv[0] / sv[-1]:.3g}'}): the lights cannot be told apart")
    return None


def check_crosstalk(M, source: str = "lights.crosstalk") -> np.ndarray:
    """`M` as a float array, or InputError naming `source`."""
    why = crosstalk_problem(M)
    if why:
        raise InputError(source, f"crosstalk {why}")
    return np.asarray(M, dtype=np.float64)


def direction_from_slant_tilt(slant_deg: float, tilt_deg: float) -> np.ndarray:
    """Unit vector toward the light, camera frame."""
    if not (0.0 < slant_deg < 90.0):
        raise InputError("lights.slant_deg", f"slant must be in (0, 90) degrees, got {slant_deg}")
    s, t = np.radians(slant_deg), np.radians(tilt_deg)
    return np.array([np.sin(s) * np.cos(t), np.sin(s) * np.sin(t), np.cos(s)])


def slant_tilt_from_direction(d) -> tuple[float, float]:
    d = np.asarray(d, dtype=np.float64)
    d = d / np.linalg.norm(d)
    return float(np.degrees(np.arccos(np.clip(d[2], -1, 1)))), float(
        np.degrees(np.arctan2(d[1], d[0])) % 360.0)


def _matrix(v, what: str, source, shape=(3, 3)) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(source, f"{what} must be a {shape[0]}x{shape[1]} array of numbers") from None
    if a.shape != shape:
        raise InputError(source, f"{what} must be {shape[0]}x{shape[1]}, got shape {list(a.shape)}")
    if not np.isfinite(a).all():
        raise InputError(source, f"{what} has NaN/inf entries")
    return a


def _number(v, what: str, source) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InputError(source, f"{what} must be a finite number, got {v!r}")
    return float(v)


def _slant_tilt(slant, tilt, source, what: str) -> np.ndarray:
    s = _number(slant, f"{what} slant_deg", source)
    t = _number(tilt, f"{what} tilt_deg", source)
    if not 0.0 < s < 90.0:
        raise InputError(source, f"{what} slant_deg must be in (0, 90) degrees, got {s:g}")
    return direction_from_slant_tilt(s, t)


def _from_lights(lights, source) -> tuple[np.ndarray, np.ndarray | None]:
    if not isinstance(lights, list) or len(lights) != 3:
        raise InputError(source, "'lights' must be a list of 3 objects")
    dirs, rgbs = [], []
    for k, e in enumerate(lights):
        if not isinstance(e, dict):
            raise InputError(source, f"lights[{k}] must be an object with 'direction' or 'slant_deg'/'tilt_deg'")
        extra = set(e) - {"direction", "slant_deg", "tilt_deg", "rgb", "kind", "name"}
        if extra:
            raise InputError(source, f"lights[{k}]: unknown key '{sorted(extra)[0]}' "
                                     "(known: direction, slant_deg, tilt_deg, rgb)")
        if "direction" in e:
            dirs.append(_matrix(e["direction"], f"lights[{k}].direction", source, (3,)))
        elif "slant_deg" in e:
            dirs.append(_slant_tilt(e["slant_deg"], e.get("tilt_deg", DEFAULT_TILTS_DEG[k]), source, f"lights[{k}]"))
        else:
            raise InputError(source, f"lights[{k}] needs 'direction' or 'slant_deg' (+ 'tilt_deg')")
        if "rgb" in e:
            rgbs.append(_matrix(e["rgb"], f"lights[{k}].rgb", source, (3,)))
    M = np.stack(rgbs, axis=1) if len(rgbs) == 3 else None
    if rgbs and M is None:
        raise InputError(source, "'rgb' must be given for all three lights or none")
    return np.stack(dirs), M


def parse_calibration(d, source: str | Path = "<calibration>") -> tuple[np.ndarray, np.ndarray]:
    """(light_dirs 3x3 unit rows, crosstalk 3x3) from a calibration dict; InputError naming `source`."""
    if not isinstance(d, dict):
        hint = ' (a 3x3 list of light directions goes in {"light_dirs": [...]})' if isinstance(d, list) else ""
        raise InputError(source, f"calibration must be a JSON object, got {type(d).__name__}{hint}")
    for k in d:
        if k not in KEYS:
            raise InputError(source, f"unknown key '{k}'{closest(k, KEYS)} (known: {', '.join(KEYS)})")
    if "format" in d and d["format"] != FORMAT:
        raise InputError(source, f"format is {d['format']!r}, expected {FORMAT!r}")
    given = [k for k in ("light_dirs", "slant_deg", "lights") if k in d]
    if len(given) > 1:
        raise InputError(source, f"give one of light_dirs, slant_deg (+ tilts_deg), lights; got {', '.join(given)}")
    if "tilts_deg" in d and "slant_deg" not in d:
        raise InputError(source, "tilts_deg needs slant_deg")
    M_lights = None
    if "light_dirs" in d:
        L = _matrix(d["light_dirs"], "light_dirs", source)
    elif "slant_deg" in d:
        tilts = d.get("tilts_deg", list(DEFAULT_TILTS_DEG))
        if not isinstance(tilts, list) or len(tilts) != 3:
            raise InputError(source, "tilts_deg must be a list of 3 numbers")
        L = np.stack([_slant_tilt(d["slant_deg"], t, source, "") for t in tilts])
    elif "lights" in d:
        L, M_lights = _from_lights(d["lights"], source)
    else:
        L = np.stack([_slant_tilt(DEFAULT_SLANT_DEG, t, source, "") for t in DEFAULT_TILTS_DEG])
    norms = np.linalg.norm(L, axis=1)
    if (norms < 1e-9).any():
        raise InputError(source, f"light direction {int(np.argmin(norms))} is the zero vector")
    L = L / norms[:, None]
    if (L[:, 2] <= 0).any():
        k = int(np.argmin(L[:, 2]))
        raise InputError(source, f"light {k} points away from the camera (z = {L[k, 2]:.3f} <= 0; "
                                 "camera frame: x right, y up, z toward the camera)")
    sv = np.linalg.svd(L, compute_uv=False)
    if sv[-1] < 1e-3 * sv[0]:
        raise InputError(source, "the three light directions are coplanar (photometric stereo needs them independent)")
    if "crosstalk" in d:
        M = _matrix(d["crosstalk"], "crosstalk", source)
    elif M_lights is not None:
        M = M_lights
    else:
        M = PAPER_CROSSTALK.copy()
    why = crosstalk_problem(M)
    if why:
        raise InputError(source, f"crosstalk {why}")
    return L, M


def load_calibration_file(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    p = Path(path)
    text = read_text(p, "calibration file")
    try:
        d = json.loads(text)
    except json.JSONDecodeError as e:
        raise InputError(p, f"not valid JSON ({e})") from None
    return parse_calibration(d, p)


def calibration_dict(light_dirs, crosstalk, source: str | None = None, info: dict | None = None) -> dict:
    """A calibration in the schema above (values rounded to 9 significant digits)."""
    r = lambda a: [[float(f"{v:.9g}") for v in row] for row in np.asarray(a, dtype=np.float64)]
    d = {"format": FORMAT, "light_dirs": r(light_dirs), "crosstalk": r(crosstalk)}
    if source:
        d["source"] = source
    if info:
        d["info"] = info
    return d


def write_calibration(path: str | Path, light_dirs, crosstalk, source: str | None = None,
                      info: dict | None = None) -> Path:
    p = Path(path)
    p.write_text(json.dumps(calibration_dict(light_dirs, crosstalk, source, info), indent=1) + "\n")
    return p


# --------------------------------------------------------- trained geometry
def paper_geometry() -> dict:
    return {"slant_deg": [DEFAULT_SLANT_DEG, DEFAULT_SLANT_DEG], "tilts_deg": list(DEFAULT_TILTS_DEG),
            "crosstalk": PAPER_CROSSTALK.tolist(), "source": "model card (paper geometry)"}


def geometry_warnings(light_dirs, crosstalk, trained: dict | None) -> list[str]:
    """Ways the given lights differ from the geometry a network was trained for (empty: none)."""
    trained = trained or paper_geometry()
    out = []
    st = [slant_tilt_from_direction(l) for l in np.asarray(light_dirs)]
    lo, hi = trained["slant_deg"]
    far = [s for s, _ in st if s < lo - SLANT_TOL_DEG or s > hi + SLANT_TOL_DEG]
    where = f"{lo:g} deg" if lo == hi else f"{lo:g}-{hi:g} deg"
    if far:
        out.append(f"light slant {', '.join(f'{s:.1f}' for s, _ in st)} deg differs from the {where} the "
                   f"network was trained for by more than {SLANT_TOL_DEG:g} deg ({trained['source']})")
    tt = trained.get("tilts_deg")
    if tt and len(tt) == len(st):
        d = [abs((t - u + 180) % 360 - 180) for (_, t), u in zip(st, tt)]
        if max(d) > TILT_TOL_DEG:
            out.append(f"light tilts {', '.join(f'{t:.0f}' for _, t in st)} deg differ from the trained "
                       f"{', '.join(f'{u:g}' for u in tt)} deg by up to {max(d):.0f} deg")
    if trained.get("crosstalk") is not None:
        diff = float(np.abs(np.asarray(crosstalk) - np.asarray(trained["crosstalk"])).max())
        if diff > CROSSTALK_TOL:
            out.append(f"crosstalk differs from the trained one by up to {diff:.2f}")
    if out:
        out.append("the network takes no light input: it assumes the trained geometry "
                   "(try --method lambertian, or train on data rendered with these lights)")
    return out


# --------------------------------------------------------- the rig as one value
# `Rig` lives in msps_render.rig (any number of lights, channels and shots); the three-light rig of this
# module's calibration JSON is its first case (`Rig.paper()`, `Rig(light_dirs, crosstalk)`).
from msps_render.rig import Rig  # noqa: E402,F401,I001  (re-exported: the dual-cue code imports it from here)
