"""`DatasetConfig`: a dataset preset (TOML) validated with clear, named errors.

A preset is a `[dataset]` table (shards, frames, patches, storage) plus a
`[scene]` table mirroring `SceneConfig`, optionally a `[sensor]` table (the
camera's noise model, applied after rendering), and optionally a `[sweep]` that
renders the same scenes under several values of one setting (e.g. the
environment-light ratio or the slant), one condition each.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, PrivateAttr, model_serializer, model_validator

from msps_render import resources
from msps_render.config_io import StrictModel, apply_overrides, check_override_keys, omit_defaults, read_toml, set_path, \
    validate
from msps_render.errors import InputError, closest
from msps_render.pipeline.scheduler_config import SchedulerSection
from msps_render.render.sensor import SensorConfig
from msps_render.scene.sample import SceneConfig

PRESET_DIR = resources.data_dir("scenes")  # where `load_config("<name>")` looks (see msps_render.resources)


class PatchConfig(StrictModel):
    size: int = Field(40, ge=8, le=512, description="patch side (px)")
    stride: int = Field(20, ge=1, le=512, description="step between patch origins (px)")
    min_coverage: float = Field(0.5, ge=0.0, le=1.0, description="keep a patch when at least this fraction of its pixels is object")


class StorageConfig(StrictModel):
    compression: Literal["lzf", "gzip", "zstd", "blosc2-lz4", "none"] = Field(
        "zstd", description="HDF5 filter of every array. zstd (the default): ~2x faster to read and ~3x "
                            "cheaper to write than lzf at 1/3 of the disk, but other tools must `import "
                            "hdf5plugin` to read it (msps's readers do); lzf: readable by plain h5py "
                            "(docs/benchmarks.md \"Storage filters\")")
    image_dtype: Literal["float16", "float32"] = Field("float16", description="stored dtype of patch images")
    normal_dtype: Literal["float16", "float32"] = Field("float16", description="stored dtype of patch normals")
    store_frames: bool = Field(False, description="also keep whole frames (test sets)")
    store_per_light: bool = Field(False, description="with store_frames: also keep each whole frame's "
                                                     "per-light images (light k alone) and its environment-"
                                                     "only image, in image_dtype, so exports need no "
                                                     "--rerender")
    store_shadows: bool = Field(False, description="any rig ([scene.rig]): also keep, per patch and per light, "
                                                   "where the surface is lit (0), in attached shadow (n.l <= 0: 1) "
                                                   "or in cast shadow (2) -- patches/shadow, uint8; one ray per "
                                                   "pixel and light (docs/rigs.md)")

    @model_serializer(mode="wrap")
    def _without_later_defaults(self, handler):
        """Configs that do not store shadows serialise (and hash) as before the option existed."""
        return omit_defaults(self, handler(self), ("store_shadows",))

    @model_validator(mode="after")
    def _per_light_needs_frames(self) -> "StorageConfig":
        if self.store_per_light and not self.store_frames:
            raise ValueError("store_per_light needs store_frames = true (per-light images are whole frames)")
        return self


class DatasetSection(StrictModel):
    name: str = Field("dataset", description="dataset name (recorded in the manifest)")
    seed: int = Field(0, ge=0, description="root seed: frame j of shard k depends only on (seed, k, j)")
    n_shards: int = Field(4, ge=1, le=100000, description="shards per condition (one HDF5 file each)")
    frames_per_shard: int = Field(8, ge=1, le=100000, description="rendered frames per shard")
    batch_frames: int = Field(1, ge=1, le=64, description="frames of a shard rendered by one kernel launch "
                                                          "(at most frames_per_shard; beyond 3 lights at most "
                                                          "128 // lights) where they can share it: one-pass, "
                                                          "no environment, directional or point lights, RGB or "
                                                          "spectral (render/batch.py); the pixels differ from one "
                                                          "frame per launch in noise only (docs/benchmarks.md "
                                                          "\"Frames in batches\")")
    patches: PatchConfig = PatchConfig()
    storage: StorageConfig = StorageConfig()

    @model_serializer(mode="wrap")
    def _without_later_defaults(self, handler):
        """Unbatched configs serialise (and hash) as before the option existed."""
        return omit_defaults(self, handler(self), ("batch_frames",))


class SweepConfig(StrictModel):
    key: str = Field(description="the swept config key, e.g. 'environment.ratio' (short for "
                                 "'scene.environment.ratio')")
    values: list[Any] = Field(min_length=1, description="one condition per value; each condition renders "
                                                        "the same shard seeds")


class DatasetConfig(StrictModel):
    dataset: DatasetSection = DatasetSection()
    scene: SceneConfig = SceneConfig()
    sensor: SensorConfig | None = Field(None, description="camera sensor model applied after rendering "
                                                          "(absent: the image is the rendered radiance)")
    sweep: SweepConfig | None = None
    scheduler: SchedulerSection = Field(SchedulerSection(), exclude=True,
                                        description="how to run the render (--scheduler slurm); not part of "
                                                    "the dataset: left out of the config hash and the shards")
    _source: str | None = PrivateAttr(default=None)  # the TOML it was read from (for error lines)

    @model_validator(mode="before")
    @classmethod
    def _legacy_scene_sensor(cls, data: Any) -> Any:
        return legacy_scene_sensor(data)

    @model_validator(mode="after")
    def _check(self) -> "DatasetConfig":
        p = self.dataset.patches
        c = self.scene.camera
        if p.size > min(c.width, c.height):
            raise ValueError(f"patch size {p.size} exceeds the frame size {c.width}x{c.height}")
        if self.dataset.storage.store_shadows and self.scene.rig is None:
            raise ValueError("dataset.storage.store_shadows needs a [scene.rig] (shadow masks are stored in "
                             "format-2 shards; the three-light rig is layout = \"three\")")
        if self.sweep is not None:
            for v in self.sweep.values:  # every condition must itself validate
                condition_config(self, v)
        return self

    def conditions(self) -> list[tuple[str, Any]]:
        """(name, value) per condition; one unnamed condition without a sweep."""
        if self.sweep is None:
            return [("", None)]
        leaf = self.sweep.key.split(".")[-1]
        return [(f"{leaf}={v}", v) for v in self.sweep.values]


def legacy_scene_sensor(data: Any) -> Any:
    """Presets before 0.2 spelled the sensor `[scene.sensor]`; read it as `[sensor]`."""
    if isinstance(data, dict) and isinstance(data.get("scene"), dict) and "sensor" in data["scene"]:
        if data.get("sensor") is not None:
            raise ValueError("sensor: give either [sensor] or the old [scene.sensor], not both")
        data = {**data, "scene": {k: v for k, v in data["scene"].items() if k != "sensor"},
                "sensor": data["scene"]["sensor"]}
    return data


def condition_config(cfg: DatasetConfig, value) -> DatasetConfig:
    """The config of one sweep condition (the swept key set to `value`)."""
    data = cfg.model_dump(mode="json")
    data.pop("sweep", None)
    set_path(data, _qualify(cfg.sweep.key), value)
    return DatasetConfig.model_validate(data)


def _qualify(key: str) -> str:
    """`lights.slant_deg` is shorthand for `scene.lights.slant_deg`."""
    top = key.split(".")[0]
    if top in DatasetConfig.model_fields:
        return key
    if top in SceneConfig.model_fields:
        return f"scene.{key}"
    if top in DatasetSection.model_fields:
        return f"dataset.{key}"
    return key


def resolve_preset(path_or_name: str | Path) -> Path:
    p = resources.find("scenes", path_or_name)
    if p is None:
        known = resources.names("scenes")
        raise InputError(Path(path_or_name), f"config file not found{closest(str(path_or_name), known)} "
                                             f"(presets: {', '.join(known) or 'none'})")
    return p


def load_config(path_or_name: str | Path, overrides: list[str] | tuple[str, ...] = ()) -> DatasetConfig:
    """Read a preset name or TOML path, apply `key=value` overrides, validate."""
    p = resolve_preset(path_or_name)
    check_override_keys(overrides, DatasetConfig, _qualify, legacy_scene_sensor)  # blame --set, not the file
    data = apply_overrides(read_toml(p), overrides, _qualify)
    cfg = validate_config(data, str(p), overrides)
    cfg._source = str(p)
    return cfg


def validate_config(data: dict, source: str = "<config>", overrides=()) -> DatasetConfig:
    try:  # before the unknown-key check, which does not know the old spelling
        data = legacy_scene_sensor(data)
    except ValueError as e:
        raise InputError(source, str(e)) from None
    return validate(DatasetConfig, data, source, overrides, _qualify)


def config_json(cfg: DatasetConfig) -> str:
    return json.dumps(cfg.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))


def config_hash(cfg: DatasetConfig) -> str:
    """sha256 of the canonical resolved config: identifies what a dataset directory contains."""
    return hashlib.sha256(config_json(cfg).encode()).hexdigest()
