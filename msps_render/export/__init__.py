"""`msps export`: a dataset's whole frames in the layouts other photometric-stereo code reads.

One module per format, each registering an `ExportFormat` in `FORMATS`
(`formats.py`; add a format: one module, and its name in the import below).  A rig dataset
(format-2 shards, `[scene.rig]`) goes through `anyrig.export_rig_dataset` and the formats'
`write_rig_frame` (diligent and psfcn: one image per light of a sequential capture).
`export_dataset` validates everything
first, writes into a hidden temporary directory beside `--out` and renames it
into place at the end, so a failure or an interrupt leaves nothing behind.
Layouts and conventions: docs/recipes.md "Export".
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

from msps_render.dataset.manifest import SHARD_DIR, read_manifest
from msps_render.errors import InputError
from msps_render.export import diligent, images, psfcn  # noqa: F401  (each registers its format)
from msps_render.export.anyrig import export_rig_dataset, is_rig_dataset
from msps_render.export.formats import FORMATS, ExportFormat, get_format, register, write_frames  # noqa: F401
from msps_render.export.source import (PER_LIGHT_CONTENTS, PER_LIGHT_SOURCES, ExportFrame, check_has_frames,
                                       dataset_variant, iter_export_frames, sensor_model, stored_per_light,
                                       write_json)
from msps_render.io.staging import check_new_out, staged_dir


def export_dataset(root: str | Path, fmt: str, out: str | Path, rerender: bool = False,
                   progress: Callable[[int, ExportFrame], None] | None = None) -> dict:
    """Export every whole frame of dataset `root` as `fmt` into the new directory `out`; returns the index.

    Per-light images come from the shards when stored (`store_per_light`), else from `rerender`;
    png16/exr write them too when they are at hand, the per-light layouts cannot do without."""
    root, out = Path(root), Path(out)
    f = get_format(fmt)
    check_has_frames(root)  # also: not a dataset, incomplete, unreadable shard
    if is_rig_dataset(root):
        return export_rig_dataset(root, f, out, rerender=rerender, progress=progress)
    missing = stored_per_light(root)
    if f.per_light and missing is not None and not rerender:
        raise InputError(missing, f"shard stores no per-light images, which the {f.name} layout needs; add "
                                  "--rerender to re-render them from the scenes stored in the shards (needs "
                                  "Mitsuba), or render with dataset.storage.store_per_light = true")
    lights = f.per_light or rerender or missing is None
    check_new_out(out)
    with staged_dir(out) as stage:
        variant = dataset_variant(root) if rerender else None
        infos = write_frames(iter_export_frames(root, per_light=lights, variant=variant, rerender=rerender),
                             f.write_frame, stage, progress)
        if f.finish:
            f.finish(stage, infos)
        m = read_manifest(root) or {}
        per = None
        if lights:
            per = {"source": PER_LIGHT_SOURCES["re-rendered" if rerender else "stored"],
                   "contents": PER_LIGHT_CONTENTS, "files": f.light_files}
        sensor = sensor_model(root)
        if per is not None and sensor is not None:  # say why sum_k image_k + environment != image
            per["deviation"] = SENSOR_DEVIATION
        index = {"format": f.name, "dataset": str(root.resolve()), "config_hash": m.get("config_hash"),
                 "n_frames": len(infos), "conventions": CONVENTIONS, "sensor_model": sensor, "per_light": per,
                 "frames": infos}
        write_json(stage / "export.json", index)
    return index


SENSOR_DEVIATION = ("the dataset has a sensor model: its images are the sensor's recording (noise, quantisation, "
                    "clipping at saturation) while the per-light images are clean radiance, so "
                    "per_light_max_rel_deviation measures the sensor's effect, not a re-rendering error")

CONVENTIONS = {
    "frame": "camera frame: x right, y up, z toward the camera (normals and light directions)",
    "radiance": "linear (no gamma); PNG value / 65535 (or / 255) / png_scale = radiance",
    "normal_png": "(n + 1) / 2 * 65535 (or * 255); n = 0 (mid grey) outside the mask",
    "light_intensities": "row k: RGB intensity of light k on the image's scale: image_k / intensity_k is "
                         "the image under a unit white light (DiLiGenT convention)",
}
