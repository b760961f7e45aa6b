"""Model presets (`models/*.toml`): network widths and training schedule, validated."""
from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field

from msps_render import resources
from msps_render.config_io import StrictModel, apply_overrides, check_override_keys, read_toml, validate
from msps_render.errors import InputError, closest



class NetSection(StrictModel):
    branch: int = Field(8, ge=1, description="features per colour-channel branch (SCN)")
    unet: tuple[int, int, int, int] = Field((24, 48, 64, 96), description="SCN U-Net widths at 40, 20, 10, 5 px")
    pcn_branch: int = Field(32, ge=1, description="width of each PCN input branch")
    pcn: tuple[int, ...] = Field((64, 64, 32, 32), description="PCN per-pixel layer widths after the merge")
    mode: Literal["dual", "scn", "pcn"] = Field("dual", description="both cues (dual) or one network alone")
    chroma_cue: bool = Field(False, description="also feed each colour channel divided by its own patch mean "
                                                "(an albedo-colour-invariant cue; docs/history.md stage 6e)")
    lambert_cue: bool = Field(False, description="also feed the PCN the calibrated Lambertian normal and its "
                                                 "length residual per pixel (the net then needs the rig: "
                                                 "light directions and crosstalk; docs/history.md stage 7)")
    lambert_scn: bool = Field(False, description="feed the same Lambertian cue to the SCN's U-Net as well "
                                                 "(beside the colour branches' features; needs the rig)")
    cue_gain: float = Field(1.0, gt=0, description="multiplies the Lambertian cue: warm-started at zero weight "
                                                   "under Adam, its weights then move this many times faster "
                                                   "(docs/history.md stage 7b)")


class TrainSection(StrictModel):
    batch_size: int = Field(24, ge=1, description="patches per step")
    lr: float = Field(1e-3, gt=0, description="Adam learning rate")
    betas: tuple[float, float] = Field((0.9, 0.999), description="Adam betas")
    epochs: int = Field(20, ge=1, description="passes over the training data (the first budget reached stops)")
    max_steps: int = Field(100000, ge=1, description="optimizer steps budget")
    max_minutes: float | None = Field(None, gt=0, description="wall-clock budget (min); unset: none")
    schedule: Literal["constant", "cosine"] = Field("cosine", description="learning-rate schedule")
    val_every: int = Field(500, ge=1, description="validate and record metrics at least every N steps (denser "
                                                  "when the planned run would give fewer than 20 points, and "
                                                  "after max_minutes/20 without one)")
    val_max_patches: int = Field(2000, ge=1, description="validation patches per check")
    seed: int = Field(0, description="seed of initialisation and data order")
    precision: Literal["auto", "fp32", "bf16"] = Field(
        "auto", description="arithmetic of the forward pass: auto = bf16 autocast on a CUDA device, float32 on "
                            "the CPU (bf16 needs no loss scaler; docs/scaling.md \"Running on a GPU\")")
    channels_last: bool | Literal["auto"] = Field("auto", description="NHWC memory format for the convolutions "
                                                                      "(auto: on a CUDA device)")
    num_workers: int = Field(0, ge=0, description="DataLoader worker processes")
    cache: bool | Literal["auto"] = Field("auto", description="keep the decoded training corpus in memory "
                                                              "(auto: when it takes <= 40 % of available memory)")
    shuffle_window: int = Field(4, ge=0, description="shards whose patches are shuffled together into batches; "
                                                     "0 = the whole corpus (i.i.d. batches, gathered from the "
                                                     "decoded cache: meant with `cache`). With windows a batch "
                                                     "holds 1-2 shards and ~100 batches in a row come from 4: "
                                                     "with several corpora, validation swings between them "
                                                     "(docs/history.md, stage 4)")
    freeze_bn: bool = Field(False, description="keep BatchNorm layers in inference mode while training: their "
                                               "statistics stay those of the --init model and only weights "
                                               "learn (fine-tuning on a new corpus mix; docs/history.md)")
    mirror_aug: float = Field(0.0, ge=0, le=1, description="share of each batch replaced by its exact mirror "
                                                          "image (rows reversed, channels 1 and 2 swapped, the "
                                                          "rig mirrored with it; models/symmetry.py): a "
                                                          "physically exact augmentation for any material")
    albedo_aug: float = Field(0.0, ge=0, le=1, description="share of each batch whose albedo is multiplied by "
                                                           "a fresh colour field (smooth, noise, patches, "
                                                           "stripes, decals; full gamut; models/augment.py): "
                                                           "exact for direct light in RGB mode")
    albedo_aug_scope: Literal["all", "lambertian"] = Field(
        "all", description="which patches `albedo_aug` may tint: all, or only those of frames whose image is "
                           "linear in the albedo (every material Lambertian, RGB mode, no camera response), "
                           "where the tint is physical too -- a tinted measured or glossy material gets a "
                           "coloured highlight, which dielectrics never have (docs/history.md, stage 11)")


# `msps train PRESET --smoke`: the whole loop (data, steps, validation, checkpoints, curve) in minutes on
# 2 cores -- a 2.5-minute budget and a 512-patch validation (~2 s per check for the cpu preset).
SMOKE = ("train.max_minutes=2.5", "train.val_max_patches=512")


class ModelConfig(StrictModel):
    preset: str = Field("custom", description="preset name (recorded in checkpoints)")
    net: NetSection = NetSection()
    train: TrainSection = TrainSection()

    def net_config(self):
        from msps_render.models.net import NetConfig

        n = self.net
        return NetConfig(branch=n.branch, unet=tuple(n.unet), pcn_branch=n.pcn_branch, pcn=tuple(n.pcn), mode=n.mode,
                         chroma_cue=n.chroma_cue, lambert_cue=n.lambert_cue,
                         lambert_scn=n.lambert_scn, cue_gain=n.cue_gain)


def load_model_config(path_or_name: str | Path, overrides: list[str] = ()) -> ModelConfig:
    p = resources.find("models", path_or_name)
    if p is None:
        known = resources.names("models")
        raise InputError(Path(path_or_name), f"model config not found{closest(str(path_or_name), known)} "
                                             f"(presets: {', '.join(known)})")
    check_override_keys(overrides, ModelConfig)  # a typo in --set is blamed on --set, not the preset file
    return validate(ModelConfig, apply_overrides(read_toml(p, "model config"), overrides), p, overrides)
