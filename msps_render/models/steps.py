"""Test-time steps: one value names them (`Steps`), one registry (`STEPS`) says what each does.

Why: five steps (selfcal, segments, netcal, mirror, refine) each change one thing -- the image before
the network, the network itself, or the normals after it -- and every command combined them by hand.
Here a step is one module with its maths (models/selfcal.py ...) plus one `Step` entry: its stage,
how it acts on a `State` (the image, the predictor, the normals of one whole image), what it needs
(a network's normals, the rig, a whole image) and what it records.  `Steps.parse("selfcal+netcal")`
gives the value every caller passes on; `models/runner.py` applies it.

Stages, in the order they run: `image` (divide a colour out of the image), `predictor` (wrap the
predictor), `predict` (a loop that replaces the one prediction), `normals` (change the normals).
Names keep the registry's order ("net+selfcal+netcal+mirror+refine"), which is the order the old
comparison columns were named in.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable, Mapping

import numpy as np

from msps_render.calibration import Rig
from msps_render.errors import InputError, closest
from msps_render.models import netcal, refine, segments, selfcal, symmetry

STAGES = ("image", "predictor", "predict", "normals")
NONE = "none"  # `--steps none`: the raw predictor


@dataclass(frozen=True)
class State:
    """One whole image on its way through the steps."""

    source: np.ndarray  # (H, W, 3) the image as given
    mask: np.ndarray  # (H, W) bool
    rig: Rig
    image: np.ndarray  # (H, W, 3) the image as the predictor sees it
    scale: np.ndarray | None = None  # (3,) or (H, W, 3): `image` = `source` x this; None: no colour step ran
    predict: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None  # (image, mask) -> normals
    normals: np.ndarray | None = None  # (H, W, 3) once predicted
    fits: Mapping[str, object] = field(default_factory=dict)  # step name -> what it found (its module's type)

    def after(self, name: str, fit, **changes) -> "State":
        return replace(self, fits={**self.fits, name: fit}, **changes)


def _selfcal(s: State) -> State:
    fit = selfcal.fit_albedo_colour(s.image, s.mask, s.rig.light_dirs, s.rig.crosstalk)
    return s.after("selfcal", fit, image=selfcal.apply_colour_fit(s.image, fit),
                   scale=fit.scale if s.scale is None else s.scale * fit.scale)


def _segments(s: State) -> State:  # after selfcal: only objects its one colour leaves alone are cut
    fit = segments.fit_segments(s.source, s.mask, s.rig.light_dirs, s.rig.crosstalk, whole=s.fits["selfcal"])
    image = (s.image * fit.scale).astype(s.image.dtype, copy=False) if fit.applied else s.image
    return s.after("segments", fit, image=image, scale=fit.scale * s.scale)


def _netcal(s: State) -> State:
    n, image, fit = netcal.calibrate(lambda x: s.predict(x, s.mask), s.image, s.mask, s.rig.matrix)
    return s.after("netcal", fit, image=image, normals=n, scale=fit.scale * s.scale)


def _mirror(s: State) -> State:
    m, inner = symmetry.require_mirror(s.rig.light_dirs, s.rig.crosstalk), s.predict
    return s.after("mirror", m, predict=lambda x, mk: symmetry.mirror_ensemble(inner, x, mk, m))


def mirror_batch(predict: Callable, rigs: list[Rig]) -> Callable:
    """`predict(images (B, P, P, 3), masks)` averaged with its mirror twins, each patch by its own rig."""
    ms = [symmetry.require_mirror(r.light_dirs, r.crosstalk) for r in rigs]
    return lambda x, mk: symmetry.mirror_ensemble_batch(predict, x, mk, ms)


def _refine(s: State) -> State:
    n, stats = refine.refine_normals(s.image, s.mask, s.normals, s.rig.light_dirs, s.rig.crosstalk)
    return s.after("refine", stats, normals=n)


def _refine_frame(s: State) -> refine.ObjectAlbedo:
    """The albedo estimate a frame's patches are refined with: the whole frame's, after its colour factor."""
    image = s.source if s.scale is None else s.source * s.scale
    return refine.estimate_albedo(image, s.mask, s.rig.light_dirs, s.rig.crosstalk)


def _refine_patches(images: np.ndarray, normals: np.ndarray, masks: np.ndarray, rigs: list[Rig],
                    albedos: list) -> np.ndarray:
    out = normals.copy()
    changed = False
    for x, n, mk, r, a, o in zip(images, normals, masks, rigs, albedos, out):
        px, n3, n2 = refine.refine_pixels(x[mk], n[mk], r.light_dirs, r.crosstalk, a)
        if n3 or n2:
            o[mk] = px
            changed = True
    return out if changed else normals  # unchanged: the same array, so its scores are shared too


def _ratio(v) -> str:
    return "x" + "/".join(f"{x:.2f}" for x in v)


@dataclass(frozen=True)
class Step:
    """One registry entry: what a step is to the runner and to the commands."""

    name: str
    stage: str  # one of STAGES
    apply: Callable[[State], State]  # on a whole image
    description: str  # a method column's description after this step
    record: Callable[[object], dict]  # its fit -> JSON (`msps predict`'s OUT-metrics.json)
    label: Callable[[object], str]  # its fit -> a few words (panel titles)
    needs_network: str = ""  # why it needs a network's normals ("": it does not)
    needs_rig: bool = True  # it reads pixels through the rig (light directions and crosstalk)
    whole_image: bool = True  # it fits the whole object (patch scores take the frame's fit)
    colour: bool = False  # divides out the albedo colour after selfcal: one such step at a time
    implies: tuple[str, ...] = ()
    batch: Callable[[Callable, list[Rig]], Callable] | None = None  # `predictor` stage: wrap a patch batch
    frame: Callable[[State], object] | None = None  # `normals` stage: what patches take from their frame's run
    patches: Callable | None = None  # `normals` stage: (images, normals, masks, rigs, frame values) -> normals

    def __post_init__(self) -> None:
        """The hooks each stage's patch path calls, checked when the step is registered (a `normals` step
        without `frame`/`patches` used to crash `msps eval` with "'NoneType' object is not callable")."""
        if self.stage not in STAGES:
            raise ValueError(f"step '{self.name}': stage must be one of {', '.join(STAGES)}, got '{self.stage}'")
        need = {"predictor": ("batch",), "normals": ("frame", "patches")}.get(self.stage, ())
        missing = [h for h in need if getattr(self, h) is None]
        if missing:
            raise ValueError(f"step '{self.name}' ({self.stage} stage) needs the hook(s) {', '.join(missing)}: "
                             "patches are scored through them (models/evaluate.py)")
        if self.stage in ("image", "predict") and not self.whole_image:
            raise ValueError(f"step '{self.name}' ({self.stage} stage) must fit the whole image: its patches "
                             "take the frame's colour factor")


STEPS: dict[str, Step] = {s.name: s for s in (
    Step("selfcal", "image", _selfcal, selfcal.DESCRIPTION,
         lambda f: {"applied": f.applied, "scale": f.scale.tolist(), "grey_rms": f.grey_rms,
                    "colour_rms": f.colour_rms, "share": f.share, "grey_share": f.grey_share},
         lambda f: _ratio(f.scale) if f.applied else "(grey kept)"),
    Step("segments", "image", _segments, segments.DESCRIPTION,
         lambda f: {"applied": f.applied, "regions": len(f.accepted), "object_share": f.object_share,
                    "reason": f.reason},
         lambda f: f"({len(f.accepted)} regions)" if f.applied else "(not applied)",
         colour=True, implies=("selfcal",)),
    Step("netcal", "predict", _netcal, netcal.DESCRIPTION,
         lambda f: {"applied": f.applied, "scale": f.scale.tolist(), "agree": f.agree, "n_pixels": f.n_pixels},
         lambda f: _ratio(f.scale) if f.applied else "(kept)",
         needs_network="reads the colour off a network's normals; the Lambertian baseline explains every "
                       "colour as a tilt", colour=True, implies=("selfcal",)),
    Step("mirror", "predictor", _mirror, symmetry.DESCRIPTION,
         lambda f: {"axis": f.axis, "perm": list(f.perm)}, lambda f: "",
         needs_network="averages a network's two predictions; the Lambertian baseline is already "
                       "mirror-symmetric", whole_image=False, batch=mirror_batch),
    Step("refine", "normals", _refine, refine.DESCRIPTION,
         lambda f: {"n_three": f.n_three, "n_two": f.n_two, "rho": f.albedo.rho, "uniform": f.albedo.uniform},
         lambda f: f"({f.n_three + f.n_two:,} px)" if f.n_three + f.n_two else "(not one albedo: kept)",
         needs_network="refines a network's normals; the Lambertian baseline has nothing to refine",
         frame=_refine_frame, patches=_refine_patches),
)}


@dataclass(frozen=True)
class Steps:
    """Which steps run, in registry order, implied ones included; `Steps()` is the raw predictor.
    `alias`: given by the old per-step flags (--selfcal ...), so messages name those flags."""

    names: tuple[str, ...] = ()
    alias: bool = field(default=False, compare=False)
    given: str = field(default="", compare=False)  # the --steps text as the user wrote it (messages quote it)
    default: bool = field(default=False, compare=False)  # a context's default, not asked for: a predictor
    # it does not fit (the baseline under a network-only step) runs without steps instead of refusing

    def for_predictor(self, network: bool) -> "Steps | None":
        """The steps a predictor runs under this value: itself, `Steps()` for a default that needs a
        network the predictor is not, None (no such column) when asked for explicitly."""
        if self.fits_network(network):
            return self
        return Steps() if self.default else None

    @classmethod
    def of(cls, names, alias: bool = False, source: str = "--steps") -> "Steps":
        """Validated: known names, implied steps added, at most one colour step."""
        want = set()
        for n in names:
            if n not in STEPS:
                raise InputError(source, f"unknown step '{n}'{closest(n, STEPS)} (steps: {', '.join(STEPS)}; "
                                         f"or {NONE})")
            want |= {n, *STEPS[n].implies}
        colour = [n for n in STEPS if n in want and STEPS[n].colour]
        if len(colour) > 1:
            src = source if not alias else f"--{colour[-1]}"
            raise InputError(src, f"{' and '.join(colour)} are two ways to divide out the albedo colour; give one")
        return cls(tuple(n for n in STEPS if n in want), alias)

    @classmethod
    def parse(cls, text: str, source: str = "--steps") -> "Steps":
        """'selfcal+netcal+refine' (any order) or 'none'."""
        t = str(text).strip()
        if t.lower() == NONE:
            return cls()
        parts = [p.strip() for p in t.split("+")]
        if not t or not all(parts):
            raise InputError(source, f"'{text}': expected step names joined by '+' "
                                     f"(e.g. selfcal+netcal+refine) or {NONE}")
        dup = sorted({p for p in parts if parts.count(p) > 1})
        if dup:
            raise InputError(f"{source} {t}", f"step '{dup[0]}' given twice")
        return replace(cls.of(parts, source=f"{source} {t}"), given=t)

    def __str__(self) -> str:
        return "+".join(self.names) or NONE

    def __contains__(self, name: str) -> bool:
        return name in self.names

    @property
    def suffix(self) -> str:
        """What a method's name gets: '+selfcal+netcal'."""
        return "".join("+" + n for n in self.names)

    def where(self, name: str) -> str:
        """How the user named step `name`: the old flag, or the --steps value."""
        return f"--{name}" if self.alias else f"--steps {self.given or self}"

    def stage(self, stage: str) -> list[Step]:
        return [STEPS[n] for n in self.names if STEPS[n].stage == stage]

    def before(self, stage: str) -> "Steps":
        """The steps of the stages before `stage`: what that stage's input depends on."""
        keep = STAGES[:STAGES.index(stage)]
        return Steps(tuple(n for n in self.names if STEPS[n].stage in keep), self.alias, self.given)

    @property
    def whole_image(self) -> list[str]:
        return [n for n in self.names if STEPS[n].whole_image]

    def fits_network(self, network: bool) -> bool:
        return network or not any(STEPS[n].needs_network for n in self.names)

    def check_network(self, network: bool, remedy: str = "") -> None:
        for n in self.names:
            if STEPS[n].needs_network and not network:
                raise InputError(self.where(n), f"{n} {STEPS[n].needs_network}" + (f" ({remedy})" if remedy else ""))

    def check(self, network: bool, rig: Rig | None, remedy: str = "") -> None:
        """One line naming the step and what is missing, before any work."""
        self.check_network(network, remedy)
        for n in self.names:
            if STEPS[n].needs_rig and rig is None:
                raise InputError(self.where(n), f"{n} needs the rig (light directions and crosstalk): "
                                                "give --calibration or --light-dirs/--crosstalk")
        if "mirror" in self and rig is not None:
            symmetry.require_mirror(rig.light_dirs, rig.crosstalk, self.where("mirror"))

    def describe(self, base: str) -> str:
        return ", ".join([base] + [STEPS[n].description for n in self.names])


