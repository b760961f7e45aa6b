"""Evaluation like the paper: angular-error statistics, SSIM, per-object tables, robustness.

Several methods (checkpoints and the Lambertian baseline) are scored on the
same patches and frames in one pass over the data, so their numbers differ only
by the method.  Patch-level metrics pool every object pixel of every patch.
Whole-frame test sets (stored with `store_frames = true`) are also predicted
image by image (tiles blended, `predict.predict_image`) for the per-object
table.  With a sweep (several conditions), MAE per condition and the paper's
fluctuation ratio alpha = |chi - chi'| / chi against the reference condition
are reported and plotted.

95 % confidence intervals are percentile bootstraps over frames: patches cut
from one frame share its shape, material and light, so they are resampled
together (resampling patches would understate the spread).  The resamples are
seeded and the same for every method (paired), so a method's interval does not
depend on which other methods ran beside it.
"""
from __future__ import annotations

import json
import zlib
from collections import defaultdict
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from msps_render.atomic import atomic_write
from msps_render.dataset import Manifest, load_manifest
from msps_render.errors import InputError
from msps_render.models.baseline import lambertian_ps
from msps_render.models.metrics import angular_error_deg, error_stats
from msps_render.models import netcal, refine, segments, selfcal, symmetry
from msps_render.models.report import (PER_OBJECT_NOTE, error_histogram, per_object_detail, write_plots,
                                       write_tables)

LAMBERTIAN = "lambertian"
FORMAT = 2  # metrics.json: "methods" + "table"; single-method runs also keep the format-1 keys at the top
CI_LEVEL = 0.95
N_BOOT = 2000
CI_SEED = 0
CI_NOTE = (f"95 % CI: percentile bootstrap over frames (a frame's patches resampled together), {N_BOOT} "
           f"resamples, seed {CI_SEED}, the same resamples for every method")


def _ssim_masked(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    """Mean SSIM over object pixels (kornia, as in the training loss)."""
    import torch

    from msps_render.models.losses import masked_ssim

    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, np.float32))
    return float(masked_ssim(t(pred), t(gt), t(mask)))


