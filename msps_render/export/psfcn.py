"""PS-FCN's synthetic-data layout (Chen et al., ECCV 2018; `datasets/PS_Synth_Dataset.py`), one
"shape" per frame and one "material" folder per shape:

    OUT/train_mtrl.txt                          "<shape>/<mtrl>" per line (rename for other splits)
    OUT/Images/<shape>/<shape>_normal.png       8-bit (n+1)/2 normal map, n = 0 outside (PS-FCN's mask)
    OUT/Images/<shape>/mask.png                 8-bit, 255 on the object (extra)
    OUT/Images/<shape>/<mtrl>/<shape>_<mtrl>.txt  "l_000.png x y z" per light
    OUT/Images/<shape>/<mtrl>/l_000.png ...     8-bit linear RGB, one per light, divided by the light's
                                                RGB (PS-FCN's data have unit white lights)
    OUT/Images/<shape>/<mtrl>/light_directions.txt, light_intensities.txt  (extra, DiLiGenT-style)
    OUT/Images/<shape>/<mtrl>/environment.png   8-bit, the environment light alone (frames with one; not
                                                in the light list; not white-balanced, own `env_png_scale`)

Image k is per_light[k] / light_rgb[k] (per channel) times one exposure per
frame (`png_scale`, brightest -> 255); light_intensities.txt holds png_scale in
every channel, so image / intensity is again the image under a unit white light.

Any rig (format-2 shards, `[scene.rig]`; `write_rig_frame`): N lights of a sequential capture (one
image per light; shots of several lights are refused, `export.anyrig`), the same layout with

    l_000.png ... l_<N-1>.png                   8-bit, image k = the camera's shot of light k divided
                                                per channel by its reading C[:, k] (the nominal rig's
                                                channel-by-light matrix), times png_scale; a mono
                                                camera's grey value in all three channels (PS-FCN reads
                                                three channels per image)
    <shape>_<mtrl>.txt                          "l_000.png x y z" per light: the NOMINAL directions
    light_directions_true.txt, light_intensities.txt (png_scale, N rows), and for near (point) lights
    light_positions.txt / _true.txt, points.npy (and light_anisotropy.txt), as the diligent layout
    writes them.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from msps_render.export.formats import ExportFormat, register
from msps_render.export.diligent import fmt_rows, write_environment
from msps_render.io.png16 import encode_normal, to_unorm, write_png
from msps_render.export.source import ExportFrame, safe_name

NAMES = ("l_000.png", "l_001.png", "l_002.png")


def white_balanced(per_light: np.ndarray, light_rgb: np.ndarray) -> np.ndarray:
    """per_light[k] / light_rgb[k] per channel (0 where the light has no such channel)."""
    rgb = np.asarray(light_rgb, np.float64)[:, None, None, :]
    return np.where(rgb > 0, per_light / np.where(rgb > 0, rgb, 1.0), 0.0)


def write_frame(ef: ExportFrame, root: Path) -> dict:
    shape, mtrl = ef.id, safe_name(ef.materials.replace(";", "+"))
    sd = root / "Images" / shape
    md = sd / mtrl
    md.mkdir(parents=True)
    wb = white_balanced(ef.per_light, ef.light_rgb)
    top = float(wb.max()) if wb.size else 0.0
    s = 1.0 / top if top > 0 else 1.0
    for name, img in zip(NAMES, wb):
        write_png(md / name, to_unorm(img * s, np.uint8))
    L = np.asarray(ef.light_dirs, np.float64)
    (md / f"{shape}_{mtrl}.txt").write_text("".join(f"{n} " + " ".join(f"{v:.9g}" for v in l) + "\n"
                                                    for n, l in zip(NAMES, L)))
    (md / "light_directions.txt").write_text(fmt_rows(L))
    (md / "light_intensities.txt").write_text(fmt_rows(np.full((len(NAMES), 3), s)))
    write_png(sd / f"{shape}_normal.png", encode_normal(ef.normal, ef.mask, np.uint8))
    write_png(sd / "mask.png", (ef.mask * 255).astype(np.uint8))
    return {"dir": f"Images/{shape}/{mtrl}", "png_scale": s, **write_environment(ef, md, np.uint8)}


def image_names(n: int) -> list[str]:
    return [f"l_{k:03d}.png" for k in range(n)]


def write_rig_frame(ef, root: Path) -> dict:
    """One frame of a rig dataset (`export.anyrig.RigExportFrame`, one image per light): see the docstring."""
    from msps_render.export.diligent import write_rig_lights

    shape, mtrl = ef.id, safe_name(ef.materials.replace(";", "+"))
    sd = root / "Images" / shape
    md = sd / mtrl
    md.mkdir(parents=True)
    wb = white_balanced(ef.images, np.asarray(ef.nominal.crosstalk, np.float64).T)  # (N, H, W, M)
    if wb.shape[-1] == 1:
        wb = np.repeat(wb, 3, axis=-1)
    top = float(wb.max()) if wb.size else 0.0
    s = 1.0 / top if top > 0 else 1.0
    names = image_names(ef.n_lights)
    for name, img in zip(names, wb):
        write_png(md / name, to_unorm(img * s, np.uint8))
    L = np.asarray(ef.nominal.light_dirs, np.float64)
    (md / f"{shape}_{mtrl}.txt").write_text("".join(f"{n} " + " ".join(f"{v:.9g}" for v in l) + "\n"
                                                    for n, l in zip(names, L)))
    write_rig_lights(ef, md, s, intensities=False)
    (md / "light_intensities.txt").write_text(fmt_rows(np.full((len(names), 3), s)))
    write_png(sd / f"{shape}_normal.png", encode_normal(ef.normal, ef.mask, np.uint8))
    write_png(sd / "mask.png", (ef.mask * 255).astype(np.uint8))
    return {"dir": f"Images/{shape}/{mtrl}", "png_scale": s, "images": names}


def finish(root: Path, infos: list[dict]) -> None:
    (root / "train_mtrl.txt").write_text("".join(i["dir"].split("/", 1)[1] + "\n" for i in infos))


register(ExportFormat("psfcn", "PS-FCN synthetic layout: Images/<shape>/<mtrl>/l_*.png + light list, "
                               "<shape>_normal.png, train_mtrl.txt", write_frame, finish, per_light=True,
                      light_files="Images/<id>/<mtrl>/l_000.png ... l_002.png (light k / its RGB, on png_scale), "
                                  "Images/<id>/<mtrl>/environment.png (frames with an environment light, on "
                                  "env_png_scale; not in the light list)",
                      write_rig_frame=write_rig_frame,
                      rig_light_files="Images/<id>/<mtrl>/l_000.png ... (the shot of light k / its nominal "
                                      "reading, on png_scale; 8-bit RGB, a mono camera's grey in all three)"))
