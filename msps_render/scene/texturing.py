"""Texture choice: `texture_materials(cfg, shape, materials, rng)` gives parts their textures.

Called by the scene sampler after every other draw, and only when
`materials.texture.fraction > 0`, so presets without textures draw exactly what
they drew before.  It takes one number from the scene's stream and draws the
rest from a child stream: the choices of one material never shift another's.
"""
from __future__ import annotations

import numpy as np

from msps_render.brdf.families import FAMILIES, MEASURED_KIND, _albedo
from msps_render.errors import InputError
from msps_render.scene.spec import MaterialSpec, ShapeSpec
from msps_render.scene.textures import TextureSpec, texture_images


def _palette(fam_name: str, own: tuple | None, n: int, gamut: str, rng: np.random.Generator) -> tuple:
    """n colours: the material's own albedo first, then draws of its family's distribution
    (grey stays grey: a grey texture varies brightness only)."""
    cols = [tuple(own)] if own is not None else []
    while len(cols) < n:
        if fam_name == "grey":
            g = float(rng.uniform(0.25, 0.85))
            cols.append((g, g, g))
        else:
            cols.append(_albedo(rng, 0.1, 0.85, gamut))
    return tuple(tuple(float(x) for x in c) for c in cols)


def _mapping(cfg, shape: ShapeSpec) -> str:
    from msps_render.scene.shapes import mesh_has_uv

    has_uv = shape.kind == "mesh" and mesh_has_uv(shape.path)
    if cfg.mapping == "uv" and not has_uv:
        raise InputError(shape.path or shape.name, "UV mapping asked of a mesh without UVs "
                                                   "(texture.mapping = 'uv'; use 'auto' or 'triplanar')")
    return "uv" if cfg.mapping == "uv" or (cfg.mapping == "auto" and has_uv) else "triplanar"


def _second_measured(mc, first: MaterialSpec, rng: np.random.Generator) -> MaterialSpec | None:
    """Another measured material of the same pool for a blend (None if the pool has one)."""
    from msps_render.scene.materials import sample_materials

    for _ in range(8):
        m = sample_materials(rng, 1, catalogue=mc.catalogue, merl_fraction=1.0, merl_dir=mc.merl_dir,
                             families=mc.families, measured=mc.measured, holdout=mc.holdout,
                             split_file=mc.split_file)[0]
        if m.kind == MEASURED_KIND and m.name != first.name:
            return m
    return None


def texture_materials(mc, shape: ShapeSpec, materials: tuple[MaterialSpec, ...],
                      rng: np.random.Generator) -> tuple[MaterialSpec, ...]:
    """Each material textured with probability `mc.texture.fraction` (the analytic sphere: none)."""
    tc = mc.texture
    sub = np.random.default_rng(int(rng.integers(2**63 - 1)))
    if shape.kind == "sphere":
        return materials
    images = texture_images(tc.folder) if "image" in tc.kinds else []
    out = []
    for m in materials:
        if sub.uniform() >= tc.fraction:
            out.append(m)
            continue
        kind = tc.kinds[int(sub.integers(len(tc.kinds)))]
        fam = FAMILIES.get(m.name)
        own = m.params.get(fam.albedo) if fam is not None and fam.albedo else None
        n_col = int(sub.integers(tc.n_colors[0], tc.n_colors[1] + 1))
        colors = _palette(m.name if fam is not None else "", own, n_col, mc.albedo, sub)
        rough = None
        if tc.roughness and fam is not None and fam.roughness:
            lo, hi = sorted(float(x) for x in sub.uniform(*fam.roughness_range, size=2))
            rough = (lo, hi)
        image, mapping = None, "triplanar"
        if kind == "image":
            image = str(images[int(sub.integers(len(images)))])
            mapping = _mapping(tc, shape)
        tex = TextureSpec(kind=kind, seed=int(sub.integers(2**31 - 1)),
                          scale=float(sub.uniform(*tc.scale_range)), colors=colors, image=image,
                          mapping=mapping, roughness=rough, max_edge=tc.max_edge)
        blend = None
        if m.kind == MEASURED_KIND:
            if not tc.blend:
                out.append(m)
                continue
            blend = _second_measured(mc, m, sub)
            if blend is None:
                out.append(m)
                continue
        elif fam is None or (fam.albedo is None and rough is None):
            out.append(m)  # nothing of this material that a texture could drive
            continue
        out.append(m.model_copy(update={"texture": tex, "blend": blend}))
    return tuple(out)
