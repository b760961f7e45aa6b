"""The frames an export writes: whole frames of a dataset, with their lights and (optionally) per-light images.

Whole frames come from `msps_render.dataset.iter_whole_frames` (datasets rendered with
`store_frames = true`).  Per-light images (and the environment-only image) come from
the shards when they were rendered with `store_per_light = true`, or else by
re-rendering each frame from the SceneSpec stored beside it (`rerender=True`,
Mitsuba needed; the only way for older shards).  Either way they sum, with the
environment image, to the stored image (up to float16 rounding when stored, and
without any sensor model), and `per_light_deviation` says by how much they differ.
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
from msps_render.dataset.reader import has_per_light, has_whole_frames
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
    env_ratio: float = 0.0  # environment light (0: none)
    per_light: np.ndarray | None = None  # (K, H, W, 3) float32 linear radiance, one image per light
    env_image: np.ndarray | None = None  # (H, W, 3) the environment light alone (None: no environment)
    per_light_source: str | None = None  # "stored" (frames/per_light) or "re-rendered" (frames/scene_json)
    per_light_deviation: float | None = None  # max |sum(per_light) + env - image| / max(image) over the mask

    def info(self) -> dict:
        d = {"id": self.id, "object": self.object, "materials": self.materials, "condition": self.condition,
             "shard": self.shard, "frame": self.index, "height": int(self.mask.shape[0]),
             "width": int(self.mask.shape[1]), "env_ratio": round(float(self.env_ratio), 6)}
        if self.per_light_source is not None:
            d["per_light_source"] = PER_LIGHT_SOURCES[self.per_light_source]
            d["per_light_max_rel_deviation"] = float(self.per_light_deviation)
            d["environment_image"] = self.env_image is not None
        return d


PER_LIGHT_SOURCES = {"stored": "stored in the shard (frames/per_light, frames/env_image)",
                     "re-rendered": "re-rendered from frames/scene_json"}
PER_LIGHT_CONTENTS = ("image k: the linear radiance light k alone makes (clean: before any sensor model). "
                      "The environment light is in none of them: where a frame has one (env_ratio > 0) its "
                      "image is written apart (environment.png / environment.exr), so image = sum_k image_k "
                      "+ environment (+ the sensor's noise, if the dataset has a sensor model)")


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


def stored_per_light(root: str | Path) -> Path | None:
    """None when every shard of the dataset stores per-light images, else the first shard without."""
    m = load_manifest(root)
    for e in m.shards_of():
        path = m.shard_path(e.name)
        with shard_errors(path), open_shard(path) as h:
            if not has_per_light(h):
                return path
    return None


def iter_export_frames(root: str | Path, per_light: bool = False, variant: str | None = None,
                       rerender: bool = False) -> Iterator[ExportFrame]:
    """Every whole frame; `per_light`: with its per-light images, from the shards or (`rerender`) re-rendered."""
    m = load_manifest(root)
    n = 0
    batch = dataset_batch_frames(root)
    for e in m.shards_of():
        light_rgb, scenes = read_frame_scenes(m.shard_path(e.name))
        rendered: dict = {}  # this shard's re-rendered batch, by frame index
        for fr in iter_whole_frames(m.shard_path(e.name), per_light=per_light and not rerender):
            ef = ExportFrame(id=f"{n:04d}-{safe_name(fr.object)}", image=np.asarray(fr.image, np.float32),
                             normal=np.asarray(fr.normal, np.float32), mask=np.asarray(fr.mask, bool),
                             light_dirs=np.asarray(fr.light_dirs, np.float64), crosstalk=np.asarray(fr.crosstalk),
                             light_rgb=np.asarray(light_rgb[fr.index], np.float64), object=fr.object,
                             materials=fr.materials, condition=fr.condition, shard=fr.shard, index=fr.index,
                             scene_json=scenes[fr.index], env_ratio=fr.env_ratio)
            if per_light and rerender:
                if batch > 1:
                    ef.per_light, ef.env_image = rerender_in_batch(ef, scenes, batch, rendered, variant)
                else:
                    ef.per_light, ef.env_image = rerender_per_light(ef, variant)
                ef.per_light_source = "re-rendered"
                if ef.env_ratio > 0 and ef.env_image is None:  # never drop the environment light silently
                    raise InputError(f"{m.shard_path(e.name)}: frame {fr.index}",
                                     f"the frame has an environment light (ratio {ef.env_ratio:g}) but its "
                                     "stored scene has none to re-render; export it without --rerender "
                                     "(png16/exr) or re-render the dataset with store_per_light = true")
            elif per_light:
                if fr.per_light is None:
                    raise InputError(m.shard_path(e.name), "shard stores no per-light images; export with --rerender")
                ef.per_light = fr.per_light
                ef.env_image = fr.env_image if fr.env_image is not None and fr.env_ratio > 0 else None
                ef.per_light_source = "stored"
            if ef.per_light is not None:
                _check_lights(ef)
                ef.per_light_deviation = per_light_deviation(ef)
            n += 1
            yield ef


def _check_lights(ef: ExportFrame) -> None:
    if ef.per_light.shape[0] != 3:
        raise InputError(f"{ef.shard}: frame {ef.index}", f"scene has {ef.per_light.shape[0]} lights, export needs 3")


def per_light_deviation(ef: ExportFrame) -> float:
    """max |sum(per_light) + env - image| over the mask, relative to the brightest object pixel."""
    m = ef.mask
    if not m.any():
        return 0.0
    total = ef.per_light.sum(0) + (ef.env_image if ef.env_image is not None else 0.0)
    return float(np.abs(total - ef.image)[m].max() / max(float(ef.image[m].max()), 1e-12))


def rerender_per_light(ef: ExportFrame, variant: str | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """(per-light images, environment-only image or None) of a frame, re-rendered from its SceneSpec."""
    spec = SceneSpec.from_json(ef.scene_json, f"{ef.shard}: frame {ef.index}")
    fr = render_frame(spec, variant=variant, per_light=True)
    env = None if fr.env_image is None else np.asarray(fr.env_image[..., :3], np.float32)
    return np.asarray(fr.per_light, np.float32), env


def rerender_in_batch(ef: ExportFrame, scenes: list[str], batch: int, rendered: dict,
                      variant: str | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """`rerender_per_light` of a frame of a dataset rendered `batch` frames per launch
    (`dataset.batch_frames`): its whole batch is rendered again as the worker rendered it (the same
    groups, `render.batch.launch_groups`), so its pixels are the shard's.  A group that could not
    share a launch was rendered frame by frame, and is again."""
    if ef.index not in rendered:
        from msps_render.render.batch import batchable, launch_groups, render_batch
        from msps_render.render.variant import activate, resolve_variant

        def spec_of(j: int) -> SceneSpec:
            return SceneSpec.from_json(scenes[j], f"{ef.shard}: frame {j}")

        rendered.clear()
        group = next(g for g in launch_groups(len(scenes), batch, spec_of) if ef.index in g)
        specs = [spec_of(j) for j in group]
        variant = variant or resolve_variant(specs[0].mode)
        if batchable(specs, activate(variant)):
            rendered.update(zip(group, render_batch(specs, variant=variant, per_light=True)))
        else:
            rendered.update((j, render_frame(s, variant=variant, per_light=True)) for j, s in zip(group, specs))
    fr = rendered[ef.index]
    env = None if fr.env_image is None else np.asarray(fr.env_image[..., :3], np.float32)
    return np.asarray(fr.per_light, np.float32), env


def dataset_batch_frames(root: str | Path) -> int:
    """Frames per kernel launch the dataset was rendered with (`dataset.batch_frames`; 1 when absent)."""
    cfg = (read_manifest(root) or {}).get("config") or {}
    return int(((cfg.get("dataset") or {}) if isinstance(cfg, dict) else {}).get("batch_frames", 1))


def dataset_variant(root: str | Path) -> str | None:
    """The Mitsuba variant a dataset was rendered with, if this Mitsuba has it (else None: the best
    available; `per_light_max_rel_deviation` in export.json then shows how far the re-render differs)."""
    m = read_manifest(root) or {}
    v = (m.get("versions") or {}).get("variant")
    return v if v in mitsuba_info().get("variants", ()) else None


def sensor_model(root: str | Path) -> dict | None:
    """The dataset's enabled `[sensor]` table (its images are the sensor's recording), else None."""
    cfg = (read_manifest(root) or {}).get("config") or {}
    sensor = cfg.get("sensor") if isinstance(cfg, dict) else None
    return sensor if isinstance(sensor, dict) and sensor.get("enabled") else None


def write_json(path: Path, d) -> Path:
    path.write_text(json.dumps(d, indent=1) + "\n")
    return path
