"""Checkpoints: plain dicts of tensors and primitives, loadable with `torch.load(weights_only=True)`.

Every checkpoint holds the weights, the model config and preset, and `format`;
a run's `last.pt` adds what resuming needs (optimizer, scheduler state, step,
epoch, position, RNG state) and provenance (data hash, validation error).
"""
from __future__ import annotations

import io
from pathlib import Path

import torch

from msps_render.atomic import write_bytes
from msps_render.errors import InputError, brief
from msps_render.models.net import DualCueNet
from msps_render.models.presets import ModelConfig

FORMAT = "msps-dualcue-1"


def save_checkpoint(path: Path, model, cfg: ModelConfig, extra: dict) -> Path:
    """Write weights + config (+ `extra`) atomically to `path`."""
    ck = {"model": model.state_dict(), "config": cfg.model_dump(mode="json"), "preset": cfg.preset,
          "format": FORMAT, **extra}
    return save_dict(path, ck)


def save_dict(path: str | Path, ck: dict) -> Path:
    """`torch.save(ck)` to `path` atomically.  Serialised in memory first: torch writing to a full disk
    says only 'unexpected pos'; written by `write_bytes`, a full disk is one `WriteFailed` naming `path`."""
    buf = io.BytesIO()
    torch.save(ck, buf)
    return write_bytes(path, buf.getbuffer())


def not_torch_reason(p: Path) -> str | None:
    """Why a file is not a `torch.save` archive, in words (None: it looks like one, the error is deeper)."""
    head = p.read_bytes()[:512]
    if head.startswith(b"PK\x03\x04") or head[:1] == b"\x80":  # zip archive (torch >= 1.6) / legacy pickle
        return None
    if not head:
        return "an empty file, not a checkpoint"
    try:
        head.decode("utf-8")
    except UnicodeDecodeError:
        return None  # other binary data: torch's own reason says more
    return f"a text file of {p.stat().st_size} bytes, not a checkpoint (a torch.save archive, e.g. a run's best.pt)"


def load_checkpoint(path: str | Path, expect_preset: str | None = None, map_location: str = "cpu"):
    """(model in eval mode, ModelConfig, checkpoint dict). Clear errors for foreign files."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "checkpoint not found")
    try:
        ck = torch.load(p, map_location=map_location, weights_only=True)
    except Exception as e:
        raise InputError(p, not_torch_reason(p) or f"not a loadable checkpoint ({brief(str(e), 100)})") from None
    if not isinstance(ck, dict) or ck.get("format") != FORMAT:
        raise InputError(p, "not an msps dual-cue checkpoint")
    cfg = ModelConfig.model_validate(ck["config"])
    if expect_preset and cfg.preset != expect_preset:
        raise InputError(p, f"checkpoint is for preset '{cfg.preset}', expected '{expect_preset}'")
    model = DualCueNet(cfg.net_config())
    try:
        model.load_state_dict(ck["model"])
    except RuntimeError as e:
        raise InputError(p, f"weights do not fit the '{cfg.preset}' network ({brief(str(e), 100)})") from None
    model.eval()
    return model, cfg, ck


TRAINING_ONLY = ("optimizer", "torch_rng")  # what resuming needs and a shipped model does not


def export_checkpoint(src: str | Path, dst: str | Path, train_lights: dict | None = None) -> Path:
    """A training checkpoint as a shipped model: weights, config, provenance; no optimizer or RNG state
    (a third of the size).  `train_lights` replaces the recorded light geometry (e.g. widened to what an
    --init checkpoint had seen, `dataset.manifest.merge_training_lights`)."""
    _, _, ck = load_checkpoint(src)  # validates the file
    out = {k: v for k, v in ck.items() if k not in TRAINING_ONLY}
    out["state"] = {k: v for k, v in ck.get("state", {}).items() if k != "batch_in_epoch"}
    if train_lights is not None:
        out["train_lights"] = train_lights
    return save_dict(dst, out)
