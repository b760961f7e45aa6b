"""Analytic BRDF models evaluated into MERL-format tables.

Without the real MERL files (not redistributable, never downloaded here) the
toolkit still renders measured-style materials from tables it builds itself:
an analytic model is evaluated at the centre of every MERL bin and written as
a valid `.binary`, so the exact same code path (reader, lookup, plugin) is used.
Tables are deterministic functions of (model, params) and cached on disk under
`$MSPS_CACHE_DIR/brdf` (default `~/.cache/msps/brdf`); they are never committed.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
from pathlib import Path
from typing import Callable

import numpy as np

from msps_render.brdf import merl

TABLE_VERSION = 1  # bump when a model's formula or the bin-centre rule changes


def _rgb(v, what: str) -> np.ndarray:
    a = np.broadcast_to(np.asarray(v, dtype=np.float64), (3,))
    if not np.all(np.isfinite(a)) or np.any(a < 0):
        raise ValueError(f"{what} must be 3 finite non-negative values, got {v}")
    return a


def lambert(wi: np.ndarray, wo: np.ndarray, albedo=(0.8, 0.8, 0.8)) -> np.ndarray:
    """rho / pi, independent of direction (so its table is exact)."""
    shape = np.broadcast_shapes(np.shape(wi)[:-1], np.shape(wo)[:-1])
    return np.broadcast_to(_rgb(albedo, "albedo") / math.pi, (*shape, 3)).copy()


def ggx_d(cos_h: np.ndarray, alpha: float) -> np.ndarray:
    """GGX / Trowbridge-Reitz normal distribution D(theta_h) (1/sr, projected-area normalised)."""
    a2 = alpha * alpha
    c2 = cos_h * cos_h
    return a2 / (math.pi * (c2 * (a2 - 1.0) + 1.0) ** 2)


def _smith_lambda(cos_t: np.ndarray, alpha: float) -> np.ndarray:
    c2 = np.maximum(cos_t * cos_t, 1e-12)
    tan2 = np.maximum(1.0 - c2, 0.0) / c2
    return 0.5 * (np.sqrt(1.0 + alpha * alpha * tan2) - 1.0)


def ggx(wi: np.ndarray, wo: np.ndarray, kd=(0.2, 0.2, 0.2), ks=(1.0, 1.0, 1.0), alpha: float = 0.1,
        f0: float = 0.04, separable: float = 0.0) -> np.ndarray:
    """Diffuse + Cook-Torrance GGX lobe: kd/pi + ks F(theta_d) D G / (4 cos_i cos_o).

    F is Schlick's with normal reflectance `f0` (f0 = 1 gives a metal whose
    colour is ks). G is Smith's height-correlated G2, or the separable
    G1(wi) G1(wo) when `separable` is 1 (as Mitsuba's `roughconductor`, which
    the tests compare against: ks = 1, f0 = 1 is its `material = "none"`). Cosines are clamped to 1e-3 so that bins whose centre lies
    just below the horizon get the smooth continuation, not a hard 0.
    """
    kd, ks = _rgb(kd, "kd"), _rgb(ks, "ks")
    if not (0 < alpha <= 1.0):
        raise ValueError(f"alpha must be in (0, 1], got {alpha}")
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    h = wi + wo
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    ci = np.maximum(wi[..., 2], 1e-3)
    co = np.maximum(wo[..., 2], 1e-3)
    cd = np.clip(np.sum(wi * h, axis=-1), 0.0, 1.0)
    F = f0 + (1.0 - f0) * (1.0 - cd) ** 5
    li, lo = _smith_lambda(ci, alpha), _smith_lambda(co, alpha)
    G = 1.0 / ((1.0 + li) * (1.0 + lo)) if separable else 1.0 / (1.0 + li + lo)
    spec = F * ggx_d(h[..., 2], alpha) * G / (4.0 * ci * co)
    return kd / math.pi + spec[..., None] * ks


MODELS: dict[str, Callable[..., np.ndarray]] = {"lambert": lambert, "ggx": ggx}


def evaluate(model: str, params: dict, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """BRDF (..., 3) of a named model for local-frame direction pairs."""
    if model not in MODELS:
        raise ValueError(f"unknown analytic BRDF model '{model}' (known: {', '.join(MODELS)})")
    return MODELS[model](wi, wo, **params)


def make_table(model: str, params: dict) -> np.ndarray:
    """The model evaluated at every MERL bin centre: shape (3, 90, 90, 180), 1/sr."""
    th, td, pd = merl.bin_centres()
    wi, wo = merl.half_diff_to_dirs(th, td, pd)
    vals = evaluate(model, params, wi, wo)  # (90, 90, 180, 3)
    return np.ascontiguousarray(np.moveaxis(vals, -1, 0))


def cache_dir() -> Path:
    """Where generated tables live: $MSPS_CACHE_DIR/brdf, else $XDG_CACHE_HOME/msps/brdf, else ~/.cache/msps/brdf."""
    if os.environ.get("MSPS_CACHE_DIR"):
        return Path(os.environ["MSPS_CACHE_DIR"]) / "brdf"
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "msps" / "brdf"


@contextlib.contextmanager
def cache_writes(d: Path):
    """Within: a write fault in the table cache `cache_dir()` (a full home disk, say) also says what the
    file is and how to move the cache, since a user did not choose that place (`d`: where it writes)."""
    from msps_render.errors import WriteFailed

    try:
        yield
    except WriteFailed as e:
        if Path(d) != cache_dir():
            raise
        raise WriteFailed(e.source, e.errno, f"{e.problem} (the measured-table cache: set MSPS_CACHE_DIR to put "
                                             "it elsewhere)") from None


def _canonical(params: dict) -> dict:
    out = {}
    for k in sorted(params):
        v = params[k]
        out[k] = [float(x) for x in v] if isinstance(v, (list, tuple, np.ndarray)) else float(v)
    return out


def table_key(model: str, params: dict) -> str:
    """Stable file stem for (model, params): same inputs give the same file on every machine."""
    blob = json.dumps({"model": model, "params": _canonical(params), "v": TABLE_VERSION}, sort_keys=True)
    return f"{model}-{hashlib.sha1(blob.encode()).hexdigest()[:16]}"


def generated_table(model: str, params: dict, directory: str | os.PathLike | None = None) -> Path:
    """Path of the MERL-format table for (model, params), building it once (atomic write) if absent."""
    d = Path(directory) if directory is not None else cache_dir()
    path = d / f"{table_key(model, params)}.binary"
    if path.is_file() and path.stat().st_size == merl.FILE_BYTES:
        return path
    with cache_writes(d):
        return merl.write_merl(path, make_table(model, _canonical(params)))
