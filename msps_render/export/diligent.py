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

Any rig (format-2 shards, `[scene.rig]`; `write_rig_frame`): N lights of a sequential capture
(one image per light; shots of several lights are refused, `export.anyrig`), the same folder with

    001.png ... NNN.png                      16-bit linear, image k = the camera's shot of light k
                                             (%03d, as DiLiGenT); RGB camera: RGB, mono camera: grey
    light_directions.txt                     the NOMINAL rig (what a calibration gives a user)
    light_directions_true.txt                what was rendered (differs with scene.rig.errors)
    light_intensities.txt                    row k: channel m's reading of light k on a white surface
                                             at the object centre (the rig's C[m, k], nominal) times
                                             png_scale, R G B (mono: the value three times);
                                             light_intensities_true.txt the rendered C
    light_positions.txt, _true.txt           near (point) lights only: x y z per light, camera frame,
                                             scene units (nominal: the true distance along the nominal
                                             direction; directional lights of a mixed rig: nan)
    points.npy                               near lights only: (H, W, 3) float32 surface point of each
                                             pixel centre, camera frame (0 off the object), so that
                                             near-field methods get each pixel's own light vectors
                                             and fall-off: l_k(x) = (p_k - x) / |p_k - x|
    light_anisotropy.txt                     near LEDs with scene.rig.anisotropy_mu: mu per light, the
                                             LED's radiant intensity cos^mu of the angle off its axis
                                             (the axis points at the object centre)

and mask.png, Normal_gt.png/.mat, normal.txt as above.  The images are the stored shots times one
exposure per frame, the intensities the channel-by-light readings times the same exposure, so
image / intensity is again the image under a unit white light (near lights: with their fall-off
across the object; an environment light, if the dataset has one, is in every image as ambient
light).  No environment.png (rig shards keep no environment-only image).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from msps_render.atomic import save_array
from msps_render.export.formats import ExportFormat, register
from msps_render.io.png16 import encode_normal, to_unorm, write_png
from msps_render.export.source import ExportFrame

NAMES = ("001.png", "002.png", "003.png")


def fmt_rows(a: np.ndarray) -> str:
    """One row per line, 9 significant digits (round-trips float32 exactly)."""
    return "".join(" ".join(f"{v:.9g}" for v in row) + "\n" for row in np.asarray(a, np.float64))


def write_frame(ef: ExportFrame, root: Path) -> dict:
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
    write_ground_truth(ef, d)
    return {"dir": d.name, "png_scale": s, **write_environment(ef, d, np.uint16)}


def write_ground_truth(ef, d: Path) -> None:
    """mask.png, Normal_gt.png, Normal_gt.mat (key Normal_gt), normal.txt of a frame (any rig)."""
    from scipy.io import savemat

    write_png(d / "mask.png", (ef.mask * 255).astype(np.uint8))
    n = np.where(ef.mask[..., None], ef.normal, 0.0).astype(np.float64)
    write_png(d / "Normal_gt.png", encode_normal(n, ef.mask))
    savemat(d / "Normal_gt.mat", {"Normal_gt": n}, do_compression=True)
    (d / "normal.txt").write_text(fmt_rows(n.reshape(-1, 3)))


def image_names(n: int) -> list[str]:
    """DiLiGenT's image names: 001.png ... (%03d)."""
    return [f"{k + 1:03d}.png" for k in range(n)]


def write_rig_frame(ef, root: Path) -> dict:
    """One frame of a rig dataset (`export.anyrig.RigExportFrame`, one image per light): see the docstring."""
    d = root / f"{ef.id}PNG"
    d.mkdir()
    imgs = ef.images  # (N, H, W, M)
    top = float(imgs.max()) if imgs.size else 0.0
    s = 1.0 / top if top > 0 else 1.0
    names = image_names(ef.n_lights)
    for name, img in zip(names, imgs):
        write_png(d / name, to_unorm(img[..., 0] * s if img.shape[-1] == 1 else img * s))
    (d / "filenames.txt").write_text("".join(n + "\n" for n in names))
    write_rig_lights(ef, d, s)
    write_ground_truth(ef, d)
    return {"dir": d.name, "png_scale": s, "images": names}


def write_rig_lights(ef, d: Path, s: float, intensities: bool = True) -> None:
    """light_directions(_true).txt, light_intensities(_true).txt (channel-by-light readings times `s`) and,
    for near lights, light_positions(_true).txt and points.npy."""
    from msps_render.export.anyrig import intensity_rows, light_positions

    (d / "light_directions.txt").write_text(fmt_rows(ef.nominal.light_dirs))
    (d / "light_directions_true.txt").write_text(fmt_rows(ef.rig.light_dirs))
    if intensities:
        (d / "light_intensities.txt").write_text(fmt_rows(intensity_rows(ef.nominal.crosstalk, s)))
        (d / "light_intensities_true.txt").write_text(fmt_rows(intensity_rows(ef.rig.crosstalk, s)))
    if ef.near:
        (d / "light_positions.txt").write_text(fmt_rows(light_positions(ef.nominal)))
        (d / "light_positions_true.txt").write_text(fmt_rows(light_positions(ef.rig)))
        save_array(d / "points.npy", np.asarray(ef.points, np.float32))  # a full disk: one line
        if ef.rig.anisotropy is not None:  # LED radiant intensity cos^mu about its axis (toward the object centre)
            (d / "light_anisotropy.txt").write_text("".join(f"{float(mu):.9g}\n" for mu in ef.rig.anisotropy))


def write_environment(ef: ExportFrame, d: Path, dtype) -> dict:
    """environment.png on its own exposure (the sky it shows around the object outshines the lights)."""
    if ef.env_image is None:
        return {}
    top = float(ef.env_image.max())
    s = 1.0 / top if top > 0 else 1.0
    write_png(d / "environment.png", to_unorm(ef.env_image * s, dtype))
    return {"environment": "environment.png", "env_png_scale": s}


def finish(root: Path, infos: list[dict]) -> None:
    names = infos[0]["images"] if infos and "images" in infos[0] else NAMES  # a rig dataset: its N lights
    (root / "objects.txt").write_text("".join(i["dir"] + "\n" for i in infos))
    (root / "filenames.txt").write_text("".join(n + "\n" for n in names))


register(ExportFormat("diligent", "DiLiGenT pmsData: per-light 16-bit PNGs, light_directions.txt, "
                                  "light_intensities.txt, mask.png, Normal_gt.png/.mat, normal.txt",
                      write_frame, finish, per_light=True,
                      light_files="<id>PNG/001.png ... 003.png (light k on png_scale), <id>PNG/environment.png "
                                  "(frames with an environment light, on env_png_scale; not in filenames.txt)",
                      write_rig_frame=write_rig_frame,
                      rig_light_files="<id>PNG/001.png ... NNN.png (the shot of light k, on png_scale; grey PNGs "
                                      "for a mono camera)"),
         aliases=("pmsdata",))
