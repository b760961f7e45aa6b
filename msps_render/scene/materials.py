"""Analytic material families: sampling parameters and translating to Mitsuba.

Each family draws its parameters from a range with the `rng` it is given, so a
material is reproducible from the scene seed.  Measured (MERL) materials live
in `msps_render.brdf`; this module only forwards them to it.
"""
from __future__ import annotations

import numpy as np

from msps_render.errors import InputError, closest
from msps_render.scene.spec import MaterialSpec


def _albedo(rng: np.random.Generator, lo: float = 0.15, hi: float = 0.9) -> tuple[float, float, float]:
    # Sample a colour as brightness x chroma so dark and saturated albedos both occur.
    chroma = rng.dirichlet([2.0, 2.0, 2.0]) * 3.0
    b = rng.uniform(lo, hi)
    rgb = np.clip(b * (0.5 + 0.5 * chroma / chroma.max()), 0.02, 0.95)
    return tuple(float(x) for x in rgb)


def _diffuse(rng):
    return {"reflectance": _albedo(rng)}


def _plastic(rng):
    return {"diffuse_reflectance": _albedo(rng, 0.1, 0.8), "int_ior": float(rng.uniform(1.4, 1.7))}


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


FAMILIES = {
    "diffuse": _diffuse,
    "plastic": _plastic,
    "roughplastic": _roughplastic,
    "roughconductor": _roughconductor,
    "principled": _principled,
    "grey": _grey,
}
KIND = {"grey": "diffuse"}  # families rendered by another family's BSDF


def sample_analytic(family: str, rng: np.random.Generator, name: str | None = None) -> MaterialSpec:
    if family not in FAMILIES:
        raise InputError("materials.families", f"unknown material family '{family}'"
                         f"{closest(family, FAMILIES)}; known: {', '.join(FAMILIES)}")
    return MaterialSpec(name=name or family, kind=KIND.get(family, family), params=FAMILIES[family](rng))


def lambertian(albedo=(0.8, 0.8, 0.8), name: str = "lambertian") -> MaterialSpec:
    return MaterialSpec(name=name, kind="diffuse", params={"reflectance": tuple(float(a) for a in albedo)})


def _rgb(v) -> dict:
    if isinstance(v, (int, float)):
        v = (float(v),) * 3
    return {"type": "rgb", "value": [float(x) for x in v]}


def to_mitsuba(m: MaterialSpec) -> dict:
    """Mitsuba `load_dict` description of a material (needs a variant set)."""
    p = dict(m.params)
    if m.kind == "merl":
        from msps_render.brdf.plugin import merl_bsdf_dict

        return merl_bsdf_dict(m)
    if m.kind == "diffuse":
        return {"type": "diffuse", "reflectance": _rgb(p.get("reflectance", 0.5))}
    if m.kind == "plastic":
        return {"type": "plastic", "diffuse_reflectance": _rgb(p.get("diffuse_reflectance", 0.5)),
                "int_ior": float(p.get("int_ior", 1.49)), "nonlinear": False}
    if m.kind == "roughplastic":
        return {"type": "roughplastic", "distribution": "ggx",
                "diffuse_reflectance": _rgb(p.get("diffuse_reflectance", 0.5)),
                "alpha": float(p.get("alpha", 0.1)), "int_ior": float(p.get("int_ior", 1.49))}
    if m.kind == "roughconductor":
        return {"type": "roughconductor", "distribution": "ggx",
                "material": str(p.get("material", "Al")), "alpha": float(p.get("alpha", 0.1))}
    if m.kind == "principled":
        return {"type": "principled", "base_color": _rgb(p.get("base_color", 0.5)),
                "roughness": float(p.get("roughness", 0.5)), "metallic": float(p.get("metallic", 0.0)),
                "specular": float(p.get("specular", 0.5))}
    raise InputError("material", f"unknown material kind '{m.kind}'")
