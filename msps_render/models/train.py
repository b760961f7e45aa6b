"""Training: joint SCN+PCN training with Adam, checkpoints, resume, metrics log and plot.

Joint (end-to-end) training is the default: the total loss is L_scn on the
coarse normal plus L_pcn on the final normal, so the SCN learns structure while
the PCN learns to correct it per pixel. (Staged SCN->PCN training is the same
loop run twice with `net.mode = "scn"` then `"dual"`; joint was simpler and
reached lower validation error at equal time in our runs: docs/history.md.)

`train()` composes small steps, PS-FCN style: `open_data`, `build_model`,
`start_run` (new, resumed or warm-started), then `fit`: per batch `set_lr` +
`train_step`, and at the `ValCadence` `validate` + `record` (metrics line,
best/last checkpoints).  The cadence adapts to the run: at least every
`val_every` steps, and at least `VAL_POINTS` times over the planned steps (and
over `max_minutes`), so a short run still draws a curve.  Checkpoints are `models.checkpoint`; `last.pt` holds everything
needed to resume the same schedule (optimizer, step, epoch, position, RNG state).
Fine-tuning a checkpoint on another corpus mix (`--init`): `train.freeze_bn` keeps its
BatchNorm statistics, which otherwise follow the corpus of the latest batches
(docs/history.md, stages 4 and 5).
"""
from __future__ import annotations

import hashlib
import json
import math
import shlex
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from msps_render.atomic import AppendLog, save_figure, write_text
from msps_render.dataset import read_manifest, training_lights
from msps_render.errors import InputError, not_a_dataset
from msps_render.models.accel import CPU, Accel, resolve_accel
from msps_render.models.checkpoint import load_checkpoint, save_checkpoint
from msps_render.models.losses import total_loss
from msps_render.models.metrics import angular_error
from msps_render.models.net import DualCueNet, count_parameters, rig_matrix, widen_inputs
from msps_render.models.presets import ModelConfig
from msps_render.progress import StartupStage


def data_hash(root: str | Path | Sequence[str | Path]) -> str:
    """Identity of the training data (shard checksums), so --resume refuses other data."""
    roots = [root] if isinstance(root, (str, Path)) else list(root)
    sums = []
    for r in roots:
        m = read_manifest(r)
        if m is None:
            raise not_a_dataset(r)
        sums.append({k: v["file_sha256"] for k, v in sorted(m["shards"].items())})
    return hashlib.sha256(json.dumps(sums[0] if len(sums) == 1 else sums).encode()).hexdigest()


def _sha1(path: str | Path) -> str:
    return hashlib.sha1(Path(path).read_bytes()).hexdigest()


def first_patches(loader, max_patches: int) -> list[dict]:
    """The first `max_patches` patches of `loader`'s first epoch as a list of batches, read once.

    Why: every validation used to iterate the loader again, decoding its first shards anew (most of a
    validation's cost on small checks); the patches were the same each time (a fixed seed and epoch),
    so they are now decoded once and kept (2,000 patches: ~80 MB)."""
    out, seen = [], 0
    for b in loader:
        out.append(b)
        seen += len(b["image"])
        if seen >= max_patches:
            break
    return out


@torch.no_grad()
def validate(model, loader, max_patches: int, accel: Accel = CPU) -> float:
    """Mean angular error (degrees) over object pixels of up to `max_patches` patches."""
    was = {m: m.training for m in model.modules()}  # restored per module (frozen BatchNorm stays frozen)
    model.eval()
    err_sum, n_pix, seen = 0.0, 0.0, 0
    for b in loader:
        b = accel.batch(b)
        with accel.autocast():
            pred, _ = model(b["image"], b["mask"], batch_rig(b))
        e = torch.rad2deg(angular_error(pred.float(), b["normal"])) * b["mask"]
        err_sum += e.sum()
        n_pix += b["mask"].sum()
        seen += len(b["image"])
        if seen >= max_patches:
            break
    for m, mode in was.items():
        m.train(mode)
    return float(err_sum) / max(float(n_pix), 1.0)


