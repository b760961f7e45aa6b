"""Albedo augmentation: a seeded colour field multiplied into training patches (`train.albedo_aug`).

Why: the error that is left on coloured objects is the albedo colour varying across the surface
(docs/history.md, stage 9's chroma bound), and a rendered corpus holds only as many colour
layouts as it has frames.  In RGB mode channel c of a pixel records

    x_c = rho_c * (sum_k M_ck s_k(n) + environment_c(n)),

linear in the albedo's channel c, so multiplying channel c by a field f_c(pixel) gives exactly the
image of the same shape, lights and rig with its albedo's channel c scaled by f_c (direct light;
interreflections, a few per cent of the signal in creases, see the colour of the first bounce
only).  The normals, mask and rig are unchanged.  For a measured material the scaled BRDF is a
spatially varying tint of it, still a valid (not brighter) material.  Spectral corpora are not
exact under it (a channel integrates a spectrum), so the augmentation is meant for RGB corpora.

The fields are the texture kinds of `scene/textures.py` (smooth, noise, patches, stripes,
decals) evaluated in the image plane, palettes drawn from the full albedo gamut
(`brdf.families.full_gamut_albedo`: channel ratios down to 0.1), feature sizes from the
texture defaults measured in object radii, at `PX_PER_RADIUS` pixels per radius (the size of a
training object in a 256 px frame)."""
from __future__ import annotations

import numpy as np

from msps_render.brdf.families import full_gamut_albedo
from msps_render.scene.textures import TextureConfig, TextureSpec, texture_fields

FIELD_KINDS = ("smooth", "noise", "patches", "stripes", "decals")
PX_PER_RADIUS = 100.0  # pixels per object radius: objects fill ~200 of the corpora's 256 px


def albedo_field(rng: np.random.Generator, height: int, width: int, kinds=FIELD_KINDS,
                 texture: TextureConfig = TextureConfig()) -> np.ndarray:
    """(3, H, W) float32 colour field in (0, 1): one texture of a kind from `kinds`, its palette
    (2-4 colours by default) from the full gamut, its feature size from `texture.scale_range`."""
    kind = str(rng.choice(list(kinds)))
    n_col = int(rng.integers(texture.n_colors[0], texture.n_colors[1] + 1))
    tex = TextureSpec(kind=kind, seed=int(rng.integers(2 ** 31)),
                      scale=float(rng.uniform(*texture.scale_range)),
                      colors=tuple(full_gamut_albedo(rng) for _ in range(n_col)))
    y, x = np.mgrid[:height, :width]
    off = rng.uniform(-1.0, 1.0, size=2)  # where in the field the patch sits
    pts = np.stack([x.ravel() / PX_PER_RADIUS + off[0], y.ravel() / PX_PER_RADIUS + off[1],
                    np.ones(x.size)], axis=1)  # the plane z = 1: decals are discs there
    rgb, _ = texture_fields(tex, pts, np.tile([0.0, 0.0, 1.0], (x.size, 1)))
    return rgb.reshape(height, width, 3).transpose(2, 0, 1)


def tint_images(images, fields):
    """The images (B, 3, H, W) with their albedo multiplied by `fields` (B, 3, H, W): x_c * f_c."""
    return images * fields


def albedo_batch(batch: dict, which, rng: np.random.Generator, kinds=FIELD_KINDS) -> dict:
    """A training batch whose patches `which` (B,) bool get a fresh colour field each; the
    normals, masks and rig stay (the shape and the lights are the same)."""
    import torch

    w = np.asarray(which, bool)
    if not w.any():
        return batch
    img = batch["image"]
    fields = np.ones(tuple(img.shape), np.float32)
    for i in np.flatnonzero(w):
        fields[i] = albedo_field(rng, img.shape[-2], img.shape[-1], kinds)
    out = dict(batch)
    out["image"] = tint_images(img, torch.from_numpy(fields).to(img.dtype))
    return out
