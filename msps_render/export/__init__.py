"""`msps export`: a dataset's whole frames in the layouts other photometric-stereo code reads.

One module per format, each registering an `ExportFormat` in `FORMATS` (add a
format: one module, one line below).  `export_dataset` validates everything
first, writes into a hidden temporary directory beside `--out` and renames it
into place at the end, so a failure or an interrupt leaves nothing behind.
Layouts and conventions: docs/recipes.md "Export".
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from msps_render.errors import InputError, closest
from msps_render.export.source import ExportFrame


@dataclass(frozen=True)
class ExportFormat:
    name: str
    help: str
    write_frame: Callable[[ExportFrame, Path], dict]  # writes one frame under the export root, returns info
    finish: Callable[[Path, list[dict]], None] | None = None  # index files, after every frame
    per_light: bool = False  # needs one image per light (shards do not store them: --rerender)


FORMATS: dict[str, ExportFormat] = {}


def register(fmt: ExportFormat, aliases: tuple[str, ...] = ()) -> ExportFormat:
    for name in (fmt.name, *aliases):
        FORMATS[name.lower()] = fmt
    return fmt


def get_format(name: str) -> ExportFormat:
    f = FORMATS.get(name.lower())
    if f is None:
        raise InputError("--format", f"unknown export format '{name}'{closest(name.lower(), FORMATS)} "
                                     f"(known: {', '.join(FORMATS)})")
    return f


def export_dataset(root: str | Path, fmt: str, out: str | Path, rerender: bool = False,
                   progress: Callable[[int, ExportFrame], None] | None = None) -> dict:
    """Export every whole frame of dataset `root` as `fmt` into the new directory `out`; returns the index."""
    from msps_render.export.source import check_has_frames, dataset_variant, iter_export_frames, write_json
    from msps_render.export.staging import check_new_out, staged_dir
    from msps_render.pipeline.manifest import SHARD_DIR, read_manifest

    root, out = Path(root), Path(out)
    f = get_format(fmt)
    check_has_frames(root)  # also: not a dataset, incomplete, unreadable shard
    if f.per_light and not rerender:
        first = sorted((root / SHARD_DIR).glob("shard-*.h5"))[0]
        raise InputError(first, f"shards store no per-light images, which the {f.name} layout needs; add "
                                "--rerender to re-render them from the scenes stored in the shards (needs Mitsuba)")
    check_new_out(out)
    with staged_dir(out) as stage:
        infos = []
        variant = dataset_variant(root) if f.per_light else None
        for i, ef in enumerate(iter_export_frames(root, per_light=f.per_light, variant=variant)):
            info = ef.info()
            info.update(f.write_frame(ef, stage))
            infos.append(info)
            if progress:
                progress(i, ef)
        if f.finish:
            f.finish(stage, infos)
        m = read_manifest(root) or {}
        index = {"format": f.name, "dataset": str(root.resolve()), "config_hash": m.get("config_hash"),
                 "n_frames": len(infos), "conventions": CONVENTIONS, "frames": infos}
        write_json(stage / "export.json", index)
    return index


CONVENTIONS = {
    "frame": "camera frame: x right, y up, z toward the camera (normals and light directions)",
    "radiance": "linear (no gamma); PNG value / 65535 (or / 255) / png_scale = radiance",
    "normal_png": "(n + 1) / 2 * 65535 (or * 255); n = 0 (mid grey) outside the mask",
    "light_intensities": "row k: RGB intensity of light k on the image's scale: image_k / intensity_k is "
                         "the image under a unit white light (DiLiGenT convention)",
}

# The registry: one line per format module.
from msps_render.export import images as _images  # noqa: E402,F401
from msps_render.export import psfcn as _psfcn  # noqa: E402,F401
from msps_render.export import diligent as _diligent  # noqa: E402,F401
