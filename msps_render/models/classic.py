"""Training and using the classic (any-light) network on rig shards: preset, data, loop, checkpoint, predict.

Data flow:  format-2 shards (sequential captures, S = N images per patch) --`RigPatchData`-->
batches of K lights drawn per sample (a random subset, as PS-FCN trains on 32 of its images) with
the nominal light directions and readings --`ClassicNet`--> normals --cosine loss--> Adam.
The run directory is the dual-cue trainer's: metrics.jsonl, best.pt / last.pt (resume with the
same data), metrics.png, a person-readable summary; progress as a bar on a terminal and as plain
lines in a log (`progress.LineTicker`).

Test time (`ClassicModel`): a whole frame or a real capture with all its lights; the max-pool over
lights runs in chunks, so memory is one chunk's features whatever N is.
"""
from __future__ import annotations

import json
import math
import shlex
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Sequence

import numpy as np
import torch
from pydantic import Field

from msps_render import resources
from msps_render.config_io import StrictModel, apply_overrides, check_override_keys, read_toml, validate
from msps_render.errors import InputError, brief, not_a_dataset
from msps_render.models.classic_net import ClassicNet, ClassicNetConfig, cosine_loss, count_parameters, pad4, prepare

FORMAT = "msps-classic-1"
KIND = "classic"


# ------------------------------------------------------------------ preset
class ClassicNetSection(StrictModel):
    widths: tuple[int, int, int] = Field((16, 32, 64), description="extractor widths at full, 1/2, 1/4 resolution")
    channels: int = Field(3, ge=1, le=16, description="camera channels per image (the training rig's M)")
    normalize: Literal["object", "pixel"] = Field(
        "object", description="input normalisation: 'object' divides each sample by its mean over the object "
                              "(the exposure); 'pixel' then divides each pixel's observations by their root mean "
                              "square over the lights (PS-FCN (Norm.): albedo brightness divided out)")


class ClassicTrainSection(StrictModel):
    batch_size: int = Field(16, ge=1, description="patches per step")
    lights_per_sample: int = Field(24, ge=1, description="lights drawn at random per patch and step (the "
                                                          "network takes any number at test time)")
    lr: float = Field(1e-3, gt=0, description="Adam learning rate (cosine decay to 5 %)")
    max_steps: int = Field(100000, ge=1, description="optimizer steps budget")
    max_minutes: float | None = Field(None, gt=0, description="wall-clock budget (min)")
    epochs: int = Field(50, ge=1, description="passes over the training data")
    val_every: int = Field(200, ge=1, description="validate at least every N steps")
    val_max_patches: int = Field(128, ge=1, description="validation patches per check (all their lights)")
    rotate_aug: bool = Field(True, description="rotate each patch by a random multiple of 90 deg about the "
                                               "view axis (image, normals and lights together: exact)")
    shuffle_window: int = Field(4, ge=1, description="shards decoded and shuffled together")
    seed: int = Field(0, description="seed of initialisation, data order and light draws")


class ClassicConfig(StrictModel):
    kind: Literal["classic"] = "classic"
    preset: str = Field("custom", description="preset name (recorded in checkpoints)")
    net: ClassicNetSection = ClassicNetSection()
    train: ClassicTrainSection = ClassicTrainSection()

    def net_config(self) -> ClassicNetConfig:
        return ClassicNetConfig(channels=self.net.channels, widths=tuple(self.net.widths), normalize=self.net.normalize)


SMOKE = ("train.max_minutes=2.0", "train.val_max_patches=32")


def preset_kind(path_or_name: str | Path) -> str:
    """'classic' or 'dualcue' (a preset without `kind`): which trainer `msps train PRESET` runs."""
    p = resources.find("models", path_or_name)
    if p is None:
        return "dualcue"  # the dual-cue loader says what is wrong with the name
    return str(read_toml(p).get("kind", "dualcue"))


def load_classic_config(path_or_name: str | Path, overrides=()) -> ClassicConfig:
    p = resources.find("models", path_or_name)
    if p is None:
        raise InputError(Path(path_or_name), "model preset not found")
    check_override_keys(overrides, ClassicConfig)
    return validate(ClassicConfig, apply_overrides(read_toml(p), overrides), str(p), overrides)


# ------------------------------------------------------------------ data
@dataclass
class Shard:
    """One decoded format-2 shard, as the classic network reads it."""

    image: np.ndarray  # (n, N, P, P, M) float16, one image per light (sequential)
    normal: np.ndarray  # (n, P, P, 3)
    mask: np.ndarray  # (n, P, P) bool
    dirs: np.ndarray  # (n, N, 3) nominal light directions of each patch's frame
    readings: np.ndarray  # (n, N, M) nominal reading of each light in each channel


