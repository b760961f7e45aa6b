"""Training loop: joint SCN+PCN training with Adam, checkpoints, resume, metrics log and plot.

Joint (end-to-end) training is the default: the total loss is L_scn on the
coarse normal plus L_pcn on the final normal, so the SCN learns structure while
the PCN learns to correct it per pixel. (Staged SCN->PCN training is the same
loop run twice with `net.mode = "scn"` then `"dual"`; joint was simpler and
reached lower validation error at equal time in our runs: docs/reproducing.md.)

Checkpoints are plain dicts of tensors and primitives, loadable with
`torch.load(weights_only=True)`; `last.pt` holds everything needed to resume
the same schedule (optimizer, scheduler, step, epoch, position, RNG state).
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from msps_render.errors import InputError, brief
from msps_render.models.losses import angular_error, total_loss
from msps_render.models.net import DualCueNet, count_parameters
from msps_render.models.presets import ModelConfig


def data_hash(root: str | Path | Sequence[str | Path]) -> str:
    """Identity of the training data (shard checksums), so --resume refuses other data."""
    import hashlib

    from msps_render.pipeline.manifest import read_manifest

    roots = [root] if isinstance(root, (str, Path)) else list(root)
    sums = []
    for r in roots:
        m = read_manifest(r)
        if m is None:
            raise InputError(r, "no dataset.json here (not a dataset directory)")
        sums.append({k: v["file_sha256"] for k, v in sorted(m["shards"].items())})
    return hashlib.sha256(json.dumps(sums[0] if len(sums) == 1 else sums).encode()).hexdigest()


def _sha1(path: str | Path) -> str:
    import hashlib

    return hashlib.sha1(Path(path).read_bytes()).hexdigest()


def save_checkpoint(path: Path, model, cfg: ModelConfig, extra: dict) -> Path:
    ck = {"model": model.state_dict(), "config": cfg.model_dump(mode="json"), "preset": cfg.preset,
          "format": "msps-dualcue-1", **extra}
    tmp = path.with_name(f".{path.name}.tmp")
    torch.save(ck, tmp)
    tmp.replace(path)
    return path


def load_checkpoint(path: str | Path, expect_preset: str | None = None, map_location: str = "cpu"):
    """(model in eval mode, ModelConfig, checkpoint dict). Clear errors for foreign files."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "checkpoint not found")
    try:
        ck = torch.load(p, map_location=map_location, weights_only=True)
    except Exception as e:
        raise InputError(p, f"not a loadable checkpoint ({brief(str(e), 100)})") from None
    if not isinstance(ck, dict) or ck.get("format") != "msps-dualcue-1":
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


@torch.no_grad()
def validate(model, loader, max_patches: int) -> float:
    """Mean angular error (degrees) over object pixels of up to `max_patches` patches."""
    was = model.training
    model.eval()
    err_sum, n_pix, seen = 0.0, 0.0, 0
    for b in loader:
        pred, _ = model(b["image"], b["mask"])
        e = torch.rad2deg(angular_error(pred, b["normal"])) * b["mask"]
        err_sum += float(e.sum())
        n_pix += float(b["mask"].sum())
        seen += len(b["image"])
        if seen >= max_patches:
            break
    model.train(was)
    return err_sum / max(n_pix, 1.0)


def lr_factor(cfg: ModelConfig, progress: float) -> float:
    """Cosine decay to 5% of the base rate as training progress goes 0 -> 1 (or constant)."""
    if cfg.train.schedule == "constant":
        return 1.0
    return 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(max(progress, 0.0), 1.0)))


