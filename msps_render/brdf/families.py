"""Analytic material families: the registry `FAMILIES` (name -> parameter sampler + BSDF kind).

Each family draws its parameters from a range with the `rng` it is given, so a
material is reproducible from the scene seed.  numpy only: the scene sampler
wraps the parameters into a `MaterialSpec`, the renderer translates the BSDF
kind (`render.materials.BSDFS`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from msps_render.errors import closest


GAMUTS = ("moderate", "full", "mixed")  # albedo colour distributions (docs/appearance.md, plotted there)


def _albedo(rng: np.random.Generator, lo: float = 0.15, hi: float = 0.9,
            gamut: str = "moderate") -> tuple[float, float, float]:
    """An albedo colour.  `moderate` (the corpora up to v0.4): brightness x chroma with every
    channel >= half the largest.  `full`: hue uniform, saturation up to 0.9 (smallest/largest
    channel down to 0.1) and brightness down to lo/3, so saturated and dark colours both occur.
    `mixed`: a third each of achromatic, moderate and full (a grey share inside a colourful corpus)."""
    if gamut == "full":
        return full_gamut_albedo(rng, lo, hi)
    if gamut == "mixed":
        return mixed_albedo(rng, lo, hi)
    chroma = rng.dirichlet([2.0, 2.0, 2.0]) * 3.0
    b = rng.uniform(lo, hi)
    rgb = np.clip(b * (0.5 + 0.5 * chroma / chroma.max()), 0.02, 0.95)
    return tuple(float(x) for x in rgb)


def full_gamut_albedo(rng: np.random.Generator, lo: float = 0.15, hi: float = 0.9) -> tuple[float, float, float]:
    """Hue uniform in [0, 1); saturation 0.9 * u^0.6 (skewed toward saturated; channel ratio
    min/max = 1 - s >= 0.1); value (largest channel) in [lo/3, hi], skewed toward bright."""
    import colorsys

    h, u, b = rng.uniform(size=3)
    s = 0.9 * u ** 0.6
    v = lo / 3.0 + (hi - lo / 3.0) * b ** 0.8
    rgb = np.clip(colorsys.hsv_to_rgb(h, s, v), 0.005, 0.95)
    return tuple(float(x) for x in rgb)


def mixed_albedo(rng: np.random.Generator, lo: float = 0.15, hi: float = 0.9) -> tuple[float, float, float]:
    """One third achromatic (equal channels, brightness uniform in [lo, hi]), one third
    `moderate`, one third `full`.  Why: a net fine-tuned on `full` alone stops defaulting to
    "achromatic" where a pixel's chroma could be shading, and regresses on grey objects; the
    grey share keeps that prior inside the same frames (docs/appearance.md)."""
    pick = rng.uniform()
    if pick < 1.0 / 3.0:
        g = float(rng.uniform(lo, hi))
        return (g, g, g)
    return _albedo(rng, lo, hi, "moderate" if pick < 2.0 / 3.0 else "full")


def _diffuse(rng, gamut="moderate"):
    return {"reflectance": _albedo(rng, gamut=gamut)}


def _plastic(rng, gamut="moderate"):
    # Mitsuba's smooth `plastic` bakes int_ior into the kernel as a literal, so every distinct value
    # compiles a new kernel (~84 % of the compiles left after warm-up, docs/benchmarks.md).  Rounded
    # to 0.1 (1.4/1.5/1.6/1.7; the same single draw, so no other draw moves) they cost 4 kernels.
    return {"diffuse_reflectance": _albedo(rng, 0.1, 0.8, gamut), "int_ior": round(float(rng.uniform(1.4, 1.7)), 1)}


def _roughplastic(rng, gamut="moderate"):
    return {"diffuse_reflectance": _albedo(rng, 0.1, 0.8, gamut), "alpha": float(rng.uniform(0.05, 0.4)),
            "int_ior": float(rng.uniform(1.4, 1.7))}


_CONDUCTORS = ("Au", "Ag", "Al", "Cu", "Cr")  # Mitsuba built-in IOR tables


def _roughconductor(rng, gamut="moderate"):
    return {"material": str(rng.choice(_CONDUCTORS)),
            "alpha": float(rng.uniform(0.08, 0.4))}


def _grey(rng, gamut="moderate"):
    """Grey Lambertian (the control of the unseen-shape tests: a classic PS method's best case)."""
    g = float(rng.uniform(0.5, 0.8))
    return {"reflectance": (g, g, g)}


def _principled(rng, gamut="moderate"):
    return {"base_color": _albedo(rng, gamut=gamut), "roughness": float(rng.uniform(0.2, 0.9)),
            "metallic": float(rng.choice([0.0, 0.0, rng.uniform(0.0, 1.0)])),
            "specular": float(rng.uniform(0.2, 0.8))}


@dataclass(frozen=True)
class MaterialFamily:
    """An analytic material family: `sample(rng, gamut)` draws its parameters, `bsdf` is the
    material kind that renders them (a key of `render.materials.BSDFS`); `albedo` and
    `roughness` name the parameters a texture drives (None: the family has none)."""

    sample: Callable[..., dict]
    bsdf: str
    albedo: str | None = None
    roughness: str | None = None
    roughness_range: tuple[float, float] = (0.05, 0.4)


# The registry: one line adds a family (its BSDF kind must exist in render.materials.BSDFS).
FAMILIES: dict[str, MaterialFamily] = {
    "diffuse": MaterialFamily(_diffuse, "diffuse", "reflectance"),
    "plastic": MaterialFamily(_plastic, "plastic", "diffuse_reflectance"),
    # Mitsuba's roughplastic takes alpha as a float only: its roughness cannot be textured
    "roughplastic": MaterialFamily(_roughplastic, "roughplastic", "diffuse_reflectance"),
    "roughconductor": MaterialFamily(_roughconductor, "roughconductor", None, "alpha", (0.08, 0.4)),
    "principled": MaterialFamily(_principled, "principled", "base_color", "roughness", (0.2, 0.9)),
    "grey": MaterialFamily(_grey, "diffuse", "reflectance"),
}
MEASURED_KIND = "merl"  # the material kind of every measured (tabulated) material
MATERIAL_KINDS = tuple(dict.fromkeys(f.bsdf for f in FAMILIES.values())) + (MEASURED_KIND,)


def unknown_family(name: str) -> str:
    """The one-line message for a family name that is not in `FAMILIES`."""
    return f"unknown material family '{name}'{closest(name, FAMILIES)}; known: {', '.join(FAMILIES)}"
