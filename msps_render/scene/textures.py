"""Spatially varying appearance: seeded texture fields over an object's own surface (numpy only).

A `TextureSpec` is pure data (kind, seed, feature size, a colour palette, an
image path): the scene sampler draws it, the renderer turns it into per-vertex
attributes of the part's mesh (`render.scene_dict`), and the ground truth reads
the same attributes back, so the stored per-pixel albedo is exactly what the
renderer shaded.  Fields are functions of the point in the object's frame (the
shape before its random rotation), so a texture sticks to the object however
it is posed, and need no UVs; `image` textures use the mesh's UVs where it has
them (`mapping = "uv"`) or a triplanar projection.

`texture_fields(tex, points, normals, uv) -> (rgb, w)`: rgb in [0, 1] drives the
albedo of analytic families, the scalar w in [0, 1] drives roughness (within
`tex.roughness`) and the weight of the second material of a measured blend.

Kinds (`TEXTURE_KINDS`, one function each; `docs/appearance.md`):
smooth (low-frequency colour field), noise (fractal, high-frequency), patches
(Voronoi cells with sharp edges), stripes (bands), decals (discs on a base
colour), image (a file from a folder the user names).
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from msps_render.config_io import FrozenModel, StrictModel
from msps_render.errors import InputError, closest

RGB = tuple[float, float, float]
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".hdr", ".tif", ".tiff")


class TextureSpec(FrozenModel):
    """One part's texture: everything needed to evaluate it again, exactly."""

    kind: str
    seed: int
    scale: float = Field(0.3, gt=0, description="feature size, in units of the object radius")
    colors: tuple[RGB, ...] = ()
    image: str | None = None
    mapping: Literal["uv", "triplanar"] = "triplanar"
    roughness: tuple[float, float] | None = None  # (lo, hi) roughness/alpha driven by w
    max_edge: float = Field(0.03, gt=0, description="mesh edges longer than this are subdivided first")

    @model_validator(mode="after")
    def _check(self) -> "TextureSpec":
        if self.kind not in TEXTURE_KINDS:
            raise ValueError(unknown_texture(self.kind))
        if self.kind == "image" and not self.image:
            raise ValueError("texture kind 'image' needs an image path")
        if self.kind != "image" and len(self.colors) < 2:
            raise ValueError(f"texture kind '{self.kind}' needs at least 2 colours")
        return self


class TextureConfig(StrictModel):
    """`[scene.materials.texture]`: which parts get a texture, of which kinds."""

    fraction: float = Field(0.0, ge=0.0, le=1.0, description="share of material parts that get a texture "
                                                             "(0 = uniform materials, as before)")
    kinds: list[str] = Field(default_factory=lambda: ["smooth", "noise", "patches", "stripes", "decals"],
                             description="texture kinds to draw from: smooth, noise, patches, stripes, "
                                         "decals, image")
    folder: str | None = Field(None, description="kind 'image': folder of texture images (png/jpg/exr/hdr; "
                                                 "8-bit images are sRGB-decoded)")
    mapping: Literal["auto", "uv", "triplanar"] = Field(
        "auto", description="kind 'image': mesh UVs (uv; an error for a mesh without UVs), triplanar "
                            "projection, or UVs where the mesh has them else triplanar (auto)")
    scale_range: tuple[float, float] = Field((0.15, 0.6), description="feature size drawn per texture "
                                                                      "(units of the object radius)")
    n_colors: tuple[int, int] = Field((2, 4), description="palette size drawn per texture [lo, hi]")
    roughness: bool = Field(True, description="the texture also varies roughness where a family has one")
    blend: bool = Field(True, description="a textured measured part blends two measured materials per "
                                          "texel (Mitsuba blendbsdf, weight = the texture)")
    max_edge: float = Field(0.03, gt=0, description="textured meshes are subdivided until no edge is longer "
                                                    "(scene units; 0.03 ~ 3.7 px at 256 px over 2.1 units)")

    @field_validator("kinds")
    @classmethod
    def _known(cls, v):
        if not v:
            raise ValueError("texture.kinds must name at least one kind")
        for k in v:
            if k not in TEXTURE_KINDS:
                raise ValueError(unknown_texture(k))
        return v

    @field_validator("scale_range")
    @classmethod
    def _scale(cls, v):
        if not 0 < v[0] <= v[1]:
            raise ValueError(f"scale_range must satisfy 0 < lo <= hi, got {list(v)}")
        return v

    @field_validator("n_colors")
    @classmethod
    def _ncol(cls, v):
        if not 2 <= v[0] <= v[1] <= 16:
            raise ValueError(f"n_colors must satisfy 2 <= lo <= hi <= 16, got {list(v)}")
        return v

    @model_validator(mode="after")
    def _folder(self) -> "TextureConfig":
        if self.fraction > 0 and "image" in self.kinds and not self.folder:
            raise ValueError("texture kind 'image' needs texture.folder")
        return self


