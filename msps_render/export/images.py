"""Per-frame images: `png16` (16-bit linear PNG) and `exr` (float EXR), each with normal map, mask and
the frame's calibration JSON (the schema `msps predict --calibration` reads).

    OUT/<frame-id>/image.png | image.exr     linear radiance (PNG: value / 65535 / png_scale)
    OUT/<frame-id>/normal.png | normal.exr   (n+1)/2 * 65535 | camera-frame float normals
    OUT/<frame-id>/mask.png                  8-bit, 255 on the object
    OUT/<frame-id>/calibration.json          light_dirs, crosstalk (+ info: object, png_scale, ...)
    OUT/<frame-id>/light0.png ... light2.png | .exr   light k alone, when per-light images are at hand
    OUT/<frame-id>/environment.png | .exr    the environment light alone (frames with one)

Per-light and environment PNGs share the image's exposure, so (in radiance) image =
light0 + light1 + light2 + environment: one exposure, nothing clips.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from msps_render.calibration import write_calibration
from msps_render.export.formats import ExportFormat, register
from msps_render.io.png16 import encode_normal, to_unorm, write_png
from msps_render.export.source import ExportFrame


def png_scale(img: np.ndarray) -> float:
    """Exposure that maps the frame's brightest value to 1 (nothing clips)."""
    top = float(np.max(img)) if img.size else 0.0
    return 1.0 / top if top > 0 else 1.0


def _common(ef: ExportFrame, d: Path, extra: dict) -> None:
    write_png(d / "mask.png", (ef.mask * 255).astype(np.uint8))
    info = {"object": ef.object, "materials": ef.materials, "condition": ef.condition, "shard": ef.shard,
            "frame": ef.index, "light_rgb": np.asarray(ef.light_rgb).tolist(), **extra}
    write_calibration(d / "calibration.json", ef.light_dirs, ef.crosstalk, source=f"msps export ({ef.shard})",
                      info=info)


def components(ef: ExportFrame) -> dict[str, np.ndarray]:
    """{file stem: image} of the per-light images and the environment image (empty without them)."""
    if ef.per_light is None:
        return {}
    out = {f"light{k}": img for k, img in enumerate(ef.per_light)}
    if ef.env_image is not None:
        out["environment"] = ef.env_image
    return out


def write_png16(ef: ExportFrame, root: Path) -> dict:
    d = root / ef.id
    d.mkdir()
    parts = components(ef)
    s = png_scale(np.stack([ef.image, *parts.values()]))  # float16 parts may exceed the image by a rounding
    write_png(d / "image.png", to_unorm(ef.image * s))
    for stem, img in parts.items():
        write_png(d / f"{stem}.png", to_unorm(img * s))
    write_png(d / "normal.png", encode_normal(ef.normal, ef.mask))
    _common(ef, d, {"png_scale": s})
    return {"dir": ef.id, "png_scale": s, "light_images": [f"{stem}.png" for stem in parts]}


def write_exr_frame(ef: ExportFrame, root: Path) -> dict:
    from msps_render.io.images import write_exr

    d = root / ef.id
    d.mkdir()
    write_exr(d / "image.exr", ef.image)
    parts = components(ef)
    for stem, img in parts.items():
        write_exr(d / f"{stem}.exr", img)
    write_exr(d / "normal.exr", np.where(ef.mask[..., None], ef.normal, 0.0))
    _common(ef, d, {})
    return {"dir": ef.id, "light_images": [f"{stem}.exr" for stem in parts]}


register(ExportFormat("png16", "per frame: 16-bit linear PNG image, 16-bit normal map, mask, calibration.json "
                               "(+ light0-2.png, environment.png when per-light images are at hand)",
                      write_png16, light_files="<id>/light0.png ... light2.png, <id>/environment.png (frames "
                                               "with an environment light), on the image's png_scale"))
register(ExportFormat("exr", "per frame: float EXR image and normal map, mask PNG, calibration.json "
                             "(+ light0-2.exr, environment.exr when per-light images are at hand)",
                      write_exr_frame, light_files="<id>/light0.exr ... light2.exr, <id>/environment.exr "
                                                   "(frames with an environment light)"))
