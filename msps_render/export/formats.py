"""The export-format registry: each format module registers one `ExportFormat` in `FORMATS`."""
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
    per_light: bool = False  # needs one image per light (stored with store_per_light, else --rerender)
    light_files: str = ""  # where the per-light and environment images go (export.json says)
    # a rig dataset's frame (format-2 shards, `anyrig.RigExportFrame`); None: the format takes three-light data only
    write_rig_frame: Callable[[object, Path], dict] | None = None
    rig_light_files: str = ""  # where a rig dataset's per-light images go (export.json says)


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


def write_frames(frames, write, stage, progress=None) -> list[dict]:
    """Every frame written by `write(frame, stage)` into `stage`: its `info()` and what the writer returns,
    one dict per frame (the export index); `progress(i, frame)` hears each."""
    infos = []
    for i, ef in enumerate(frames):
        info = ef.info()
        info.update(write(ef, stage))
        infos.append(info)
        if progress:
            progress(i, ef)
    return infos