@dataclass
class Method:
    """One column of the comparison: the Lambertian baseline or a loaded checkpoint."""

    name: str
    kind: str  # "net" or "lambertian"
    info: dict = field(default_factory=dict)
    model: object = None
    selfcal: bool = False  # divide out the frame's fitted albedo colour first (models/selfcal.py)
    refine: bool = False  # refine the network's normals by the Lambertian closed form (models/refine.py)
    mirror: bool = False  # average with the prediction of the mirrored image (models/symmetry.py)
    segments: bool = False  # after selfcal, divide out each colour region's albedo (models/segments.py)
    netcal: bool = False  # after selfcal, divide out the colour read off its own normals, predict again

    @property
    def base_key(self) -> tuple:
        """Methods with the same key predict the same normals before the refinement: a `+refine`
        twin reuses its base method's prediction (`patch_predictions`, `frame_predictions`)."""
        return self.kind, id(self.model), self.selfcal, self.segments, self.mirror, self.netcal

    @property
    def netcal_key(self) -> tuple:
        """What the network-colour loop's result depends on (a `+refine` twin shares its base's)."""
        return id(self.model), self.mirror

    def object_albedo(self, f: "FrameFit") -> refine.ObjectAlbedo:
        """The refinement's albedo estimate of the frame as this method sees it."""
        if self.netcal:
            return f.netcal[self.netcal_key].albedo
        if self.segments:
            return f.albedo_segments
        return f.albedo_selfcal if self.selfcal else f.albedo

    def patches(self, b, fits: list["FrameFit"] | None = None) -> np.ndarray:
        """(B, 3, P, P) normals for a batch dict; `fits`: each patch's frame-level fits (`frame_fits`)."""
        image, pred = self.unrefined_patches(b, fits)
        return self.refined_patches(image, pred, b, fits)

    def unrefined_patches(self, b, fits: list["FrameFit"] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(the batch's images as the method sees them, its normals before any refinement)."""
        image = b["image"]
        if (self.selfcal or self.refine) and fits is None:
            raise ValueError(f"{self.name}: self-calibration and refinement need the frames' fits")
        if self.selfcal:  # the frames' factors: one colour per frame, or (segments) a map cropped per patch
            import torch

            P = image.shape[-1]
            if self.segments:
                factor = np.stack([f.segment_map(y, x, P) for f, (y, x) in zip(fits, b["yx"].numpy())])
            elif self.netcal:  # the loop ran on the whole frame (`frame_fits`): its colour, then this network
                factor = np.stack([f.netcal[self.netcal_key].scale for f in fits])[:, None, None, :]
            else:
                factor = np.stack([f.scale for f in fits])[:, None, None, :]
            image = image * torch.from_numpy(factor.transpose(0, 3, 1, 2).astype(np.float32))
        if self.kind == LAMBERTIAN:
            img = image.numpy().transpose(0, 2, 3, 1)
            out = np.stack([lambertian_ps(img[i], b["light_dirs"][i].numpy(), b["crosstalk"][i].numpy())
                            for i in range(len(img))])
            return image.numpy(), out.transpose(0, 3, 1, 2)
        import torch

        rigs = b["crosstalk"] @ b["light_dirs"]

        def net(x: np.ndarray, mk: np.ndarray) -> np.ndarray:  # (B, P, P, 3), (B, P, P) -> (B, P, P, 3)
            with torch.no_grad():
                out = self.model(torch.from_numpy(np.ascontiguousarray(x.transpose(0, 3, 1, 2), np.float32)),
                                 torch.from_numpy(np.ascontiguousarray(mk[:, None], np.float32)), rigs)[0]
            return out.numpy().transpose(0, 2, 3, 1)

        img, mk = image.numpy().transpose(0, 2, 3, 1), b["mask"].numpy()[:, 0] > 0
        if not self.mirror:
            return image.numpy(), net(img, mk).transpose(0, 3, 1, 2)
        mirrors = [symmetry.require_mirror(b["light_dirs"][i].numpy(), b["crosstalk"][i].numpy())
                   for i in range(len(img))]
        return image.numpy(), symmetry.mirror_ensemble_batch(net, img, mk, mirrors).transpose(0, 3, 1, 2)

    def refined_patches(self, image: np.ndarray, pred: np.ndarray, b, fits: list["FrameFit"] | None
                        ) -> np.ndarray:
        """Each patch refined with its frame's albedo estimate, as the whole frame would be
        (`pred` itself when this method does not refine)."""
        if not self.refine:
            return pred
        out = pred.copy()
        for i, f in enumerate(fits):
            mk = b["mask"][i, 0].numpy() > 0
            n, n3, n2 = refine.refine_pixels(image[i].transpose(1, 2, 0)[mk], pred[i].transpose(1, 2, 0)[mk],
                                             b["light_dirs"][i].numpy(), b["crosstalk"][i].numpy(),
                                             self.object_albedo(f))
            if n3 or n2:
                o = out[i].transpose(1, 2, 0)  # a view: writes go to out
                o[mk] = n
        return out

    def frame(self, fr) -> np.ndarray:
        return self.refined_frame(fr, *self.unrefined_frame(fr))

    def unrefined_frame(self, fr, fit: "FrameFit | None" = None) -> tuple[np.ndarray, np.ndarray]:
        """(the frame's image as the method sees it, its normals before any refinement); `fit`: the
        frame's fits, whose network-colour loop (if this method's ran in `frame_fits`) is reused."""
        if self.netcal and fit is not None and self.netcal_key in fit.netcal:
            loop = fit.netcal[self.netcal_key]
            return loop.image, loop.normals
        if self.segments:
            image = segments.calibrated(fr.image, fr.mask, fr.light_dirs, fr.crosstalk)
        elif self.selfcal:
            image = selfcal.self_calibrated(fr.image, fr.mask, fr.light_dirs, fr.crosstalk)
        else:
            image = fr.image
        if self.kind == LAMBERTIAN:
            return image, lambertian_ps(image, fr.light_dirs, fr.crosstalk, fr.mask)
        predict = self.frame_predictor(fr)
        if self.netcal:
            normals, image, _ = netcal.calibrate(predict, image, fr.mask, fr.crosstalk @ fr.light_dirs)
            return image, normals
        return image, predict(image)

    def frame_predictor(self, fr):
        """image (H, W, 3) -> this network's normals of the frame (mirror-averaged with `mirror`)."""
        from msps_render.models.predict import predict_image

        rig = fr.crosstalk @ fr.light_dirs
        if not self.mirror:
            return lambda x: predict_image(self.model, x, fr.mask, rig=rig)
        mirror = symmetry.require_mirror(fr.light_dirs, fr.crosstalk)
        return lambda x: symmetry.mirror_ensemble(lambda y, m: predict_image(self.model, y, m, rig=rig), x,
                                                  fr.mask, mirror)

    def refined_frame(self, fr, image: np.ndarray, normals: np.ndarray) -> np.ndarray:
        if not self.refine:
            return normals
        return refine.refine_normals(image, fr.mask, normals, fr.light_dirs, fr.crosstalk)[0]


def patch_predictions(methods: list[Method], b, fits: list["FrameFit"] | None) -> list[np.ndarray]:
    """Each method's (B, 3, P, P) normals for one batch; the network runs once per `base_key`."""
    base: dict[tuple, tuple] = {}
    out = []
    for m in methods:
        if m.base_key not in base:
            base[m.base_key] = m.unrefined_patches(b, fits)
        out.append(m.refined_patches(*base[m.base_key], b, fits))
    return out


def frame_predictions(methods: list[Method], fr, fit: "FrameFit | None" = None) -> list[np.ndarray]:
    """Each method's (H, W, 3) normals for one whole frame; the network runs once per `base_key`
    (and not at all for a network-colour loop that `frame_fits` already ran: pass the frame's `fit`)."""
    base: dict[tuple, tuple] = {}
    out = []
    for m in methods:
        if m.base_key not in base:
            base[m.base_key] = m.unrefined_frame(fr, fit)
        out.append(m.refined_frame(fr, *base[m.base_key]))
    return out


def with_selfcal(methods: list[Method]) -> list[Method]:
    """Each method, then each again after the albedo-colour self-calibration ("NAME+selfcal")."""
    twins = [replace(m, name=m.name + selfcal.SUFFIX, selfcal=True,
                     info={**m.info, "description": f"{m.info.get('description', m.name)}, {selfcal.DESCRIPTION}"})
             for m in methods]
    return list(methods) + twins


def with_segments(methods: list[Method]) -> list[Method]:
    """Each method, then each one without selfcal again after the object-level and the segment-wise
    self-calibration ("NAME+selfcal+segments")."""
    twins = [replace(m, name=m.name + selfcal.SUFFIX + segments.SUFFIX, selfcal=True, segments=True,
                     info={**m.info, "description": f"{m.info.get('description', m.name)}, {segments.DESCRIPTION}"})
             for m in methods if not m.selfcal]
    return list(methods) + twins


def with_netcal(methods: list[Method]) -> list[Method]:
    """Each network without selfcal, then again after the object-level self-calibration and the colour read
    off its own normals ("NAME+selfcal+netcal"; models/netcal.py)."""
    twins = [replace(m, name=m.name + selfcal.SUFFIX + netcal.SUFFIX, selfcal=True, netcal=True,
                     info={**m.info, "description": f"{m.info.get('description', m.name)}, {selfcal.DESCRIPTION}, "
                                                    f"{netcal.DESCRIPTION}"})
             for m in methods if m.kind == "net" and not m.selfcal]
    return list(methods) + twins


def with_mirror(methods: list[Method]) -> list[Method]:
    """Each method, then each network again averaged with its mirror-image prediction ("NAME+mirror")."""
    twins = [replace(m, name=m.name + symmetry.SUFFIX, mirror=True,
                     info={**m.info, "description": f"{m.info.get('description', m.name)}, {symmetry.DESCRIPTION}"})
             for m in methods if m.kind == "net"]
    return list(methods) + twins


def with_refine(methods: list[Method]) -> list[Method]:
    """Each method, then each network again with the Lambertian refinement after it ("NAME+refine")."""
    twins = [replace(m, name=m.name + refine.SUFFIX, refine=True,
                     info={**m.info, "description": f"{m.info.get('description', m.name)}, {refine.DESCRIPTION}"})
             for m in methods if m.kind == "net"]
    return list(methods) + twins


@dataclass(frozen=True)
class NetcalFrame:
    """One network's colour loop on a whole frame (models/netcal.py), kept for its patches and its frame."""

    scale: np.ndarray  # (3,) selfcal x loop factor on the image as rendered
    albedo: refine.ObjectAlbedo  # the refinement's estimate after it
    image: np.ndarray  # (H, W, 3) the image the normals were predicted on
    normals: np.ndarray  # (H, W, 3) the loop's normals, before any refinement


@dataclass(frozen=True)
class FrameFit:
    """A frame's whole-object estimates that its patches are scored with."""

    scale: np.ndarray  # (3,) the self-calibration's colour factor (models/selfcal.py)
    albedo: refine.ObjectAlbedo  # the refinement's albedo estimate on the image as rendered
    albedo_selfcal: refine.ObjectAlbedo  # ... after the colour factor
    segment_scale: np.ndarray | None = None  # (H, W, 3) selfcal then segment-wise factors (models/segments.py)
    albedo_segments: refine.ObjectAlbedo | None = None  # ... the refinement's estimate after them
    netcal: dict = field(default_factory=dict)  # Method.netcal_key -> NetcalFrame

    def segment_map(self, y: int, x: int, size: int) -> np.ndarray:
        """(size, size, 3) factors of the patch at (y, x)."""
        if self.segment_scale is None:
            raise ValueError("frame fits made without segments (frame_fits(..., segments=True))")
        return self.segment_scale[y:y + size, x:x + size]


def frame_fits(data: Path, condition: str | None, why: str = "--selfcal", segment_fits: bool = False,
               netcal_methods: list[Method] = ()) -> dict[tuple[str, int], FrameFit]:
    """(shard file name, frame index) -> the frame's fits, for scoring patches as whole frames are.
    `netcal_methods`: each runs its network-colour loop on the whole frame (a network pass or two)."""
    from msps_render.data import iter_frames

    try:
        frames = list(iter_frames(data, condition=condition))
    except InputError:
        raise InputError(data, f"{why} fits each object on its whole frame; this dataset has no "
                               "whole frames (render a preset with store_frames = true)") from None
    fits = {}
    for fr in frames:
        whole = selfcal.fit_albedo_colour(fr.image, fr.mask, fr.light_dirs, fr.crosstalk)
        scale = whole.scale
        seg = alb_seg = None
        if segment_fits:  # ones where the object-level fit applies (or nothing does): then `scale` alone
            seg = segments.fit_segments(fr.image, fr.mask, fr.light_dirs, fr.crosstalk, whole=whole).scale * scale
            alb_seg = refine.estimate_albedo(fr.image * seg, fr.mask, fr.light_dirs, fr.crosstalk)
        loops = {}
        for m in netcal_methods:
            if m.netcal_key not in loops:
                img = selfcal.apply_colour_fit(fr.image, whole)
                n, seen, fit = netcal.calibrate(m.frame_predictor(fr), img, fr.mask, fr.crosstalk @ fr.light_dirs)
                loops[m.netcal_key] = NetcalFrame(fit.scale * scale, refine.estimate_albedo(
                    fr.image * (fit.scale * scale), fr.mask, fr.light_dirs, fr.crosstalk), seen, n)
        fits[(fr.shard, fr.index)] = FrameFit(
            scale, refine.estimate_albedo(fr.image, fr.mask, fr.light_dirs, fr.crosstalk),
            refine.estimate_albedo(fr.image * scale, fr.mask, fr.light_dirs, fr.crosstalk), seg, alb_seg, loops)
    return fits


def lambertian_method() -> Method:
    return Method(LAMBERTIAN, LAMBERTIAN, {"description": "calibrated Lambertian photometric stereo"})


def checkpoint_method(path: str | Path, name: str | None = None) -> Method:
    """A checkpoint; unnamed, it is called after its network: net (dual cue), scn or pcn (ablations)."""
    from msps_render.models.checkpoint import load_checkpoint

    model, cfg, ck = load_checkpoint(path)
    mode = cfg.net.mode
    return Method(name or ("net" if mode == "dual" else mode), "net",
                  {"description": "dual-cue network" if mode == "dual" else f"{mode.upper()} only (ablation)",
                   "checkpoint": str(path), "preset": cfg.preset, "mode": mode,
                   "val_mae_deg": ck.get("val_mae_deg")}, model)


def resolve_methods(checkpoints=(), methods=(), selfcal: bool = False, refine: bool = False,
                    mirror: bool = False, segments: bool = False, netcal: bool = False) -> list[Method]:
    """`msps eval --checkpoint [NAME=]PATH ... --method net|lambertian ...` -> the methods, checkpoints first.

    `net` stands for the checkpoints given (the shipped one when none is); checkpoints imply `net`, so
    `--checkpoint a.pt --method lambertian` compares both.  Nothing given: the shipped checkpoint."""
    kinds = list(dict.fromkeys(methods or ["net"]))
    for k in kinds:
        if k not in ("net", LAMBERTIAN):
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
    if not specs and "net" in kinds:
        from msps_render.models.predict import default_checkpoint

        specs = [(None, default_checkpoint())]
    out: list[Method] = []
    for name, p in specs:
        if name == LAMBERTIAN:
            raise InputError("--checkpoint", f"'{name}={p}': '{LAMBERTIAN}' names the baseline")
        if name is not None and name in [m.name for m in out]:
            raise InputError("--checkpoint", f"method name '{name}' given twice")
        m = checkpoint_method(p, name)
        if name is None:  # two unnamed checkpoints of one kind: add the run folder and file
            base, k = m.name, 1
            while m.name in [o.name for o in out]:
                m.name = f"{base} {p.resolve().parent.name}/{p.stem}" + (f" ({k})" if k > 1 else "")
                k += 1
        out.append(m)
    if LAMBERTIAN in kinds:
        out.append(lambertian_method())
    out = with_selfcal(out) if selfcal else out
    out = with_segments(out) if segments else out  # twins of the methods without selfcal only
    if netcal and not any(m.kind == "net" for m in out):
        raise InputError("--netcal", "reads the colour off a network's normals: give a checkpoint or --method net "
                                     "(the Lambertian baseline explains every colour as a tilt)")
    out = with_netcal(out) if netcal else out  # ... of the networks without selfcal only
    out = with_mirror(out) if mirror else out
    return with_refine(out) if refine else out


def bootstrap_ci(num: np.ndarray, den: np.ndarray, key: str, n_boot: int = N_BOOT,
                 level: float = CI_LEVEL) -> np.ndarray:
    """Percentile CI of sum(num) / sum(den) with units (columns) resampled: (M, U) -> (M, 2).

    The draws depend only on `key` and the number of units, so every row (method) gets the same ones."""
    num = np.atleast_2d(np.asarray(num, np.float64))
    den = np.broadcast_to(np.asarray(den, np.float64), num.shape)
    U = num.shape[1]
    if U == 0:
        return np.full((len(num), 2), np.nan)
    rng = np.random.default_rng([CI_SEED, zlib.crc32(key.encode())])
    stats = []
    for a in range(0, n_boot, 256):
        counts = rng.multinomial(U, np.full(U, 1.0 / U), size=min(256, n_boot - a)).astype(np.float64)
        stats.append((counts @ num.T) / np.maximum(counts @ den.T, 1e-300))  # (k, M)
    s = np.concatenate(stats)
    tail = 50.0 * (1.0 - level)
    return np.stack(np.percentile(s, [tail, 100.0 - tail], axis=0), -1)


def _legacy_methods(checkpoint, method: str) -> list[Method]:
    if method not in ("net", LAMBERTIAN):
        raise InputError("--method", f"unknown method '{method}' (net or lambertian)")
    if method == LAMBERTIAN:
        return [lambertian_method()]
    if checkpoint is None:
        from msps_render.models.predict import default_checkpoint

        checkpoint = default_checkpoint()
    return [checkpoint_method(checkpoint)]


def evaluate(data: str | Path, out: str | Path, checkpoint: str | Path | None = None, method: str = "net",
             max_patches: int | None = None, verify: bool = True, methods: list[Method] | None = None) -> dict:
    """Score `methods` (default: the checkpoint, or the baseline with `method="lambertian"`) on a dataset.

    Writes metrics.json, table.md, per_object.csv and the figures into `out`; returns the report."""
    from msps_render.data import PatchDataset, iter_frames, make_loader

    methods = methods or _legacy_methods(checkpoint, method)
    names = [m.name for m in methods]
    if len(set(names)) != len(names):
        raise InputError("--checkpoint", f"method names must differ: {', '.join(names)}")
    data, out = Path(data), Path(out)
    man = load_manifest(data, need_complete=False)
    conditions = [c.name for c in man.conditions]
    per = {m.name: {"conditions": {}} for m in methods}
    units: dict = {}  # condition -> patches: (unit keys, (M, U) error sums, (U,) pixels); frames: rows
    for cond in conditions:
        ds = PatchDataset(data, condition=cond, verify=verify)
        errs = {n: [] for n in names}
        ssims = {n: 0.0 for n in names}
        usum: dict = defaultdict(lambda: np.zeros(len(methods)))
        upix: dict = defaultdict(float)
        seen = 0
        why = ("--segments" if any(m.segments for m in methods) else
               "--netcal" if any(m.netcal for m in methods) else
               "--selfcal" if any(m.selfcal for m in methods) else "--refine")
        fits = frame_fits(data, cond, why, segment_fits=any(m.segments for m in methods),
                          netcal_methods=[m for m in methods if m.netcal]) \
            if any(m.selfcal or m.refine for m in methods) else None
        for b in make_loader(ds, 64, shuffle=False):
            g = b["normal"].numpy()
            mk = b["mask"].numpy()
            keys = list(zip(b["shard"].tolist(), b["frame"].tolist()))
            bfits = None if fits is None else [fits[(ds.shards[s][0].name, f)] for s, f in keys]
            pix = mk[:, 0].sum((1, 2))
            for k, px in zip(keys, pix):
                upix[k] += float(px)
            for j, (m, p) in enumerate(zip(methods, patch_predictions(methods, b, bfits))):
                e = angular_error_deg(p.transpose(0, 2, 3, 1), g.transpose(0, 2, 3, 1))
                errs[m.name].append(e[mk[:, 0] > 0])
                ssims[m.name] += _ssim_masked(p, g, mk) * len(p)
                for k, s in zip(keys, (e * mk[:, 0]).sum((1, 2))):
                    usum[k][j] += float(s)
            seen += len(g)
            if max_patches and seen >= max_patches:
                break
        ukeys = sorted(upix)
        num = np.stack([usum[k] for k in ukeys], 1) if ukeys else np.zeros((len(methods), 0))
        den = np.array([upix[k] for k in ukeys])
        ci = bootstrap_ci(num, den, f"patches:{cond}")
        units[cond] = {"patches": ([(cond, *k) for k in ukeys], num, den), "frames": []}
        for j, m in enumerate(methods):
            e_all = np.concatenate(errs[m.name]) if errs[m.name] else np.zeros(0)
            stats = error_stats(e_all)
            stats["hist_deg"] = error_histogram(e_all)
            stats["ssim"] = float(ssims[m.name] / max(seen, 1))
            stats["n_patches"] = seen
            stats["n_frames"] = len(ukeys)
            stats["ci95_deg"] = ci[j].tolist()
            per[m.name]["conditions"][cond] = {"patches": stats}
        # whole frames, when stored: per-object table
        try:
            frames = list(iter_frames(data, condition=cond))
        except InputError:
            frames = []
        if frames:
            rows = {n: [] for n in names}
            all_err = {n: [] for n in names}
            for fr in frames:
                for m, n in zip(methods, frame_predictions(methods, fr, None if fits is None
                                                           else fits.get((fr.shard, fr.index)))):
                    e = angular_error_deg(n[fr.mask], fr.normal[fr.mask])
                    all_err[m.name].append(e)
                    rows[m.name].append((fr.object, float(e.mean()), int(e.size), float(e.sum())))
            units[cond]["frames"] = rows
            for m in methods:
                c = per[m.name]["conditions"][cond]
                c["frames"] = error_stats(np.concatenate(all_err[m.name]))
                c["frames"]["n_frames"] = len(frames)
                det = per_object_detail(rows[m.name])  # models/report.py
                c["per_object"] = {k: v["mae_deg"] for k, v in det.items()}
                c["per_object_detail"] = det
            _frame_cis(per, names, rows, cond)
    for m in methods:
        if len(conditions) > 1:
            per[m.name]["robustness"] = robustness(per[m.name], man)
        per[m.name] = {"kind": m.kind, **m.info, **per[m.name]}
    report: dict = {"format": FORMAT, "data": str(data), "dataset": dataset_name(man), "methods": per,
                    "ci": CI_NOTE}
    report["pooled"] = _pooled(units, names, conditions)
    report["table"] = comparison_table(report)
    if len(methods) == 1:  # format-1 keys: what single-method consumers (robust_table.py, tests) read
        only = per[names[0]]
        report.update({"method": methods[0].kind, "checkpoint": only.get("checkpoint"),
                       "conditions": only["conditions"]})
        if "robustness" in only:
            report["robustness"] = only["robustness"]
    if any(c.get("per_object") for v in per.values() for c in v["conditions"].values()):
        report["per_object_note"] = PER_OBJECT_NOTE
    out.mkdir(parents=True, exist_ok=True)
    with atomic_write(out / "metrics.json") as tmp:  # a crash leaves the old metrics.json or the new one
        tmp.write_text(json.dumps(report, indent=1))
    report["files"] = [str(out / "metrics.json")] + [str(p) for p in write_tables(report, out)] + \
        [str(p) for p in write_plots(report, out)]
    return report


def _frame_cis(per: dict, names: list[str], rows: dict, cond: str) -> None:
    """CI of the frame-pooled MAE and of each object's mean of frame MAEs (bootstrap over its frames)."""
    num = np.array([[r[3] for r in rows[n]] for n in names])
    den = np.array([r[2] for r in rows[names[0]]], np.float64)
    key = f"frames:{cond}"
    ci = bootstrap_ci(num, den, key)
    objs = [r[0] for r in rows[names[0]]]
    for j, n in enumerate(names):
        c = per[n]["conditions"][cond]
        c["frames"]["ci95_deg"] = ci[j].tolist()
    for o in sorted(set(objs)):
        idx = [i for i, x in enumerate(objs) if x == o]
        oci = bootstrap_ci(np.array([[rows[n][i][1] for i in idx] for n in names]), np.ones(len(idx)),
                           f"{key}:{o}")
        for j, n in enumerate(names):
            per[n]["conditions"][cond]["per_object_detail"][o]["ci95_deg"] = oci[j].tolist()


def _pooled(units: dict, names: list[str], conditions: list[str]) -> dict:
    """Every condition together: patch pixels, whole frames and per object (mean of frame MAEs), with CIs."""
    out: dict = {n: {} for n in names}
    keys, nums, dens = [], [], []
    for cond in conditions:
        k, num, den = units[cond]["patches"]
        keys += k
        nums.append(num)
        dens.append(den)
    num, den = np.concatenate(nums, 1), np.concatenate(dens)
    ci = bootstrap_ci(num, den, "patches:*")
    for j, n in enumerate(names):
        out[n]["patches"] = {"mae_deg": float(num[j].sum() / max(den.sum(), 1.0)), "ci95_deg": ci[j].tolist(),
                             "n_frames": len(keys)}
    rows = {n: [r for c in conditions for r in (units[c]["frames"] or {}).get(n, [])] for n in names}
    if rows[names[0]]:
        fnum = np.array([[r[3] for r in rows[n]] for n in names])
        fden = np.array([r[2] for r in rows[names[0]]], np.float64)
        fci = bootstrap_ci(fnum, fden, "frames:*")
        objs = [r[0] for r in rows[names[0]]]
        for j, n in enumerate(names):
            out[n]["frames"] = {"mae_deg": float(fnum[j].sum() / fden.sum()), "ci95_deg": fci[j].tolist(),
                                "n_frames": len(objs)}
            out[n]["per_object"] = {}
        for o in sorted(set(objs)):
            idx = [i for i, x in enumerate(objs) if x == o]
            vals = np.array([[rows[n][i][1] for i in idx] for n in names])
            oci = bootstrap_ci(vals, np.ones(len(idx)), f"frames:*:{o}")
            for j, n in enumerate(names):
                out[n]["per_object"][o] = {"mae_deg": float(vals[j].mean()), "ci95_deg": oci[j].tolist(),
                                           "n_frames": len(idx)}
    return out


def comparison_table(report: dict) -> dict:
    """One table, every method a column: per condition (patch pixels, whole frames, objects), then pooled."""
    names = list(report["methods"])
    per = report["methods"]
    first = per[names[0]]["conditions"]
    rows = []

    def row(condition, what, obj, cells, n_frames, n_patches=None):
        rows.append({"condition": condition, "what": what, "object": obj, "n_frames": n_frames,
                     "n_patches": n_patches, "mae_deg": {n: cells[n].get("mae_deg") for n in names},
                     "ci95_deg": {n: cells[n].get("ci95_deg") for n in names}})

    for cond, c in first.items():
        row(cond, "patch pixels", None, {n: per[n]["conditions"][cond]["patches"] for n in names},
            c["patches"].get("n_frames"), c["patches"].get("n_patches"))
        if c.get("frames"):
            row(cond, "whole frames", None, {n: per[n]["conditions"][cond]["frames"] for n in names},
                c["frames"].get("n_frames"))
        for o, d in c.get("per_object_detail", {}).items():
            row(cond, "object", o, {n: per[n]["conditions"][cond]["per_object_detail"][o] for n in names},
                d["n_frames"])
    if len(first) > 1:
        pooled, p0 = report["pooled"], report["pooled"][names[0]]
        n_patches = sum(c["patches"].get("n_patches", 0) for c in first.values())
        row("all", "patch pixels", None, {n: pooled[n]["patches"] for n in names}, p0["patches"]["n_frames"],
            n_patches)
        if p0.get("frames"):
            row("all", "whole frames", None, {n: pooled[n]["frames"] for n in names}, p0["frames"]["n_frames"])
        for o, d in p0.get("per_object", {}).items():
            row("all", "object", o, {n: pooled[n]["per_object"][o] for n in names}, d["n_frames"])
    return {"methods": names, "unit": "deg", "rows": rows}


def dataset_name(man: Manifest) -> str:
    return (man.config.get("dataset") or {}).get("name") or man.root.resolve().name


REFERENCE_VALUES = (0, 30)  # the training-like condition of a sweep: no env light, or the 30 deg slant


def robustness(report: dict, manifest: Manifest) -> dict:
    """MAE per condition and alpha = |chi - chi'| / chi against the reference (training-like) condition."""
    conds = list(report["conditions"])
    typed = {c.name: c for c in manifest.conditions}
    values = {c: typed[c].value if c in typed else None for c in conds}
    mae = {c: report["conditions"][c]["patches"]["mae_deg"] for c in conds}
    ref = next((c for c in conds if _is_number(values[c]) and float(values[c]) in REFERENCE_VALUES), conds[0])
    chi = mae[ref]
    key = next((typed[c].key for c in conds if c in typed and typed[c].key), None)
    return {"reference": ref, "key": key, "values": values, "mae_deg": mae,
            "alpha": {c: abs(chi - v) / chi for c, v in mae.items()}}


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)