def lr_factor(cfg: ModelConfig, progress: float) -> float:
    """Cosine decay to 5% of the base rate as training progress goes 0 -> 1 (or constant)."""
    if cfg.train.schedule == "constant":
        return 1.0
    return 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(max(progress, 0.0), 1.0)))


@dataclass
class Run:
    """One training run: the model, its optimizer and the schedule state that `last.pt` keeps."""

    cfg: ModelConfig
    out: Path
    model: torch.nn.Module
    opt: torch.optim.Optimizer
    dhash: str
    state: dict = field(default_factory=lambda: {"step": 0, "epoch": 0, "batch_in_epoch": 0, "elapsed": 0.0,
                                                 "best_val": float("inf")})
    train_lights: dict | None = None  # the light geometry of the training data (predict compares against it)
    n_params: int = 0
    val_seconds: float = 0.0  # wall time spent validating in this process (the end summary's share)
    t_start: float = 0.0
    budget: float = float("inf")

    def elapsed(self) -> float:
        return time.perf_counter() - self.t_start

    def progress(self) -> float:
        """Share of the step budget, or of the time budget when that is nearer."""
        return max(self.state["step"] / self.cfg.train.max_steps, self.elapsed() / self.budget)

    def should_stop(self) -> bool:
        return self.state["step"] >= self.cfg.train.max_steps or self.elapsed() >= self.budget

    def checkpoint(self, name: str, val_mae: float | None = None) -> Path:
        self.state["elapsed"] = self.elapsed()
        return save_checkpoint(self.out / name, self.model, self.cfg, {
            "optimizer": self.opt.state_dict(), "state": dict(self.state),
            "torch_rng": torch.get_rng_state(), "data_hash": self.dhash, "n_params": self.n_params,
            "val_mae_deg": val_mae, "train_lights": self.train_lights})


def build_model(cfg: ModelConfig, accel: Accel = CPU) -> tuple[torch.nn.Module, torch.optim.Optimizer]:
    """The network (seeded by `train.seed`, initialised on the CPU so every device starts from the same
    weights) and its Adam optimizer."""
    torch.manual_seed(cfg.train.seed)
    model = accel.model(DualCueNet(cfg.net_config()))
    return model, torch.optim.Adam(model.parameters(), lr=cfg.train.lr, betas=tuple(cfg.train.betas))


# Settings that change how batches are read, never which: a run may resume with other values.
_READING_ONLY = {"num_workers", "cache", "channels_last"}


def _results_config(cfg: ModelConfig) -> dict:
    """The model config without the reading-only settings (same batches for any value, tested)."""
    d = cfg.model_dump()
    d["train"] = {k: v for k, v in d["train"].items() if k not in _READING_ONLY}
    return d


def start_run(run: Run, resume: bool, init: str | Path | None) -> None:
    """Restore `last.pt` (`resume`), refuse to overwrite a run, or warm-start weights from `init`."""
    last = run.out / "last.pt"
    if resume:
        if not last.is_file():
            raise InputError(last, "nothing to resume (no last.pt)")
        _, rcfg, ck = load_checkpoint(last)
        if _results_config(rcfg) != _results_config(run.cfg):
            raise InputError(last, "checkpoint was trained with a different model config")
        if ck.get("data_hash") != run.dhash:
            raise InputError(last, "checkpoint was trained on a different dataset")
        run.model.load_state_dict(ck["model"])
        run.opt.load_state_dict(ck["optimizer"])
        run.state.update(ck["state"])
        torch.set_rng_state(ck["torch_rng"])
    elif last.is_file():
        raise InputError(run.out, "already holds a training run; use --resume to continue it")
    elif init is not None:
        _, icfg, ick = load_checkpoint(init)
        adds_cues = _adds_input_cues(icfg.net, run.cfg.net)
        if icfg.net != run.cfg.net and not adds_cues:
            raise InputError(init, f"--init checkpoint has a different network ({icfg.preset}: {icfg.net})")
        if adds_cues:  # same net plus input cues: the new inputs start at zero weight
            widen_inputs(run.model, ick["model"])
        else:
            run.model.load_state_dict(ick["model"])
        from msps_render.dataset.manifest import merge_training_lights

        run.train_lights = merge_training_lights(run.train_lights, ick.get("train_lights"))
        run.state["init_from"] = f"{Path(init).name} sha1:{_sha1(init)[:12]}"


