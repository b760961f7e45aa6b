"""One test-time pipeline: a `Method` (name, predictor, steps) run on one whole image.

`msps predict`, `msps eval`, `msps bench-real`, benchmarks/ and the tests all build `Method`s here
(`resolve_predictors`, `methods`) and run them with `run`, which applies the steps stage by stage
(models/steps.py) and returns the final `State`: normals, the image the predictor saw, the colour
factor, and what each step found (`state.fits`, `trace`).

Several methods on one image share work through a `Memo`: the image-stage steps run once per image
for every predictor, and the predictor runs once per distinct input (a colour step that was not
applied leaves the image as it was, so that column costs nothing).  Reuse is by exact input bytes, so
a shared run gives the numbers a fresh one gives.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from msps_render.calibration import Rig
from msps_render.errors import InputError
from msps_render.resources import data_dir
from msps_render.models.steps import STAGES, STEPS, State, Steps

NET = "net"
LAMBERTIAN = "lambertian"
CLASSIC = "classic"  # the any-light network (models/classic.py), here on a three-light image read as three


@dataclass(eq=False)
class Predictor:
    """Normals from an image: a loaded checkpoint or the calibrated Lambertian baseline."""

    name: str
    kind: str  # NET (dual cue), CLASSIC (any-light network, the channels as images) or LAMBERTIAN
    model: object = None
    info: dict = field(default_factory=dict)
    train_lights: dict | None = None  # the geometry a checkpoint was trained for (`geometry_warnings`)

    @property
    def network(self) -> bool:
        return self.kind in (NET, CLASSIC)

    def image(self, image: np.ndarray, mask: np.ndarray, rig: Rig, on_batch=None) -> np.ndarray:
        """(H, W, 3) normals of a whole image (network: overlapping 40x40 tiles, blended; `on_batch(done,
        total)` hears the tiles)."""
        if not self.network:
            from msps_render.models.baseline import lambertian_ps

            return lambertian_ps(image, rig.light_dirs, rig.crosstalk, mask)
        if self.kind == CLASSIC:
            return self.model.predict_three(image, rig.light_dirs, rig.crosstalk, mask)
        from msps_render.models.tiles import predict_image

        return predict_image(self.model, image, mask, rig=rig.matrix, on_batch=on_batch)

    def patches(self, images: np.ndarray, masks: np.ndarray, rigs: list[Rig], matrices) -> np.ndarray:
        """(B, P, P, 3) normals of patches (B, P, P, 3); `matrices`: the batch's (B, 3, 3) rig matrices
        as the network takes them (the baseline solves each patch alone, unmasked)."""
        if not self.network:
            from msps_render.models.baseline import lambertian_ps

            return np.stack([lambertian_ps(x, r.light_dirs, r.crosstalk) for x, r in zip(images, rigs)])
        if self.kind == CLASSIC:
            return np.stack([self.model.predict_three(x, r.light_dirs, r.crosstalk, m)
                             for x, r, m in zip(images, rigs, np.asarray(masks, bool))])
        import torch

        with torch.no_grad():
            out = self.model(torch.from_numpy(np.ascontiguousarray(images.transpose(0, 3, 1, 2), np.float32)),
                             torch.from_numpy(np.ascontiguousarray(masks[:, None], np.float32)), matrices)[0]
        return out.numpy().transpose(0, 2, 3, 1)


@dataclass(eq=False)
class Method:
    """One column of a comparison, or the one prediction of `msps predict`."""

    name: str
    predictor: Predictor
    steps: Steps = Steps()

    @property
    def kind(self) -> str:
        return self.predictor.kind

    @property
    def info(self) -> dict:
        base = self.predictor.info.get("description", self.predictor.name)
        return {**self.predictor.info, "description": self.steps.describe(base), "steps": str(self.steps)}


def lambertian_predictor() -> Predictor:
    return Predictor(LAMBERTIAN, LAMBERTIAN, info={"description": "calibrated Lambertian photometric stereo"})


def checkpoint_predictor(path: str | Path, name: str | None = None) -> Predictor:
    """A checkpoint; unnamed, it is called after its network: net (dual cue), scn or pcn (ablations)."""
    from msps_render.models import classic
    from msps_render.models.checkpoint import load_checkpoint

    if classic.is_classic_checkpoint(path):  # the any-light network: a three-light image as three images
        m = classic.load_classic(path)
        return Predictor(name or CLASSIC, CLASSIC, m, {"description": f"classic network, channels as images "
                                                                       f"({m.cfg.preset})", "checkpoint": str(path),
                                                        "preset": m.cfg.preset})
    model, cfg, ck = load_checkpoint(path)
    mode = cfg.net.mode
    return Predictor(name or (NET if mode == "dual" else mode), NET, model,
                     {"description": "dual-cue network" if mode == "dual" else f"{mode.upper()} only (ablation)",
                      "checkpoint": str(path), "preset": cfg.preset, "mode": mode,
                      "val_mae_deg": ck.get("val_mae_deg")}, ck.get("train_lights"))


def resolve_predictors(checkpoints=(), kinds=(NET,)) -> list[Predictor]:
    """`--checkpoint [NAME=]PATH ...` and `--method net|lambertian ...` -> the predictors, checkpoints first.

    `net` stands for the checkpoints given (the shipped one when none is); checkpoints imply `net`.
    Two unnamed checkpoints of one kind are told apart by their run folder and file."""
    kinds = list(dict.fromkeys(kinds or [NET]))
    for k in kinds:
        if k not in (NET, LAMBERTIAN):
            raise InputError("--method", f"unknown method '{k}' (net or lambertian)")
    specs: list[tuple[str | None, Path]] = []
    for s in checkpoints or ():
        s = str(s)
        if "=" in s and not Path(s).is_file():
            name, _, p = s.partition("=")
            if not name.strip() or not p.strip():
                raise InputError("--checkpoint", f"'{s}': expected PATH or NAME=PATH")
            specs.append((name.strip(), Path(p.strip())))
        else:
            specs.append((None, Path(s)))
    if not specs and NET in kinds:
        specs = [(None, default_checkpoint())]
    out: list[Predictor] = []
    for name, p in specs:
        if name == LAMBERTIAN:
            raise InputError("--checkpoint", f"'{name}={p}': '{LAMBERTIAN}' names the baseline")
        if name is not None and name in [m.name for m in out]:
            raise InputError("--checkpoint", f"method name '{name}' given twice")
        m = checkpoint_predictor(p, name)
        if name is None:
            base, k = m.name, 1
            while m.name in [o.name for o in out]:
                m.name = f"{base} {p.resolve().parent.name}/{p.stem}" + (f" ({k})" if k > 1 else "")
                k += 1
        out.append(m)
    if LAMBERTIAN in kinds:
        out.append(lambertian_predictor())
    return out


def default_classic_checkpoint() -> Path:
    """The classic (any-light) network shipped in models/ (docs/history.md stage 15)."""
    p = data_dir("models") / "classic-cpu.pt"
    if not p.is_file():
        raise InputError(p, "no shipped classic checkpoint; pass --checkpoint")
    return p


def classic_predictors(checkpoints, default: bool = False) -> list[Predictor]:
    """`--checkpoint [NAME=]PATH ...` of classic (any-light) networks, as `resolve_predictors` names and
    checks them (`default`: the shipped one when none is given); a dual-cue checkpoint is refused in one
    line (it reads one three-light image)."""
    if not checkpoints and default:
        checkpoints = [f"{CLASSIC}={default_classic_checkpoint()}"]
    out = resolve_predictors(checkpoints, [NET]) if checkpoints else []
    for p in out:
        if p.kind != CLASSIC:
            raise InputError(p.info.get("checkpoint", p.name), "not an msps classic-network checkpoint (a dual-cue "
                                                               "one: it reads one three-light image, not N lights)")
    return out


def methods(predictors: list[Predictor], columns: list[Steps], remedy: str = "give a checkpoint or --method net"
            ) -> list[Method]:
    """Every predictor under every steps value (steps-major, the order of the columns given); a step
    that needs a network's normals skips the baseline, and refuses when no predictor is a network."""
    network = any(p.network for p in predictors)
    for steps in columns:
        if not steps.default:
            steps.check_network(network, remedy)
    out = [Method(p.name + t.suffix, p, t) for s in columns for p in predictors
           if (t := s.for_predictor(p.network)) is not None]
    names = [m.name for m in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError("--steps", f"column '{dup[0]}' given twice")
    return out


def default_checkpoint() -> Path:
    """The small checkpoint shipped in models/ (trained by docs/reproducing.md)."""
    p = data_dir("models") / "dualcue-cpu.pt"
    if not p.is_file():
        raise InputError(p, "no shipped checkpoint; pass --checkpoint")
    return p


def _digest(*arrays: np.ndarray) -> tuple:
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype}{a.shape}".encode())
        h.update(a.view(np.uint8).reshape(-1))
    return h.digest(),


