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


def _albedo(rng: np.random.Generator, lo: float = 0.15, hi: float = 0.9) -> tuple[float, float, float]:
    # Sample a colour as brightness x chroma so dark and saturated albedos both occur.
    chroma = rng.dirichlet([2.0, 2.0, 2.0]) * 3.0
    b = rng.uniform(lo, hi)
    rgb = np.clip(b * (0.5 + 0.5 * chroma / chroma.max()), 0.02, 0.95)
    return tuple(float(x) for x in rgb)


def _diffuse(rng):
    return {"reflectance": _albedo(rng)}


def _plastic(rng):
    # Mitsuba's smooth `plastic` bakes int_ior into the kernel as a literal, so every distinct value
    # compiles a new kernel (~84 % of the compiles left after warm-up, docs/benchmarks.md).  Rounded
    # to 0.1 (1.4/1.5/1.6/1.7; the same single draw, so no other draw moves) they cost 4 kernels.
    return {"diffuse_reflectance": _albedo(rng, 0.1, 0.8), "int_ior": round(float(rng.uniform(1.4, 1.7)), 1)}


def _roughplastic(rng):
    return {"diffuse_reflectance": _albedo(rng, 0.1, 0.8), "alpha": float(rng.uniform(0.05, 0.4)),
            "int_ior": float(rng.uniform(1.4, 1.7))}


_CONDUCTORS = ("Au", "Ag", "Al", "Cu", "Cr")  # Mitsuba built-in IOR tables


def _roughconductor(rng):
    return {"material": str(rng.choice(_CONDUCTORS)),
            "alpha": float(rng.uniform(0.08, 0.4))}


def _grey(rng):
    """Grey Lambertian (the control of the unseen-shape tests: a classic PS method's best case)."""
    g = float(rng.uniform(0.5, 0.8))
    return {"reflectance": (g, g, g)}


def _principled(rng):
    return {"base_color": _albedo(rng), "roughness": float(rng.uniform(0.2, 0.9)),
            "metallic": float(rng.choice([0.0, 0.0, rng.uniform(0.0, 1.0)])),
            "specular": float(rng.uniform(0.2, 0.8))}


@dataclass(frozen=True)
class MaterialFamily:
    """An analytic material family: `sample(rng)` draws its parameters, `bsdf` is the
    material kind that renders them (a key of `render.materials.BSDFS`)."""

    sample: Callable[[np.random.Generator], dict]
    bsdf: str


# The registry: one line adds a family (its BSDF kind must exist in render.materials.BSDFS).
FAMILIES: dict[str, MaterialFamily] = {
    "diffuse": MaterialFamily(_diffuse, "diffuse"),
    "plastic": MaterialFamily(_plastic, "plastic"),
    "roughplastic": MaterialFamily(_roughplastic, "roughplastic"),
    "roughconductor": MaterialFamily(_roughconductor, "roughconductor"),
    "principled": MaterialFamily(_principled, "principled"),
    "grey": MaterialFamily(_grey, "diffuse"),
}
MEASURED_KIND = "merl"  # the material kind of every measured (tabulated) material
MATERIAL_KINDS = tuple(dict.fromkeys(f.bsdf for f in FAMILIES.values())) + (MEASURED_KIND,)


def unknown_family(name: str) -> str:
    """The one-line message for a family name that is not in `FAMILIES`."""
    return f"unknown material family '{name}'{closest(name, FAMILIES)}; known: {', '.join(FAMILIES)}"
