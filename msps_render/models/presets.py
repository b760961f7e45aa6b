"""Model presets (`models/*.toml`): network widths and training schedule, validated."""
from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field

from msps_render import resources
from msps_render.config_io import StrictModel, apply_overrides, read_toml, validate
from msps_render.errors import InputError



class NetSection(StrictModel):
    branch: int = Field(8, ge=1)
    unet: tuple[int, int, int, int] = (24, 48, 64, 96)
    pcn_branch: int = Field(32, ge=1)
    pcn: tuple[int, ...] = (64, 64, 32, 32)
    mode: Literal["dual", "scn", "pcn"] = "dual"


class TrainSection(StrictModel):
    batch_size: int = Field(24, ge=1)
    lr: float = Field(1e-3, gt=0)
    betas: tuple[float, float] = (0.9, 0.999)
    epochs: int = Field(20, ge=1)
    max_steps: int = Field(100000, ge=1)
    max_minutes: float | None = Field(None, gt=0)
    schedule: Literal["constant", "cosine"] = "cosine"
    val_every: int = Field(500, ge=1)
    val_max_patches: int = Field(2000, ge=1)
    seed: int = 0
    num_workers: int = Field(0, ge=0)


class ModelConfig(StrictModel):
    preset: str = "custom"
    net: NetSection = NetSection()
    train: TrainSection = TrainSection()

    def net_config(self):
        from msps_render.models.net import NetConfig

        n = self.net
        return NetConfig(branch=n.branch, unet=tuple(n.unet), pcn_branch=n.pcn_branch, pcn=tuple(n.pcn), mode=n.mode)


def load_model_config(path_or_name: str | Path, overrides: list[str] = ()) -> ModelConfig:
    p = resources.find("models", path_or_name)
    if p is None:
        known = ", ".join(resources.names("models"))
        raise InputError(Path(path_or_name), f"model config not found (presets: {known})")
    return validate(ModelConfig, apply_overrides(read_toml(p, "model config"), overrides), p)