class Memo:
    """What several methods on one image (or one batch of patches) share: image-stage states per
    steps prefix, and predictor outputs per exact input.  One per image; dropped with it.
    `task`: a progress line (msps_render.progress) that hears each step and each predictor pass's tiles."""

    def __init__(self, task=None):
        self.states: dict[tuple, State] = {}
        self.outputs: dict[tuple, np.ndarray] = {}
        self.task, self._what, self._passes = task, "", 0

    def note(self, what: str) -> None:
        if self.task:
            self._what = what
            self.task.describe(what)

    def tiles(self, done: int, total: int) -> None:
        if self.task:
            if done <= 0:
                self._passes += 1
                self.task.describe(f"{self._what}: network pass {self._passes}, tiles")
            self.task.set(done, total)

    def call(self, key: tuple, fn, *arrays: np.ndarray) -> np.ndarray:
        k = key + _digest(*arrays)
        if k not in self.outputs:
            self.outputs[k] = fn(*arrays)
        return self.outputs[k]


def run(method: Method, image: np.ndarray, mask: np.ndarray, rig: Rig, memo: Memo | None = None) -> State:
    """The method's steps on one whole image: the final state (`normals`, `image`, `scale`, `fits`)."""
    memo = memo or Memo()
    p = method.predictor
    key = tuple(method.steps.before("predictor").names)
    s = memo.states.get(key)
    if s is None:
        s = State(image, np.asarray(mask, bool), rig, image)
        for step in method.steps.stage("image"):
            memo.note(f"{method.name}: {step.name}")
            s = step.apply(s)
        memo.states[key] = s
    s = State(s.source, s.mask, s.rig, s.image, s.scale,
              lambda x, mk: memo.call(("image", id(p)), lambda a, b: p.image(a, b, rig, memo.tiles), x, mk),
              None, s.fits)
    for step in method.steps.stage("predictor"):
        s = step.apply(s)
    memo.note(method.name)
    loops = method.steps.stage("predict")
    if not loops:
        s = State(s.source, s.mask, s.rig, s.image, s.scale, s.predict, s.predict(s.image, s.mask), s.fits)
    for step in loops:
        s = step.apply(s)
    for step in method.steps.stage("normals"):
        memo.note(f"{method.name}: {step.name}")
        s = step.apply(s)
    return s