def train(cfg: ModelConfig, data: str | Path | Sequence[str | Path], val: str | Path, out: str | Path, resume: bool = False,
          device: str = "cpu", progress: bool = True, verify: bool = True,
          init: str | Path | None = None) -> dict:
    """Train from scratch, continue a run (`resume`), or warm-start from another run's weights.

    `init` loads only the weights of a checkpoint of the same network (fresh optimizer and
    schedule): how a longer run or a fine-tune on a new corpus starts from an earlier model.
    """
    from msps_render.data import PatchDataset, make_loader

    out = Path(out)
    t_cfg = cfg.train
    train_ds = PatchDataset(data, verify=verify)
    val_ds = PatchDataset(val, verify=verify)
    if len(train_ds) == 0 or len(val_ds) == 0:
        raise InputError(train_ds.root if len(train_ds) == 0 else val, "dataset has no patches")
    torch.manual_seed(t_cfg.seed)
    model = DualCueNet(cfg.net_config()).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=t_cfg.lr, betas=tuple(t_cfg.betas))
    state = {"step": 0, "epoch": 0, "batch_in_epoch": 0, "elapsed": 0.0, "best_val": float("inf")}
    dhash = data_hash(data)
    from msps_render.calibration import training_lights  # the lights predict compares against

    train_lights = training_lights(data)
    last = out / "last.pt"
    if resume:
        if not last.is_file():
            raise InputError(last, "nothing to resume (no last.pt)")
        _, rcfg, ck = load_checkpoint(last)
        if rcfg.model_dump() != cfg.model_dump():
            raise InputError(last, "checkpoint was trained with a different model config")
        if ck.get("data_hash") != dhash:
            raise InputError(last, "checkpoint was trained on a different dataset")
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        state.update(ck["state"])
        torch.set_rng_state(ck["torch_rng"])
    elif last.is_file():
        raise InputError(out, "already holds a training run; use --resume to continue it")
    elif init is not None:
        _, icfg, ick = load_checkpoint(init)
        if icfg.net != cfg.net:
            raise InputError(init, f"--init checkpoint has a different network ({icfg.preset}: {icfg.net})")
        model.load_state_dict(ick["model"])
        state["init_from"] = f"{Path(init).name} sha1:{_sha1(init)[:12]}"
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(cfg.model_dump(mode="json"), indent=1))
    loader = make_loader(train_ds, t_cfg.batch_size, shuffle=True, seed=t_cfg.seed, drop_last=True,
                         num_workers=t_cfg.num_workers)
    val_loader = make_loader(val_ds, 64, shuffle=True, seed=1234)
    log = open(out / "metrics.jsonl", "a")
    n_params = count_parameters(model)
    t_start = time.perf_counter() - state["elapsed"]
    budget = t_cfg.max_minutes * 60 if t_cfg.max_minutes else float("inf")
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=t_cfg.max_steps, initial=state["step"], unit="step", dynamic_ncols=True)

    def checkpoint(name: str, val_mae: float | None = None):
        state["elapsed"] = time.perf_counter() - t_start
        save_checkpoint(out / name, model, cfg, {
            "optimizer": opt.state_dict(), "state": dict(state),
            "torch_rng": torch.get_rng_state(), "data_hash": dhash, "n_params": n_params,
            "val_mae_deg": val_mae, "train_lights": train_lights})

    model.train()
    done = False
    window_t, window_n, run_loss = time.perf_counter(), 0, []
    while not done and state["epoch"] < t_cfg.epochs:
        loader.batch_sampler.set_epoch(state["epoch"])
        for i, b in enumerate(loader):
            if i < state["batch_in_epoch"]:  # resume mid-epoch on the same deterministic order
                continue
            x, n, m = b["image"].to(device), b["normal"].to(device), b["mask"].to(device)
            # progress = share of the step budget, or of the time budget when that is nearer
            progress = max(state["step"] / t_cfg.max_steps, (time.perf_counter() - t_start) / budget)
            lr = t_cfg.lr * lr_factor(cfg, progress)
            for g in opt.param_groups:
                g["lr"] = lr
            final, coarse = model(x, m)
            loss, parts = total_loss(final, coarse, n, m, cfg.net.mode)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            state["step"] += 1
            state["batch_in_epoch"] = i + 1
            window_n += len(x)
            run_loss.append(float(loss.detach()))
            if bar:
                bar.update(1)
                bar.set_postfix(loss=f"{np.mean(run_loss[-50:]):.4f}", epoch=state["epoch"])
            stop = state["step"] >= t_cfg.max_steps or time.perf_counter() - t_start >= budget
            if state["step"] % t_cfg.val_every == 0 or stop:
                v = validate(model, val_loader, t_cfg.val_max_patches)
                rate = window_n / (time.perf_counter() - window_t)
                rec = {"step": state["step"], "epoch": state["epoch"], "loss": float(np.mean(run_loss)),
                       **{f"loss_{k}": val for k, val in parts.items()}, "lr": lr,
                       "val_mae_deg": v, "patches_per_s": rate,
                       "elapsed_s": time.perf_counter() - t_start}
                log.write(json.dumps(rec) + "\n")
                log.flush()
                if v < state["best_val"]:
                    state["best_val"] = v
                    checkpoint("best.pt", v)
                checkpoint("last.pt", v)
                window_t, window_n, run_loss = time.perf_counter(), 0, []
            if stop:
                done = True
                break
        if not done:
            state["epoch"] += 1
            state["batch_in_epoch"] = 0
    checkpoint("last.pt")
    log.close()
    if bar:
        bar.close()
    plot_metrics(out / "metrics.jsonl", out / "metrics.png")
    return {"steps": state["step"], "epochs": state["epoch"], "best_val_mae_deg": state["best_val"],
            "elapsed_s": time.perf_counter() - t_start, "n_params": n_params}


def plot_metrics(jsonl: Path, png: Path) -> Path | None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    recs = [json.loads(l) for l in jsonl.read_text().splitlines() if l.strip()]
    if not recs:
        return None
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
    steps = [r["step"] for r in recs]
    ax[0].plot(steps, [r["loss"] for r in recs])
    ax[0].set(xlabel="step", ylabel="training loss", yscale="log")
    ax[1].plot(steps, [r["val_mae_deg"] for r in recs], color="C1")
    ax[1].set(xlabel="step", ylabel="validation MAE (deg)")
    fig.tight_layout()
    fig.savefig(png, dpi=90)
    plt.close(fig)
    return png


def export_checkpoint(src: str | Path, dst: str | Path, **info) -> Path:
    """A slim copy for shipping: weights, config and provenance, without optimizer/RNG state."""
    _, cfg, ck = load_checkpoint(src)
    keep = {k: ck[k] for k in ("data_hash", "n_params", "val_mae_deg", "state", "train_lights") if k in ck}
    model = DualCueNet(cfg.net_config())
    model.load_state_dict(ck["model"])
    return save_checkpoint(Path(dst), model, cfg, {**keep, **info})