# The default steps per context: ONE constant each (`--steps none` gives the raw predictor anywhere).
# Chosen on validation data by a rule written before scoring (docs/history.md "Stage 14"): on the
# four DiLiGenT objects selfcal+netcal gives 0.545x Lambertian's mean error (the raw network 0.60x);
# on val-frames / -colour / -texture selfcal+segments+refine gives 12.93 / 12.00 / 15.08 deg (raw
# 13.44 / 12.44 / 18.94). The baseline runs without steps under a default that needs a network.
DEFAULT_PHOTOS = Steps(("selfcal", "netcal"), default=True)  # real photographs: `msps predict`, `bench-real`
DEFAULT_RENDERED = Steps(("selfcal", "segments", "refine"), default=True)  # rendered test sets: `msps eval`


def from_flags(columns: bool, selfcal: bool = False, segments: bool = False, netcal: bool = False,
               mirror: bool = False, refine: bool = False) -> list[Steps]:
    """The old per-step flags (hidden aliases for one release) as Steps: the ONE place they are mapped.

    `columns=False` (`msps predict`): the flags' union.  `columns=True` (`msps eval`, `bench-real`): the
    comparison columns the flags used to add, in their order: every column again with selfcal; with
    segments, or with netcal (each after selfcal), of the columns without selfcal; with mirror; with refine.
    No flag: [] (the caller's --steps or default)."""
    given = [n for n, on in (("selfcal", selfcal), ("segments", segments), ("netcal", netcal),
                             ("mirror", mirror), ("refine", refine)) if on]
    if not given:
        return []
    if not columns:
        return [Steps.of(given, alias=True)]
    cols: list[tuple[str, ...]] = [()]
    for n in given:
        if n in ("segments", "netcal"):
            cols += [c + ("selfcal", n) for c in cols if "selfcal" not in c]
        else:
            cols += [c + (n,) for c in cols]
    return [Steps.of(c, alias=True) for c in cols]