def trace(state: State) -> dict:
    """What each step did, as JSON (step name -> its record)."""
    return {n: STEPS[n].record(f) for n, f in state.fits.items()}


def label(method: Method, state: State) -> str:
    """'net (dualcue-cpu.pt) +selfcal x1.20/0.90/0.90 +refine (1,234 px)': a title for one prediction."""
    base = method.predictor.name if not method.predictor.info.get("checkpoint") else \
        f"{method.predictor.kind} ({Path(method.predictor.info['checkpoint']).name})"
    parts = [base] + [f"+{n} {STEPS[n].label(state.fits[n])}".rstrip() for n in method.steps.names]
    return " ".join(parts)


__all__ = ["LAMBERTIAN", "NET", "STAGES", "Memo", "Method", "Predictor", "checkpoint_predictor",
           "lambertian_predictor", "methods", "resolve_predictors", "run", "trace", "label"]


# ------------------------------------------------------------------ the patch path, beside `run`
@dataclass(frozen=True)
class FrameFit:
    """What a method's steps found on a whole frame that its patches are scored with: the colour factor
    on the frame's image ((3,) or (H, W, 3); None: no colour step) and, per `normals`-stage step, its
    frame value (the refinement's albedo estimate)."""

    scale: np.ndarray | None
    values: dict

    def factor(self, y: int, x: int, size: int) -> np.ndarray:
        """The factor of the patch at (y, x): (1, 1, 3) or (size, size, 3)."""
        s = np.asarray(self.scale)
        return s[None, None, :] if s.ndim == 1 else s[y:y + size, x:x + size]


def frame_fit(m: Method, state: State) -> FrameFit:
    """What `run` found on a whole frame that its patches are scored with (`run_patches`)."""
    return FrameFit(state.scale, {st.name: st.frame(state) for st in m.steps.stage("normals")})


def run_patches(m: Method, images: np.ndarray, masks: np.ndarray, rigs: list[Rig], matrices, yx: np.ndarray,
                fits: list[FrameFit] | None, memo: Memo) -> np.ndarray:
    """Method `m` on a batch of patches (B, P, P, 3) cut from whole frames: each patch's colour factor and
    `normals`-stage values from its frame's `run` (`fits`, one per patch; None: no whole frames), the
    predictor on the patches alone (wrapped by `predictor`-stage steps), then the `normals` stage.  The
    second interpreter of the steps that `msps eval` used to carry is this one, next to `run`: every stage
    is dispatched here through the hooks the registry checks at registration (`steps.Step`)."""
    img = images
    if fits is not None and fits and fits[0].scale is not None:
        P = images.shape[1]
        factor = np.stack([f.factor(y, x, P) for f, (y, x) in zip(fits, yx)])
        img = (images * factor.astype(np.float32)).astype(np.float32, copy=False)
    p = m.predictor
    predict = lambda x, k: memo.call((id(p),), lambda a, c: p.patches(a, c, rigs, matrices), x, k)  # noqa: E731
    for step in m.steps.stage("predictor"):
        predict = step.batch(predict, rigs)
    out = predict(img, masks)
    for step in m.steps.stage("normals"):
        if fits is None:
            raise InputError(step.name, f"{step.name} takes each patch's value from its whole frame; give whole frames")
        out = step.patches(img, out, masks, rigs, [f.values[step.name] for f in fits])
    return out
