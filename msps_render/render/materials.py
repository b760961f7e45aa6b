"""MaterialSpec -> Mitsuba BSDF dict, one translator per material kind (`BSDFS`).

Adding a BSDF kind: one function here registered in `BSDFS`; the kind names
of `MaterialSpec` are these keys (`scene.spec.MATERIAL_KINDS` is checked
against them in tests).  Measured tables (`merl`) go to the `merl` plugin.
"""
from __future__ import annotations

from typing import Callable

from msps_render.errors import InputError, closest
from msps_render.render.merl_bsdf import merl_bsdf_dict
from msps_render.render.textures import WEIGHT, attribute, textured_bsdf
from msps_render.scene.spec import MaterialSpec


def _rgb(v) -> dict:
    if isinstance(v, (int, float)):
        v = (float(v),) * 3
    return {"type": "rgb", "value": [float(x) for x in v]}


def _diffuse(p: dict) -> dict:
    return {"type": "diffuse", "reflectance": _rgb(p.get("reflectance", 0.5))}


def _plastic(p: dict) -> dict:
    return {"type": "plastic", "diffuse_reflectance": _rgb(p.get("diffuse_reflectance", 0.5)),
            "int_ior": float(p.get("int_ior", 1.49)), "nonlinear": False}


def _roughplastic(p: dict) -> dict:
    return {"type": "roughplastic", "distribution": "ggx",
            "diffuse_reflectance": _rgb(p.get("diffuse_reflectance", 0.5)),
            "alpha": float(p.get("alpha", 0.1)), "int_ior": float(p.get("int_ior", 1.49))}


def _roughconductor(p: dict) -> dict:
    return {"type": "roughconductor", "distribution": "ggx",
            "material": str(p.get("material", "Al")), "alpha": float(p.get("alpha", 0.1))}


def _principled(p: dict) -> dict:
    # `metallic` as a texture, never a bare float: Mitsuba's principled BSDF leaves out its
    # metallic code when given the float 0, so metallic and non-metallic materials compiled
    # different kernels; as a texture both share one (images equal to float rounding).
    return {"type": "principled", "base_color": _rgb(p.get("base_color", 0.5)),
            "roughness": float(p.get("roughness", 0.5)),
            "metallic": {"type": "uniform", "value": float(p.get("metallic", 0.0))},
            "specular": float(p.get("specular", 0.5))}


# Parameters a Mitsuba plugin bakes into the render kernel as literals (not opaque): two BSDFs that differ
# in one run different code (the batched launch keeps such BSDFs apart, `render.batch._slot_kind`).
BAKED: dict[str, tuple[str, ...]] = {"plastic": ("int_ior",)}


def baked_literals(m: MaterialSpec) -> tuple:
    """The values of `m`'s parameters its plugin bakes into the kernel (`BAKED`), as `to_mitsuba` passes them."""
    d = BSDFS[m.kind](dict(m.params)) if m.kind in BAKED else {}
    return tuple(d[k] for k in BAKED.get(m.kind, ()))


BSDFS: dict[str, Callable[[dict], dict]] = {
    "diffuse": _diffuse,
    "plastic": _plastic,
    "roughplastic": _roughplastic,
    "roughconductor": _roughconductor,
    "principled": _principled,
}


def to_mitsuba(m: MaterialSpec) -> dict:
    """Mitsuba `load_dict` description of a material (needs a variant set).

    A textured material reads its albedo/roughness from the mesh attributes
    (`render.textures`); a measured material with `blend` becomes Mitsuba's
    `blendbsdf` of the two, weighted per texel by the texture."""
    if m.kind == "merl":
        d = merl_bsdf_dict(m)
        if m.blend is not None:
            d = {"type": "blendbsdf", "weight": attribute(WEIGHT, 1), "bsdf_0": d, "bsdf_1": to_mitsuba(m.blend)}
        return d
    translate = BSDFS.get(m.kind)
    if translate is None:
        raise InputError("material", f"unknown material kind '{m.kind}'{closest(m.kind, BSDFS)}")
    return textured_bsdf(m, translate(dict(m.params)))