INPUT_CUES = ("chroma_cue", "lambert_cue", "lambert_scn")


def _adds_input_cues(old, new) -> bool:
    """`new` is `old` with one or more input cues switched on (and nothing else changed)."""
    added = [c for c in INPUT_CUES if getattr(new, c) and not getattr(old, c)]
    removed = [c for c in INPUT_CUES if getattr(old, c) and not getattr(new, c)]
    update = {c: True for c in added}
    if "lambert_cue" in added or "lambert_scn" in added:
        update["cue_gain"] = new.cue_gain  # the gain comes with the cue
    return bool(added) and not removed and old.model_copy(update=update) == new


def batch_rig(batch: dict) -> torch.Tensor:
    """(B, 3, 3) rig matrix of a batch (what a `lambert_cue` net takes; `net.rig_matrix`, the one spelling)."""
    return rig_matrix(batch["light_dirs"], batch["crosstalk"])


def set_train_mode(model: torch.nn.Module, freeze_bn: bool) -> None:
    """Training mode; with `freeze_bn` BatchNorm keeps normalising with its running statistics
    and does not update them, so a fine-tune cannot drift them toward the last batches' corpus."""
    model.train()
    if freeze_bn:
        for m in model.modules():
            if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
                m.eval()


def set_lr(opt: torch.optim.Optimizer, lr: float) -> None:
    for g in opt.param_groups:
        g["lr"] = lr


def augment(train_cfg, batch: dict, step: int) -> dict:
    """The batch after the configured augmentations (`train.mirror_aug`, `train.albedo_aug`).

    Each draws from its own stream seeded by (seed, step), so a resumed run augments the same
    patches and a run with `mirror_aug` alone is unchanged by the albedo options."""
    if train_cfg.mirror_aug > 0:
        from msps_render.models.symmetry import mirror_batch

        rng = np.random.default_rng((train_cfg.seed, step))
        batch = mirror_batch(batch, rng.random(len(batch["image"])) < train_cfg.mirror_aug)
    if train_cfg.albedo_aug > 0:
        from msps_render.models.augment import albedo_batch

        rng = np.random.default_rng((train_cfg.seed, step, 1))
        which = rng.random(len(batch["image"])) < train_cfg.albedo_aug
        if train_cfg.albedo_aug_scope == "lambertian":  # only where the tint is exact and physical
            which &= batch["lambertian"].numpy().astype(bool)
        batch = albedo_batch(batch, which, rng)
    return batch


def train_step(run: Run, batch: dict, accel: Accel = CPU) -> tuple[torch.Tensor, dict]:
    """One optimizer step on one batch: (loss, loss parts), left on the device (reading them waits
    for the GPU, so `fit` does that only when it records)."""
    batch = accel.batch(augment(run.cfg.train, batch, run.state["step"]))
    with accel.autocast():
        final, coarse = run.model(batch["image"], batch["mask"], batch_rig(batch))
    loss, parts = total_loss(final.float(), None if coarse is None else coarse.float(), batch["normal"],
                             batch["mask"], run.cfg.net.mode)
    run.opt.zero_grad(set_to_none=True)
    loss.backward()
    run.opt.step()
    return loss, parts


def record(run: Run, log, val_mae: float, losses: list, parts: dict, lr: float, rate: float) -> None:
    """One metrics line; `best.pt` when validation improved; `last.pt` always."""
    s = run.state
    rec = {"step": s["step"], "epoch": s["epoch"], "loss": float(torch.stack(losses).float().mean()),
           **{f"loss_{k}": float(val) for k, val in parts.items()}, "lr": lr,
           "val_mae_deg": val_mae, "patches_per_s": rate, "elapsed_s": run.elapsed()}
    log.write(json.dumps(rec) + "\n")
    log.flush()
    if val_mae < s["best_val"]:
        s["best_val"] = val_mae
        run.checkpoint("best.pt", val_mae)
    run.checkpoint("last.pt", val_mae)


