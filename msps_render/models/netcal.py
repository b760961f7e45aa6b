"""Albedo colour read off the network's own normals ("+netcal"), then predicted again.

Why: a pixel of a surface with albedo colour rho reads c = diag(rho) A n (A = crosstalk @ light
directions), so one RGB image cannot tell the object's colour from a tilt of its normals.
`models/selfcal.py` pins a uniform colour from the unit length of the normals, which needs the
image to be exactly Lambertian under exactly known light intensities: on measured materials and real
captures (highlights, shadows, 8-bit quantisation) its fit degrades -- on DiLiGenT it returns
negative factors -- and it refuses.  The network's normals, though several degrees off per pixel,
are off in *different* directions from pixel to pixel, so over a whole object the per-channel ratio

    rho_k = median over lit pixels of c_k / (A n_net)_k

recovers the colour the network's normals do not explain.  Dividing it out and predicting again
removes the colour the network read as tilt; each round starts from better normals, so a few
rounds converge.  Only pixels every light reaches (the ratio is unstable at grazing shading) and
clear of the dark floor are used; the median ignores highlights and cast shadows.

The loop needs whole images (one colour per object, from the whole object's pixels).  Its settings
were chosen on validation frames only (procedural shapes, training materials: `val-frames`,
`val-frames-grey`, `-colour`, `-texture`), never on a test set or a real capture
(docs/history.md "Stage 13").
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

SUFFIX = "+netcal"  # a method's name with the loop after its (optional) selfcal: NAME+selfcal+netcal
DESCRIPTION = "after the albedo colour read off its own normals, predicted again (models/netcal.py)"


@dataclass(frozen=True)
class NetcalSettings:
    """Chosen on the validation frames by experiments/netcal_sweep.py (docs/history.md "Stage 13"): the lowest
    mean over val-frames, -grey, -colour and -texture with no set worse than +0.10 deg (runs/13-decision.txt).
    More rounds diverge on objects of several colours; the agreement gate keeps the loop off them."""

    rounds: int = 1  # estimate -> divide -> predict again, this many times
    shade_floor: float = 0.2  # a pixel is used when (A n)_k exceeds this for every channel k
    rel_floor: float = 0.1  # ... and every channel exceeds this share of the object's 99th percentile
    min_pixels: int = 200  # fewer usable pixels: no estimate, the network's first normals stand
    min_colour: float = 0.05  # apply only when the first estimate's max |log factor| exceeds this
    chroma_tol: float = 0.2  # a pixel agrees with the estimate when its log chroma is within this of the median
    min_agree: float = 0.6  # apply only when this share of the used pixels agrees (one colour explains them)


@dataclass(frozen=True)
class NetcalFit:
    """What the loop did to one object."""

    scale: np.ndarray  # (3,) multiplies the image's channels (mean 1); ones when not applied
    rounds: int  # rounds run (0: the first estimate was refused)
    n_pixels: int  # pixels the last estimate used
    applied: bool
    agree: float = float("nan")  # the first estimate's share of pixels with its chroma (`chroma_agreement`)


def pixel_ratios(image: np.ndarray, mask: np.ndarray, normals: np.ndarray, rig: np.ndarray,
                 settings: NetcalSettings = NetcalSettings()) -> np.ndarray:
    """(N, 3) c_k / (A n)_k of the pixels every light reaches and clear of the dark floor.
    `rig` = crosstalk @ light_dirs (3, 3); `normals` (H, W, 3) as predicted."""
    m = np.asarray(mask, bool)
    c = np.asarray(image, np.float64)[m]
    if len(c) == 0:
        return np.zeros((0, 3))
    s = np.asarray(normals, np.float64)[m] @ np.asarray(rig, np.float64).T
    top = np.percentile(c, 99.0, axis=0)
    use = (s > settings.shade_floor).all(1) & (c > settings.rel_floor * top).all(1) & (top > 0).all()
    return c[use] / s[use]


def chroma_agreement(ratios: np.ndarray, tol: float) -> float:
    """Share of pixels whose log chroma (log ratio minus its mean over channels: brightness left out)
    lies within `tol` (max over channels) of the median chroma.  Why: one colour per object is the
    model; an object of several coloured materials spreads its ratios, and the loop then diverges
    (measured on val-frames, docs/history.md "Stage 13")."""
    if len(ratios) == 0:
        return 0.0
    lr = np.log(np.maximum(ratios, 1e-12))
    ch = lr - lr.mean(1, keepdims=True)
    return float((np.abs(ch - np.median(ch, axis=0)).max(1) < tol).mean())


def estimate_colour(image: np.ndarray, mask: np.ndarray, normals: np.ndarray, rig: np.ndarray,
                    settings: NetcalSettings = NetcalSettings()) -> tuple[np.ndarray | None, int, float]:
    """(rho (3,) normalised to mean 1, or None when too few pixels; pixels used; their chroma agreement)."""
    r = pixel_ratios(image, mask, normals, rig, settings)
    if len(r) < settings.min_pixels:
        return None, len(r), 0.0
    rho = np.median(r, axis=0)
    if not (np.all(rho > 0) and np.all(np.isfinite(rho))):
        return None, len(r), 0.0
    return rho / rho.mean(), len(r), chroma_agreement(r, settings.chroma_tol)


def divide_out(scale: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """The image's channel factor after also dividing out `rho`, normalised to mean 1 (exposure kept)."""
    s = scale / rho
    return s / s.mean()


def calibrate(predict: Callable[[np.ndarray], np.ndarray], image: np.ndarray, mask: np.ndarray,
              rig: np.ndarray, settings: NetcalSettings = NetcalSettings()
              ) -> tuple[np.ndarray, np.ndarray, NetcalFit]:
    """Run the loop with `predict(image) -> (H, W, 3) normals`.
    Returns (normals, the image the normals were predicted on, fit)."""
    normals = predict(image)
    scale = np.ones(3)
    n_px, done, agree = 0, 0, float("nan")
    for r in range(settings.rounds):
        rho, n_px, ag = estimate_colour(image * scale, mask, normals, rig, settings)
        if rho is None:
            break
        step = divide_out(scale, rho)
        if r == 0:
            agree = ag
            if np.abs(np.log(step)).max() <= settings.min_colour or ag < settings.min_agree:
                break
        scale = step
        normals = predict((image * scale).astype(np.asarray(image).dtype, copy=False))
        done += 1
    applied = done > 0
    out_image = (image * scale).astype(np.asarray(image).dtype, copy=False) if applied else image
    return normals, out_image, NetcalFit(scale if applied else np.ones(3), done, n_px, applied, agree)
