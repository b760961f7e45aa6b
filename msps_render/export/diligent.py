"""DiLiGenT `pmsData` layout (Shi et al., CVPR 2016), one object folder per frame:

    OUT/objects.txt, OUT/filenames.txt       folder names; image names (as DiLiGenT loaders read them)
    OUT/<frame-id>PNG/001.png 002.png 003.png  16-bit linear RGB, one per light (no environment light)
    OUT/<frame-id>PNG/environment.png        16-bit, the environment light alone (frames with one; not
                                             in filenames.txt; its own exposure `env_png_scale`)
    OUT/<frame-id>PNG/filenames.txt          the image names
    OUT/<frame-id>PNG/light_directions.txt   row k: x y z toward light k (camera frame, as DiLiGenT)
    OUT/<frame-id>PNG/light_intensities.txt  row k: R G B of light k on the images' scale
    OUT/<frame-id>PNG/mask.png               8-bit, 255 on the object
    OUT/<frame-id>PNG/Normal_gt.png          16-bit (n+1)/2; Normal_gt.mat (key Normal_gt, HxWx3);
                                             normal.txt (H*W rows "x y z", row-major)

Images are the per-light radiance times one exposure per frame (`png_scale`,
brightest value -> 65535), and the intensities are `light_rgb * png_scale`,
so image / intensity is the image under a unit white light, as in DiLiGenT.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from msps_render.export.formats import ExportFormat, register
from msps_render.io.png16 import encode_normal, to_unorm, write_png
from msps_render.export.source import ExportFrame

NAMES = ("001.png", "002.png", "003.png")


def fmt_rows(a: np.ndarray) -> str:
    """One row per line, 9 significant digits (round-trips float32 exactly)."""
    return "".join(" ".join(f"{v:.9g}" for v in row) + "\n" for row in np.asarray(a, np.float64))


def write_frame(ef: ExportFrame, root: Path) -> dict:
    from scipy.io import savemat

    d = root / f"{ef.id}PNG"
    d.mkdir()
    per = ef.per_light
    top = float(per.max()) if per.size else 0.0
    s = 1.0 / top if top > 0 else 1.0
    for name, img in zip(NAMES, per):
        write_png(d / name, to_unorm(img * s))
    (d / "filenames.txt").write_text("".join(n + "\n" for n in NAMES))
    (d / "light_directions.txt").write_text(fmt_rows(ef.light_dirs))
    (d / "light_intensities.txt").write_text(fmt_rows(np.asarray(ef.light_rgb) * s))
    write_png(d / "mask.png", (ef.mask * 255).astype(np.uint8))
    n = np.where(ef.mask[..., None], ef.normal, 0.0).astype(np.float64)
    write_png(d / "Normal_gt.png", encode_normal(n, ef.mask))
    savemat(d / "Normal_gt.mat", {"Normal_gt": n}, do_compression=True)
    (d / "normal.txt").write_text(fmt_rows(n.reshape(-1, 3)))
    return {"dir": d.name, "png_scale": s, **write_environment(ef, d, np.uint16)}


def write_environment(ef: ExportFrame, d: Path, dtype) -> dict:
    """environment.png on its own exposure (the sky it shows around the object outshines the lights)."""
    if ef.env_image is None:
        return {}
    top = float(ef.env_image.max())
    s = 1.0 / top if top > 0 else 1.0
    write_png(d / "environment.png", to_unorm(ef.env_image * s, dtype))
    return {"environment": "environment.png", "env_png_scale": s}


def finish(root: Path, infos: list[dict]) -> None:
    (root / "objects.txt").write_text("".join(i["dir"] + "\n" for i in infos))
    (root / "filenames.txt").write_text("".join(n + "\n" for n in NAMES))


register(ExportFormat("diligent", "DiLiGenT pmsData: per-light 16-bit PNGs, light_directions.txt, "
                                  "light_intensities.txt, mask.png, Normal_gt.png/.mat, normal.txt",
                      write_frame, finish, per_light=True,
                      light_files="<id>PNG/001.png ... 003.png (light k on png_scale), <id>PNG/environment.png "
                                  "(frames with an environment light, on env_png_scale; not in filenames.txt)"),
         aliases=("pmsdata",))