def trim_metrics(jsonl: Path, step: int) -> None:
    """Keep the whole records of `jsonl` up to `step` (the checkpoint the run starts from; 0 for a new
    run): a run stopped by a full disk may end in a torn line, or in records whose checkpoint was never
    written."""
    if not jsonl.is_file():
        return
    keep = []
    for line in jsonl.read_text().splitlines():
        try:
            rec = json.loads(line)
        except ValueError:
            continue
        if isinstance(rec, dict) and rec.get("step", 0) <= step:
            keep.append(line + "\n")
    write_text(jsonl, "".join(keep))


def open_data(data, val, verify: bool, cache: bool | str = False):
    """(training, validation) PatchDatasets; `InputError` if either has no patches.

    `cache` (`train.cache`): keep the training corpus decoded in memory -- True, False, or
    "auto" (when it takes at most 40 % of the available memory, `data.should_cache`)."""
    from msps_render.data import PatchDataset, available_memory_bytes, should_cache

    train_ds = PatchDataset(data, verify=verify)
    if cache is True or (cache == "auto" and should_cache(train_ds.decoded_bytes(), available_memory_bytes())):
        train_ds.keep_decoded()
    val_ds = PatchDataset(val, verify=verify)
    if len(train_ds) == 0 or len(val_ds) == 0:
        raise InputError(train_ds.root if len(train_ds) == 0 else val, "dataset has no patches")
    return train_ds, val_ds


VAL_POINTS = 20  # validations a run plans for at least (its curve's points)
VAL_MAX_SHARE = 0.2  # time-triggered validations take at most about this share of the wall time