def unknown_texture(name: str) -> str:
    return f"unknown texture kind '{name}'{closest(name, TEXTURE_KINDS)}; known: {', '.join(TEXTURE_KINDS)}"


# ------------------------------------------------------------------ images
def texture_images(folder: str | Path) -> list[Path]:
    """The image files of a texture folder (sorted), or InputError naming the folder."""
    root = Path(folder)
    if not root.is_dir():
        raise InputError(root, "texture folder not found")
    files = sorted(p for p in root.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise InputError(root, f"texture folder holds no images ({', '.join(IMAGE_SUFFIXES)})")
    return files


def read_texture_image(path: str | Path) -> np.ndarray:
    """A texture image as linear float RGB (H, W, 3) in [0, 1]; InputError on anything else.

    8/16-bit files are sRGB-decoded (texture images are pictures, not radiance);
    EXR/HDR are taken as linear and clipped to [0, 1] (an albedo cannot exceed 1).
    """
    from msps_render.compose import read_photo

    p = Path(path)
    try:
        img = read_photo(p, linear=False)  # PNG forced to sRGB; JPG/TIFF are sRGB, EXR/HDR linear anyway
    except InputError:
        raise
    except Exception as e:  # decoders raise many types on garbage
        raise InputError(p, f"not a readable image ({type(e).__name__}: {str(e).splitlines()[0][:100]})") from None
    if img.ndim != 3 or img.shape[-1] != 3 or min(img.shape[:2]) < 2:
        raise InputError(p, f"texture must be an RGB or grey image of at least 2x2, got shape {img.shape}")
    if not np.isfinite(img).all():
        raise InputError(p, "texture has NaN/inf values")
    return np.clip(img, 0.0, 1.0).astype(np.float32)


# ------------------------------------------------------------------ fields
def _fourier(rng: np.random.Generator, p: np.ndarray, freq: float, n: int = 6) -> np.ndarray:
    """A smooth random field ~N(0, 1) at points p: n random plane waves of wavenumber ~freq."""
    w = rng.normal(size=(n, 3)) * freq
    phi = rng.uniform(0, 2 * np.pi, size=n)
    return np.sin(p @ w.T + phi).sum(axis=1) * np.sqrt(2.0 / n)


def _palette(colors: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Colours at t in [0, 1], piecewise linear through the palette."""
    x = np.clip(t, 0, 1) * (len(colors) - 1)
    i = np.minimum(np.floor(x).astype(int), len(colors) - 2)
    f = (x - i)[:, None]
    return colors[i] * (1 - f) + colors[i + 1] * f


def _smooth(tex, rng, p, n, uv):
    t = 0.5 + 0.5 * np.tanh(0.9 * _fourier(rng, p, 1.0 / tex.scale))
    return _palette(np.asarray(tex.colors), t), t


def _noise(tex, rng, p, n, uv):
    f = sum(_fourier(rng, p, (2.0 ** o) / tex.scale) * 0.55 ** o for o in range(4))
    t = 0.5 + 0.5 * np.tanh(1.2 * f)
    return _palette(np.asarray(tex.colors), t), t


def _patches(tex, rng, p, n, uv):
    n_cells = int(np.clip(round((2.0 / tex.scale) ** 2), 4, 64))
    seeds = rng.uniform(-1.1, 1.1, size=(n_cells, 3))
    which = rng.integers(len(tex.colors), size=n_cells)
    weight = rng.uniform(0, 1, size=n_cells)
    cell = np.empty(len(p), dtype=np.int64)
    for s in range(0, len(p), 65536):  # chunks bound the (points x cells) distance table
        d = ((p[s:s + 65536, None, :] - seeds[None]) ** 2).sum(-1)
        cell[s:s + 65536] = d.argmin(1)
    return np.asarray(tex.colors)[which[cell]], weight[cell]


def _stripes(tex, rng, p, n, uv):
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    warp = 0.25 * tex.scale * _fourier(rng, p, 0.5 / tex.scale, 3)
    x = (p @ d + warp) / tex.scale + rng.uniform(0, 1)
    band = np.floor(x).astype(np.int64) % len(tex.colors)
    return np.asarray(tex.colors)[band], band / max(len(tex.colors) - 1, 1)


def _decals(tex, rng, p, n, uv):
    cols = np.asarray(tex.colors)
    rgb = np.repeat(cols[:1], len(p), axis=0)
    w = np.zeros(len(p))
    k = int(np.clip(round(1.5 / tex.scale), 2, 12))
    centres = rng.normal(size=(k, 3))
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    radii = tex.scale * rng.uniform(0.4, 1.0, size=k)
    for j in range(k):
        inside = np.linalg.norm(p / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-9)
                                - centres[j], axis=1) < radii[j]
        rgb[inside] = cols[1 + j % (len(cols) - 1)]
        w[inside] = 1.0
    return rgb, w


def _lookup(img: np.ndarray, st: np.ndarray) -> np.ndarray:
    """Bilinear lookup with wrap-around at texture coordinates st (N, 2) (s right, t up)."""
    H, W = img.shape[:2]
    x = (st[:, 0] % 1.0) * W - 0.5
    y = (1.0 - st[:, 1] % 1.0) * H - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0, x1, y1 = x0 % W, y0 % H, (x0 + 1) % W, (y0 + 1) % H
    return ((img[y0, x0] * (1 - fx) + img[y0, x1] * fx) * (1 - fy)
            + (img[y1, x0] * (1 - fx) + img[y1, x1] * fx) * fy)


def _image(tex, rng, p, n, uv):
    img = read_texture_image(tex.image)
    if tex.mapping == "uv":
        if uv is None:
            raise InputError(tex.image, "UV mapping asked for a mesh without UVs")
        rgb = _lookup(img, uv)
    else:  # triplanar: three axis projections blended by |normal|^4
        b = np.abs(n) ** 4
        b /= np.maximum(b.sum(1, keepdims=True), 1e-12)
        off = rng.uniform(0, 1, size=2)
        s = 1.0 / (2.0 * tex.scale)
        rgb = sum(_lookup(img, p[:, ax] * s + off) * b[:, [k]]
                  for k, ax in enumerate(([1, 2], [0, 2], [0, 1])))
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722])
    return rgb, np.clip(lum / max(float(lum.max()), 1e-6), 0, 1)


FIELDS: dict[str, Callable] = {"smooth": _smooth, "noise": _noise, "patches": _patches,
                               "stripes": _stripes, "decals": _decals, "image": _image}
TEXTURE_KINDS = tuple(FIELDS)


def texture_fields(tex: TextureSpec, points: np.ndarray, normals: np.ndarray | None = None,
                   uv: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(rgb (N, 3) in [0, 1], w (N,) in [0, 1]) of `tex` at object-frame points (N, 3).

    Deterministic: a function of (tex, points) only (the field's random numbers come
    from `tex.seed`), so ground truth and re-renders evaluate the same values.
    """
    p = np.asarray(points, dtype=np.float64)
    nn = np.zeros_like(p) if normals is None else np.asarray(normals, dtype=np.float64)
    rgb, w = FIELDS[tex.kind](tex, np.random.default_rng(tex.seed), p, nn, uv)
    return np.clip(rgb, 0.0, 1.0).astype(np.float32), np.clip(w, 0.0, 1.0).astype(np.float32)