def three_as_images(image: np.ndarray, light_dirs: np.ndarray, crosstalk: np.ndarray, frame_index: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A three-light multispectral image read as three grey images (the seed paper's comparison: PS-FCN
    "trained on the three channels as three images"): image k = channel k, lit by light k, whose reading
    in it is crosstalk[k, k] (the leak of the other two lights is left in, as a three-image method sees it).
    (n, P, P, 3) -> images (n, 3, P, P, 1), dirs (n, 3, 3), readings (n, 3, 1)."""
    images = np.moveaxis(image, -1, 1)[..., None]
    dirs = np.asarray(light_dirs, np.float32)[frame_index]
    readings = np.diagonal(np.asarray(crosstalk, np.float32), axis1=-2, axis2=-1)[frame_index][..., None]
    return images, dirs, readings


def read_rig_shard(path: Path) -> Shard:
    """A format-2 shard of a sequential capture, decoded (or a three-light format-1 shard as three grey
    images, `three_as_images`); InputError naming it otherwise."""
    from msps_render.dataset import schema as K
    from msps_render.dataset.reader import format_version, open_shard, read_rig_patches, read_rigs, shard_errors

    with shard_errors(path), open_shard(path) as h:
        if format_version(h) == K.FORMAT_VERSION:
            fi = h[K.PATCH_FRAME_INDEX][()]
            images, dirs, readings = three_as_images(h[K.PATCH_IMAGE][()], h[K.FRAME_LIGHT_DIRS][()],
                                                     h[K.FRAME_CROSSTALK][()], fi)
            return Shard(images, h[K.PATCH_NORMAL][()], h[K.PATCH_MASK][()].astype(bool), dirs, readings)
        p = read_rig_patches(h)
        _, nominal = read_rigs(h)
    for r in nominal:
        if r.shot_list != tuple((k,) for k in range(r.n_lights)):
            raise InputError(path, f"the classic network reads one image per light (a sequential capture); "
                                   f"this rig has {r.describe()}")
        if r.has_point_lights:
            raise InputError(path, "the classic network assumes far (directional) lights; this rig has near "
                                   "point lights")
    fi = p["frame_index"]
    dirs = np.stack([r.light_dirs for r in nominal]).astype(np.float32)[fi]
    readings = np.stack([np.asarray(r.crosstalk).T for r in nominal]).astype(np.float32)[fi]
    return Shard(p["image"], p["normal"], p["mask"].astype(bool), dirs, readings)


def rig_shard_paths(root: str | Path | Sequence[str | Path]) -> list[Path]:
    """The shards of one dataset, or of several trained on as one (`--data` repeated), in that order."""
    from msps_render.dataset import read_manifest

    paths = []
    for r in ([root] if isinstance(root, (str, Path)) else root):
        r = Path(r)
        m = read_manifest(r)
        if m is None:
            raise not_a_dataset(r)
        if not m["shards"]:
            raise InputError(r, "dataset has no rendered shard yet")
        paths += [r / "shards" / n for n in sorted(m["shards"])]
    return paths


def _rotate(b: dict, k: int) -> dict:
    """Rotate a batch by k x 90 deg counter-clockwise in the image: pixels, normals' and lights' x, y."""
    if k == 0:
        return b
    c, s = [(1, 0), (0, 1), (-1, 0), (0, -1)][k]
    R = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=torch.float32, device=b["dirs"].device)
    out = dict(b)
    out["image"] = torch.rot90(b["image"], k, dims=(-2, -1))
    out["mask"] = torch.rot90(b["mask"], k, dims=(-2, -1))
    n = torch.rot90(b["normal"], k, dims=(-2, -1))
    out["normal"] = torch.einsum("ij,bjhw->bihw", R, n)
    out["dirs"] = b["dirs"] @ R.T
    return out


class RigPatchData:
    """Batches of patches with K lights each, in a seeded order: shards in windows, patches shuffled
    within a window, a fresh light subset per patch.  Position (epoch, batch) is the resume state."""

    def __init__(self, root, batch_size: int, lights: int | None, seed: int, window: int = 4):
        self.paths = rig_shard_paths(root)
        self.batch_size, self.lights, self.seed, self.window = batch_size, lights, seed, window
        self.n_patches = self._count()

    def _count(self) -> int:
        """Patches in all shards; refuses shards of other rig sizes in one line (a window's shards are
        cut into batches together, so every patch needs the same number of images and channels)."""
        from msps_render.dataset import schema as K
        from msps_render.dataset.reader import open_shard

        n, size = 0, None
        for p in self.paths:
            with open_shard(p) as h:
                k = int(h.attrs["n_patches"])
                here = (int(h.attrs.get(K.ATTR_N_SHOTS, 0)), int(h.attrs.get(K.ATTR_N_CHANNELS, 0)))
            n += k
            if k == 0:  # no patch, nothing to cut (its attributes say 0 images)
                continue
            if size is None:
                size, first = here, p
            elif here != size:
                raise InputError(p, f"{here[0]} images of {here[1]} channel(s) per patch, but {first} has "
                                    f"{size[0]} of {size[1]}: train on datasets of one rig size")
        return n

    def __len__(self) -> int:
        return max(1, self.n_patches // self.batch_size)

    def batches(self, epoch: int):
        rng = np.random.default_rng([self.seed, epoch])
        order = rng.permutation(len(self.paths))
        for w in range(0, len(order), self.window):
            shards = [read_rig_shard(self.paths[i]) for i in order[w:w + self.window]]
            cat = Shard(*(np.concatenate([getattr(s, f) for s in shards]) for f in
                          ("image", "normal", "mask", "dirs", "readings")))
            idx = rng.permutation(len(cat.image))
            for b0 in range(0, len(idx) - self.batch_size + 1, self.batch_size):
                yield self.batch(cat, idx[b0:b0 + self.batch_size], rng)

    def batch(self, s: Shard, idx: np.ndarray, rng: np.random.Generator) -> dict:
        N = s.image.shape[1]
        K = min(self.lights or N, N)
        pick = np.stack([np.sort(rng.choice(N, K, replace=False)) for _ in idx]) if K < N else \
            np.broadcast_to(np.arange(N), (len(idx), N))
        rows = idx[:, None]
        img = s.image[rows, pick].astype(np.float32)  # (B, K, P, P, M)
        return {"image": torch.from_numpy(np.ascontiguousarray(img.transpose(0, 1, 4, 2, 3))),
                "dirs": torch.from_numpy(s.dirs[rows, pick]),
                "readings": torch.from_numpy(s.readings[rows, pick]),
                "normal": torch.from_numpy(np.ascontiguousarray(s.normal[idx].astype(np.float32).transpose(0, 3, 1, 2))),
                "mask": torch.from_numpy(s.mask[idx])}


def angular_error_sum(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> tuple[float, float]:
    cos = (pred * gt).sum(1).clamp(-1, 1)
    err = torch.rad2deg(torch.acos(cos))[mask]
    return float(err.sum()), float(mask.sum())


@torch.no_grad()
def validate_model(model: ClassicNet, val: list[dict], chunk: int = 16) -> float:
    model.eval()
    s = n = 0.0
    for b in val:
        x = prepare(b["image"], b["readings"], b["mask"], model.cfg.normalize)
        e, c = angular_error_sum(model(x, b["dirs"], chunk), b["normal"], b["mask"])
        s, n = s + e, n + c
    model.train()
    return s / max(n, 1.0)


# ------------------------------------------------------------------ checkpoints
def save(path: Path, model: ClassicNet, cfg: ClassicConfig, extra: dict) -> Path:
    from msps_render.models.checkpoint import save_dict

    return save_dict(path, {"model": model.state_dict(), "config": cfg.model_dump(mode="json"),
                            "preset": cfg.preset, "format": FORMAT, **extra})


def load(path: str | Path) -> tuple[ClassicNet, ClassicConfig, dict]:
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "checkpoint not found")
    try:
        ck = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as e:
        from msps_render.models.checkpoint import not_torch_reason

        raise InputError(p, not_torch_reason(p) or f"not a loadable checkpoint ({brief(str(e), 100)})") from None
    if not isinstance(ck, dict) or ck.get("format") != FORMAT:
        raise InputError(p, "not an msps classic-network checkpoint (the dual-cue network's checkpoints "
                            "read one three-light image: use them on three-light data)")
    cfg = ClassicConfig.model_validate(ck["config"])
    model = ClassicNet(cfg.net_config())
    model.load_state_dict(ck["model"])
    model.eval()
    return model, cfg, ck


# ------------------------------------------------------------------ training
@dataclass
class RunState:
    step: int = 0
    epoch: int = 0
    batch_in_epoch: int = 0
    elapsed: float = 0.0
    best_val: float = float("inf")
    init_from: str = ""  # `--init`: the checkpoint whose weights the run started from
    history: list = field(default_factory=list)


def _check_start(out: Path, resume: bool, init, cfg: ClassicConfig) -> dict | None:
    """Refuse, in one line, what would lose or mix runs: resuming nothing, overwriting a run, or a
    warm start from another network.  Returns the `init` checkpoint (read once), else None."""
    last = out / "last.pt"
    if resume and not last.is_file():
        raise InputError(last, "nothing to resume (no last.pt)")
    if resume and init is not None:
        raise InputError("--init", "a resumed run keeps its own weights; give --init to a new run only")
    if not resume and last.is_file():
        raise InputError(out, "already holds a training run; use --resume to continue it")
    if init is None:
        return None
    _, icfg, ick = load(init)
    if (icfg.net.widths, icfg.net.channels) != (cfg.net.widths, cfg.net.channels):  # the weights' shapes; the
        # input normalisation may change (fine-tuning a network to another one)
        raise InputError(init, f"--init checkpoint has a different network ({icfg.preset}: {icfg.net})")
    return ick


def _device(device: str) -> torch.device:
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cuda" and not torch.cuda.is_available():
        raise InputError("--device", "cuda asked for, but torch sees no CUDA device")
    return torch.device(device)


def _to(b: dict, dev: torch.device) -> dict:
    return b if dev.type == "cpu" else {k: v.to(dev, non_blocking=True) for k, v in b.items()}


def train_classic(cfg: ClassicConfig, data, val, out, resume: bool = False, progress: bool = True,
                  device: str = "auto", init: str | Path | None = None) -> dict:
    """Train the classic network on rig shards; checkpoints and metrics in `out`; returns the summary.

    `resume` continues the run in `out` (its `last.pt`: weights, optimizer, schedule, data position);
    `init` warm-starts a new run from a checkpoint's weights (same network) with a fresh optimizer and
    schedule, e.g. to train a shipped model further on a larger corpus, whose run folder is gone.
    """
    from msps_render.atomic import AppendLog, write_text
    from msps_render.models.train import _sha1, data_hash, plot_metrics
    from msps_render.progress import LineTicker, StartupStage

    t = cfg.train
    out = Path(out)
    init_ck = _check_start(out, resume, init, cfg)  # one line before any data is read
    torch.manual_seed(t.seed)
    dev = _device(device)
    with StartupStage("train", "opening the corpus and reading the validation patches", progress) as stage:
        train_data = RigPatchData(data, t.batch_size, t.lights_per_sample, t.seed, t.shuffle_window)
        val_data = RigPatchData(val, 16, None, 1234, 1)
        val_batches, seen = [], 0
        for b in val_data.batches(0):  # read once, all lights
            val_batches.append(b)
            seen += len(b["mask"])
            if seen >= t.val_max_patches:
                break
        stage.done = f"{train_data.n_patches:,} training patches, {seen:,} validation patches; {cfg.preset} on {dev}"
    if not val_batches:
        raise InputError(val, "validation set has fewer patches than one batch (16)")
    C = int(val_batches[0]["image"].shape[2])
    if C != cfg.net.channels:
        raise InputError(val, f"the data has {C} camera channel(s), the preset's network takes {cfg.net.channels} "
                              f"(set net.channels = {C})")
    val_batches = [_to(b, dev) for b in val_batches]
    model = ClassicNet(cfg.net_config()).to(dev)
    opt = torch.optim.Adam(model.parameters(), t.lr)
    dhash = data_hash(data)
    st = RunState()
    if resume and (out / "last.pt").is_file():
        _, _, ck = load(out / "last.pt")
        if ck.get("data_hash") != dhash:
            raise InputError(out / "last.pt", "--resume with other training data than the run's")
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])  # its tensors follow the model's device
        st = RunState(**{k: v for k, v in ck["state"].items() if k in RunState.__dataclass_fields__})
        torch.set_rng_state(ck["torch_rng"])
    elif init_ck is not None:
        model.load_state_dict(init_ck["model"])
        st.init_from = f"{Path(init).name} sha1:{_sha1(init)[:12]}"
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "config.json", json.dumps(cfg.model_dump(mode="json"), indent=1))
    n_params = count_parameters(model)
    budget = t.max_minutes * 60 if t.max_minutes else float("inf")
    planned = min(t.max_steps, t.epochs * len(train_data))
    t0 = time.perf_counter() - st.elapsed

    def ckpt(name: str, v: float | None) -> Path:
        st.elapsed = time.perf_counter() - t0
        return save(out / name, model, cfg, {"optimizer": opt.state_dict(), "torch_rng": torch.get_rng_state(),
                                             "state": {k: v for k, v in st.__dict__.items() if k != "history"},
                                             "data_hash": dhash, "n_params": n_params, "val_mae_deg": v})

    ticker = LineTicker("train", planned, enabled=progress, unit="step", start=st.step, first_line=True,
                        budget_s=budget - st.elapsed if budget < float("inf") else None)
    done = st.step >= t.max_steps
    losses, window_t, window_n, last_val = [], time.perf_counter(), 0, time.perf_counter()
    val_s = 0.0
    with AppendLog(out / "metrics.jsonl") as log:
        while not done and st.epoch < t.epochs:
            for i, b in enumerate(train_data.batches(st.epoch)):
                if i < st.batch_in_epoch:
                    continue
                if t.rotate_aug:
                    b = _rotate(b, int(torch.randint(4, (1,))))
                b = _to(b, dev)
                prog = max(st.step / t.max_steps, (time.perf_counter() - t0) / budget)
                lr = t.lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(prog, 1.0))))
                for g in opt.param_groups:
                    g["lr"] = lr
                x = prepare(b["image"], b["readings"], b["mask"], model.cfg.normalize)
                loss = cosine_loss(model(x, b["dirs"]), b["normal"], b["mask"])
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                st.step += 1
                st.batch_in_epoch = i + 1
                window_n += len(b["mask"])
                losses.append(loss.item())
                stop = st.step >= t.max_steps or time.perf_counter() - t0 >= budget
                due = st.step % t.val_every == 0 or time.perf_counter() - last_val > max(budget / 20, 60.0)
                if stop or due:
                    tv = time.perf_counter()
                    v = validate_model(model, val_batches)
                    val_s += time.perf_counter() - tv
                    rate = window_n / max(tv - window_t, 1e-9)
                    rec = {"step": st.step, "epoch": st.epoch, "loss": float(np.mean(losses)) if losses else None,
                           "val_mae_deg": v, "lr": lr, "patches_per_s": rate,
                           "elapsed_s": time.perf_counter() - t0}
                    log.write(json.dumps(rec) + "\n")
                    if v < st.best_val:
                        st.best_val = v
                        ckpt("best.pt", v)
                    ckpt("last.pt", v)
                    ticker.note(f"val {v:.2f} deg, best {st.best_val:.2f} deg, {rate:.1f} patches/s")
                    losses, window_t, window_n, last_val = [], time.perf_counter(), 0, time.perf_counter()
                ticker.update(st.step)
                if stop:
                    done = True
                    break
            if not done:
                st.epoch += 1
                st.batch_in_epoch = 0
    ticker.close()
    ckpt("last.pt", st.best_val if st.best_val < float("inf") else None)
    plot_metrics(out / "metrics.jsonl", out / "metrics.png", title=f"{cfg.preset}")
    elapsed = time.perf_counter() - t0
    return {"steps": st.step, "epochs": round(st.epoch + st.batch_in_epoch / len(train_data), 3),
            "patches_seen": st.step * t.batch_size, "corpus_patches": train_data.n_patches,
            "lights_per_sample": t.lights_per_sample, "best_val_mae_deg": st.best_val, "elapsed_s": elapsed,
            "validation_s": val_s, "n_params": n_params, "device": str(dev), "preset": cfg.preset, "out": str(out),
            **({"init_from": st.init_from} if st.init_from else {})}


# ------------------------------------------------------------------ test time
@dataclass
class ClassicModel:
    """A loaded classic checkpoint, as `msps eval` / `predict` / `bench-real` use it."""

    net: ClassicNet
    cfg: ClassicConfig
    path: str
    chunk: int = 8  # lights per extractor pass (memory: one chunk's features)

    @property
    def info(self) -> dict:
        return {"preset": self.cfg.preset, "what": f"classic network ({self.cfg.preset}, {self.path})"}

    @torch.no_grad()
    def normals(self, shots: np.ndarray, dirs: np.ndarray, readings: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """(H, W, 3) unit normals from per-light images (N, H, W, M), directions (N, 3), readings (N, M)."""
        N, H, W, M = shots.shape
        if M != self.cfg.net.channels:
            raise InputError(self.path, f"the network takes {self.cfg.net.channels}-channel images, got {M}")
        x = torch.from_numpy(np.ascontiguousarray(shots.transpose(0, 3, 1, 2), np.float32))[None]
        m = torch.from_numpy(np.asarray(mask, bool))[None]
        x = prepare(x, torch.from_numpy(np.asarray(readings, np.float32))[None], m, self.net.cfg.normalize)
        x, (ph, pw) = pad4(x)
        n = self.net(x, torch.from_numpy(np.asarray(dirs, np.float32))[None], self.chunk)[0]
        n = n[:, :H, :W].permute(1, 2, 0).numpy()
        return np.where(np.asarray(mask, bool)[..., None], n, 0.0).astype(np.float32)

    def predict_three(self, image: np.ndarray, light_dirs: np.ndarray, crosstalk: np.ndarray,
                      mask: np.ndarray) -> np.ndarray:
        """A three-light multispectral image (H, W, 3) read as three grey images (`three_as_images`);
        a network trained on 3-channel images takes each grey image in all three channels."""
        if self.cfg.net.channels != 1:
            image = np.asarray(image)
            imgs, dirs, readings = three_as_images(image[None], light_dirs[None], crosstalk[None], np.zeros(1, int))
            imgs = np.repeat(imgs, self.cfg.net.channels, axis=-1)
            return self.normals(imgs[0], dirs[0], np.repeat(readings[0], self.cfg.net.channels, axis=-1), mask)
        imgs, dirs, readings = three_as_images(image[None], light_dirs[None], crosstalk[None], np.zeros(1, int))
        return self.normals(imgs[0], dirs[0], readings[0], mask)

    def predict_frame(self, frame) -> np.ndarray:
        """A stored rig frame (`RigFrame`, sequential), with its nominal calibration."""
        r = frame.nominal
        if r.shot_list != tuple((k,) for k in range(r.n_lights)):
            raise InputError(frame.shard, f"the classic network reads one image per light; this rig has {r.describe()}")
        return self.normals(frame.shots, r.light_dirs, np.asarray(r.crosstalk).T, frame.mask)


def is_classic_checkpoint(path: str | Path) -> bool:
    """True for a readable checkpoint of this network (others are left to their own loader's errors)."""
    try:  # memory-mapped: the format key is read without loading the weights a second time
        ck = torch.load(Path(path), map_location="cpu", weights_only=True, mmap=True)
    except Exception:
        return False
    return isinstance(ck, dict) and ck.get("format") == FORMAT


def load_classic(path: str | Path) -> ClassicModel:
    net, cfg, _ = load(path)
    return ClassicModel(net, cfg, str(path))


def summary_lines(r: dict) -> list[str]:
    out = Path(r["out"])
    best = out / "best.pt"
    share = r["validation_s"] / r["elapsed_s"] if r["elapsed_s"] > 0 else 0.0
    ck = best if best.is_file() else out / "last.pt"
    return [f"trained {r['preset']} (classic network, {r['n_params']:,} parameters) on {r['device']}: "
            f"{r['steps']:,} steps, {r['epochs']:.2f} epochs ({r['patches_seen']:,} patches of a "
            f"{r['corpus_patches']:,}-patch corpus, {r['lights_per_sample']} lights each), "
            f"{r['elapsed_s'] / 60:.1f} min, {100 * share:.0f} % of it validating"
            + (f"; warm start from {r['init_from']}" if r.get("init_from") else ""),
            f"best validation error: {r['best_val_mae_deg']:.2f} deg (mean angular error over object pixels, "
            f"all lights of each validation patch)",
            f"checkpoint: {ck}  (resume: --resume; curve: {out / 'metrics.png'})",
            f"evaluate: msps eval --data TEST_DIR --checkpoint {shlex.quote(str(ck))} --out REPORT_DIR"]


def export(src: str | Path, dst: str | Path) -> Path:
    """A training checkpoint as a shipped model: weights, config and provenance, no optimizer or RNG state."""
    _, _, ck = load(src)
    from msps_render.models.checkpoint import save_dict

    return save_dict(Path(dst), {k: v for k, v in ck.items() if k not in ("optimizer", "torch_rng")})


if __name__ == "__main__":  # python -m msps_render.models.classic export SRC DST (scripts/rebuild_model.sh)
    import sys

    if len(sys.argv) != 4 or sys.argv[1] != "export":
        sys.exit("usage: python -m msps_render.models.classic export SRC.pt DST.pt")
    print(export(sys.argv[2], sys.argv[3]))