@dataclass
class ValCadence:
    """When to validate: every `every` steps (`val_every`, or denser so that the planned steps give
    `VAL_POINTS` points), with a time budget also after `budget / VAL_POINTS` seconds without one -- but
    never so often that validation takes more than `VAL_MAX_SHARE` of the wall time (a 2000-patch check
    costs ~30 training steps of the cpu preset: in a short run the step cadence alone made validation
    most of the run).  Validation changes no training state, so the weights of step N do not depend on
    when it ran; only which checkpoint is `best.pt` can."""

    every: int
    seconds: float = float("inf")
    last_t: float = 0.0
    val_s: float = 0.0
    last_step: int = 0

    @classmethod
    def plan(cls, cfg: ModelConfig, batches_per_epoch: int, budget_s: float, now: float,
             step: int = 0) -> "ValCadence":
        t = cfg.train
        steps = min(t.max_steps, t.epochs * max(batches_per_epoch, 1))
        return cls(max(1, min(t.val_every, steps // VAL_POINTS)), budget_s / VAL_POINTS, now, last_step=step)

    def due(self, step: int, now: float) -> bool:
        since = now - self.last_t
        if since < self.val_s * (1 - VAL_MAX_SHARE) / VAL_MAX_SHARE:
            return False
        return step - self.last_step >= self.every or since >= self.seconds

    def done(self, started: float, now: float, step: int | None = None) -> None:
        self.val_s, self.last_t = now - started, now
        if step is not None:
            self.last_step = step


def fit(run: Run, loader, val_loader, log, bar, accel: Accel = CPU) -> None:
    """Epochs of `train_step` until the step or time budget; validate + `record` when `ValCadence` says."""
    t_cfg, state = run.cfg.train, run.state
    set_train_mode(run.model, t_cfg.freeze_bn)
    cadence = ValCadence.plan(run.cfg, len(loader), run.budget, time.perf_counter(), state["step"])
    done = run.should_stop()  # a finished run resumed does no extra step
    window_t, window_n, run_loss = time.perf_counter(), 0, []
    while not done and state["epoch"] < t_cfg.epochs:
        loader.set_epoch(state["epoch"])
        for i, b in enumerate(loader):
            if i < state["batch_in_epoch"]:  # resume mid-epoch on the same deterministic order
                continue
            lr = t_cfg.lr * lr_factor(run.cfg, run.progress())
            set_lr(run.opt, lr)
            loss, parts = train_step(run, b, accel)
            state["step"] += 1
            state["batch_in_epoch"] = i + 1
            window_n += len(b["image"])
            run_loss.append(loss.detach())
            if bar:
                bar.update(state["step"])
            stop = run.should_stop()
            if stop or cadence.due(state["step"], time.perf_counter()):
                t0 = time.perf_counter()
                v = validate(run.model, val_loader, t_cfg.val_max_patches, accel)
                record(run, log, v, run_loss, parts, lr, window_n / (t0 - window_t))
                cadence.done(t0, time.perf_counter(), state["step"])
                run.val_seconds += cadence.val_s
                if bar:
                    loss_now = float(torch.stack(run_loss[-50:]).mean()) if run_loss else 0.0
                    bar.note(f"loss {loss_now:.4f}, val {v:.2f} deg, best {state['best_val']:.2f} deg, epoch "
                             f"{state['epoch']}, {window_n / max(t0 - window_t, 1e-9):.0f} patches/s")
                window_t, window_n, run_loss = time.perf_counter(), 0, []
            if stop:
                done = True
                break
        if not done:
            state["epoch"] += 1
            state["batch_in_epoch"] = 0


def train(cfg: ModelConfig, data: str | Path | Sequence[str | Path], val: str | Path, out: str | Path,
          resume: bool = False, device: str = "auto", progress: bool = True, verify: bool = True,
          init: str | Path | None = None) -> dict:
    """Train from scratch, continue a run (`resume`), or warm-start from another run's weights.

    `init` loads only the weights of a checkpoint of the same network (fresh optimizer and
    schedule): how a longer run or a fine-tune on a new corpus starts from an earlier model.
    """
    from msps_render.data import make_loader

    out, t_cfg = Path(out), cfg.train
    if t_cfg.freeze_bn and init is None and not resume:  # before reading (maybe caching) any data
        raise InputError("train.freeze_bn", "needs --init: a new network has no BatchNorm statistics to keep")
    accel = resolve_accel(device, t_cfg.precision, t_cfg.channels_last)
    what = ["verifying every shard"] if verify else []
    what += {True: ["decoding it into memory"], "auto": ["decoding it into memory if it fits"]}.get(t_cfg.cache, [])
    with StartupStage("train", "opening the corpus" + (f" ({', '.join(what)})" if what else ""), progress) as st:
        train_ds, val_ds = open_data(data, val, verify, t_cfg.cache)
        st.done = (f"{len(train_ds):,} training patches in {len(train_ds.shards)} shards"
                   f"{' (in memory)' if train_ds.is_cached else ''}, {len(val_ds):,} validation patches; "
                   f"{cfg.preset} on {accel.describe()}")
    model, opt = build_model(cfg, accel)
    run = Run(cfg, out, model, opt, data_hash(data), train_lights=training_lights(data))
    start_run(run, resume, init)
    out.mkdir(parents=True, exist_ok=True)
    trim_metrics(out / "metrics.jsonl", run.state["step"])  # a new run: none left by a run never checkpointed
    write_text(out / "config.json", json.dumps(cfg.model_dump(mode="json"), indent=1))
    loader = make_loader(train_ds, t_cfg.batch_size, shuffle=True, seed=t_cfg.seed, drop_last=True,
                         num_workers=t_cfg.num_workers, window=t_cfg.shuffle_window or None)
    val_loader = first_patches(make_loader(val_ds, 64, shuffle=True, seed=1234), t_cfg.val_max_patches)
    with AppendLog(out / "metrics.jsonl") as log:  # a full disk: one line; --resume trims (trim_metrics)
        run.n_params = count_parameters(model)
        run.t_start = time.perf_counter() - run.state["elapsed"]
        run.budget = t_cfg.max_minutes * 60 if t_cfg.max_minutes else float("inf")
        bar = None
        if progress:  # a bar on a terminal, plain lines every 15 s in a log file (`LineTicker`)
            from msps_render.progress import LineTicker

            planned = min(t_cfg.max_steps, t_cfg.epochs * max(len(loader), 1))  # a time budget may end it sooner
            bar = LineTicker("train", planned, unit="step", start=run.state["step"], first_line=True,
                             budget_s=run.budget - run.state["elapsed"] if run.budget < float("inf") else None)
        ok = False
        try:
            fit(run, loader, val_loader, log, bar, accel)
            run.checkpoint("last.pt")
            ok = True
        finally:
            if bar:  # closed before an error's line is printed (a failed run: no last progress line)
                bar.close(ok)
    plot_metrics(out / "metrics.jsonl", out / "metrics.png")
    s = run.state
    batches = max(len(loader), 1)
    return {"steps": s["step"], "epochs": round(s["epoch"] + s["batch_in_epoch"] / batches, 3),
            "patches_seen": s["step"] * t_cfg.batch_size, "corpus_patches": len(train_ds),
            "best_val_mae_deg": s["best_val"], "elapsed_s": run.elapsed(), "n_params": run.n_params,
            "validation_s": run.val_seconds, "device": accel.describe(), "preset": cfg.preset, "out": str(out)}


def summary_lines(r: dict) -> list[str]:
    """The end of `msps train`, for a person: what ran, how far, how well, where the result is."""
    out = Path(r["out"])
    share = r["validation_s"] / r["elapsed_s"] if r["elapsed_s"] > 0 else 0.0
    best = out / "best.pt"
    return [f"trained {r['preset']} ({r['n_params']:,} parameters) on {r['device']}: {r['steps']:,} steps, "
            f"{r['epochs']:.2f} epochs ({r['patches_seen']:,} patches of a {r['corpus_patches']:,}-patch corpus), "
            f"{r['elapsed_s'] / 60:.1f} min, {100 * share:.0f} % of it validating",
            f"best validation error: {r['best_val_mae_deg']:.2f} deg (mean angular error over object pixels)",
            f"checkpoint: {best if best.is_file() else out / 'last.pt'}  (resume: --resume; curve: "
            f"{out / 'metrics.png'})",
            f"evaluate: msps eval --data TEST_DIR --checkpoint "
            f"{shlex.quote(str(best if best.is_file() else out / 'last.pt'))} --out REPORT_DIR"]


def plot_metrics(jsonl: Path, png: Path, title: str | None = None) -> Path | None:
    """The training curve: every recorded point, training loss (mean since the previous point) and
    validation MAE, the best marked; titled with the run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    recs = [json.loads(l) for l in jsonl.read_text().splitlines() if l.strip()]
    if not recs:
        return None
    if title is None:
        title = jsonl.parent.name
        cfg_file = jsonl.parent / "config.json"
        if cfg_file.is_file():
            c = json.loads(cfg_file.read_text())
            title += f" ({c.get('preset', '?')}, {c.get('net', {}).get('mode', '?')})"
    steps = [r["step"] for r in recs]
    val = [r["val_mae_deg"] for r in recs]
    loss = [r["loss"] for r in recs]
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    ax[0].plot(steps, loss, ".-", ms=4, lw=1)
    ax[0].set(xlabel="step", ylabel="training loss (mean since previous point)", yscale="log")
    ax[1].plot(steps, val, ".-", ms=4, lw=1, color="C1")
    b = int(np.argmin(val))
    ax[1].plot([steps[b]], [val[b]], "*", ms=11, color="C3")
    ax[1].set(xlabel="step", ylabel="validation MAE (deg)")
    ax[1].set_title(f"best (star): {val[b]:.2f} deg at step {steps[b]}", fontsize=9)
    for a in ax:
        a.grid(alpha=0.3)
    mins = recs[-1].get("elapsed_s", 0) / 60
    fig.suptitle(f"{title}: {len(recs)} validations, {steps[-1]} steps, {mins:.1f} min", fontsize=10)
    fig.tight_layout()
    save_figure(fig, png, dpi=90)
    plt.close(fig)
    return png
