"""The frames an export writes: whole frames of a dataset, with their lights and (optionally) per-light images.

Whole frames come from `msps_render.dataset.iter_whole_frames` (datasets rendered with
`store_frames = true`).  Shards keep no per-light images; the formats that need
them (PS-FCN, DiLiGenT) get them by re-rendering each frame from the SceneSpec
stored beside it (`rerender=True`, Mitsuba needed): the per-light renders sum
to the stored image (without the environment light and any sensor model), and
`per_light_deviation` says by how much they differ.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from msps_render.dataset import (iter_whole_frames, load_manifest, open_shard, read_frame_scenes, read_manifest,
                                 shard_errors)
from msps_render.dataset.reader import has_whole_frames
from msps_render.errors import InputError
from msps_render.render import render_frame
from msps_render.render.variant import mitsuba_info
from msps_render.scene.spec import SceneSpec


@dataclass
class ExportFrame:
    id: str  # unique, file-name safe: "0003-torus"
    image: np.ndarray  # (H, W, 3) float32 linear radiance
    normal: np.ndarray  # (H, W, 3) camera frame, 0 outside the mask
    mask: np.ndarray  # (H, W) bool
    light_dirs: np.ndarray  # (3, 3) rows toward light k
    crosstalk: np.ndarray  # (3, 3)
    light_rgb: np.ndarray  # (3, 3) row k: RGB irradiance of light k
    object: str
    materials: str
    condition: str
    shard: str
    index: int
    scene_json: str
    per_light: np.ndarray | None = None  # (K, H, W, 3) float32 linear radiance, one image per light
    per_light_deviation: float | None = None  # max |sum(per_light) - image| / max(image) over the mask

    def info(self) -> dict:
        d = {"id": self.id, "object": self.object, "materials": self.materials, "condition": self.condition,
             "shard": self.shard, "frame": self.index, "height": int(self.mask.shape[0]),
             "width": int(self.mask.shape[1])}
        if self.per_light_deviation is not None:
            d["per_light_source"] = "re-rendered from frames/scene_json"
            d["per_light_max_rel_deviation"] = float(self.per_light_deviation)
        return d


def safe_name(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", s).strip("_") or "x"


def check_has_frames(root: str | Path) -> None:
    """InputError naming the first shard without whole frames (before anything is written)."""
    m = load_manifest(root)
    for e in m.shards_of():
        path = m.shard_path(e.name)
        with shard_errors(path), open_shard(path) as h:
            if not has_whole_frames(h):
                raise InputError(path, "shard has no whole frames: export needs a dataset rendered with "
                                       "dataset.storage.store_frames = true (e.g. --set "
                                       "dataset.storage.store_frames=true)")


def iter_export_frames(root: str | Path, per_light: bool = False, variant: str | None = None,
                       ) -> Iterator[ExportFrame]:
    m = load_manifest(root)
    n = 0
    for e in m.shards_of():
        light_rgb, scenes = read_frame_scenes(m.shard_path(e.name))
        for fr in iter_whole_frames(m.shard_path(e.name)):
            ef = ExportFrame(id=f"{n:04d}-{safe_name(fr.object)}", image=np.asarray(fr.image, np.float32),
                             normal=np.asarray(fr.normal, np.float32), mask=np.asarray(fr.mask, bool),
                             light_dirs=np.asarray(fr.light_dirs, np.float64), crosstalk=np.asarray(fr.crosstalk),
                             light_rgb=np.asarray(light_rgb[fr.index], np.float64), object=fr.object,
                             materials=fr.materials, condition=fr.condition, shard=fr.shard, index=fr.index,
                             scene_json=scenes[fr.index])
            if per_light:
                ef.per_light, ef.per_light_deviation = rerender_per_light(ef, variant)
            n += 1
            yield ef


def rerender_per_light(ef: ExportFrame, variant: str | None = None) -> tuple[np.ndarray, float]:
    spec = SceneSpec.from_json(ef.scene_json, f"{ef.shard}: frame {ef.index}")
    fr = render_frame(spec, variant=variant, per_light=True)
    per = np.asarray(fr.per_light, np.float32)
    if per.shape[0] != 3:
        raise InputError(f"{ef.shard}: frame {ef.index}", f"scene has {per.shape[0]} lights, export needs 3")
    m = ef.mask
    ref = float(ef.image[m].max()) if m.any() else 1.0
    dev = float(np.abs(per.sum(0) - ef.image)[m].max() / max(ref, 1e-12)) if m.any() else 0.0
    return per, dev


def dataset_variant(root: str | Path) -> str | None:
    """The Mitsuba variant a dataset was rendered with, if this Mitsuba has it (else None: the best
    available; `per_light_max_rel_deviation` in export.json then shows how far the re-render differs)."""
    m = read_manifest(root) or {}
    v = (m.get("versions") or {}).get("variant")
    return v if v in mitsuba_info().get("variants", ()) else None


def write_json(path: Path, d) -> Path:
    path.write_text(json.dumps(d, indent=1) + "\n")
    return path
