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
from pathlib import Path
from typing import NamedTuple

import numpy as np

from msps_render.atomic import atomic_write
from msps_render.calibration import Rig
from msps_render.dataset import Manifest, load_manifest
from msps_render.errors import InputError
from msps_render.models.metrics import angular_error_deg, error_stats
from msps_render.models.report import (PER_OBJECT_NOTE, error_histogram, per_object_detail, write_plots,
                                       write_tables)
from msps_render.models.runner import (LAMBERTIAN, FrameFit, Memo, Method, frame_fit, methods as make_methods,
                                       resolve_predictors, run, run_patches)
from msps_render.models.steps import DEFAULT_RENDERED, STEPS, Steps
from msps_render.progress import Bar
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


def resolve_methods(checkpoints=(), methods=(), columns: list[Steps] | None = None) -> list[Method]:
    """`msps eval --checkpoint [NAME=]PATH ... --method net|lambertian ... --steps S ...` -> the columns:
    every predictor (checkpoints first) under every steps value (default: `DEFAULT_RENDERED`)."""
    return make_methods(resolve_predictors(checkpoints, methods), columns or [DEFAULT_RENDERED])


class FrameRow(NamedTuple):
    """One method on one whole frame: the per-object table's unit."""

    object: str
    mae_deg: float
    n_pixels: int
    error_sum: float


def frame_pass(frames, methods: list[Method], bar=None) -> tuple[dict, dict, dict]:
    """Every method on every whole frame, sharing work per frame (`Memo`): ({method: [FrameRow]},
    {method: [per-pixel errors per frame]}, {(shard, frame index): [FrameFit per method]})."""
    rows: dict = {m.name: [] for m in methods}
    errs: dict = {m.name: [] for m in methods}
    fits: dict = {}
    for fr in frames:
        memo, rig, fs = Memo(), Rig.of(fr), []
        for m in methods:
            s = run(m, fr.image, fr.mask, rig, memo)
            e = angular_error_deg(s.normals[fr.mask], fr.normal[fr.mask])
            rows[m.name].append(FrameRow(fr.object, float(e.mean()), int(e.size), float(e.sum())))
            errs[m.name].append(e)
            fs.append(frame_fit(m, s))
        fits[(fr.shard, fr.index)] = fs
        if bar:
            bar.advance()
    return rows, errs, fits


def patch_normals(m: Method, j: int, b, fits: list[list[FrameFit]] | None, memo: Memo) -> np.ndarray:
    """Method `m`'s (B, P, P, 3) normals for one torch batch of patches (`runner.run_patches`)."""
    from msps_render.models.net import rig_matrix  # torch: imported only when patches are scored

    img, mk = b["image"].numpy().transpose(0, 2, 3, 1), b["mask"].numpy()[:, 0] > 0
    rigs = [Rig(L.numpy(), M.numpy()) for L, M in zip(b["light_dirs"], b["crosstalk"])]
    return run_patches(m, img, mk, rigs, rig_matrix(b["light_dirs"], b["crosstalk"]), b["yx"].numpy(),
                       None if fits is None else [f[j] for f in fits], memo)


def frame_errors(data, checkpoint, steps: str = "none") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per whole frame of a dataset: summed angular error of the checkpoint through `steps` (e.g.
    "selfcal+netcal+refine"), of calibrated Lambertian PS on the image as rendered, and the pixel count.
    What the shipped model's claims are measured with (tests/test_shipped_targets.py,
    benchmarks/shipped_claims.py): the same runner as `msps eval`."""
    from msps_render.data import iter_frames
    from msps_render.models.runner import checkpoint_predictor, lambertian_predictor

    net = Method("net", checkpoint_predictor(checkpoint), Steps.parse(steps))
    base = Method("lambertian", lambertian_predictor())
    out = []
    for fr in iter_frames(data):
        m, memo = fr.mask.astype(bool), Memo()
        errs = [angular_error_deg(run(k, fr.image, m, Rig.of(fr), memo).normals[m], fr.normal[m]).sum()
                for k in (net, base)]
        out.append(errs + [m.sum()])
    return tuple(np.array(c, np.float64) for c in zip(*out)) if out else (np.zeros(0),) * 3


def _whole_frame_step(methods: list[Method]) -> str | None:
    """How the user named a step that fits whole frames (a colour step first), or None."""
    for m in methods:
        names = m.steps.whole_image
        if names:
            return m.steps.where(next((n for n in names if STEPS[n].colour), names[0]))
    return None


def _defaults_without_frames(methods: list[Method], data: Path, conditions: list[str]) -> list[Method]:
    """A default (not asked-for) chain of whole-image steps cannot run on a dataset without whole frames:
    those methods are scored raw instead, with one warning line, so plain `msps eval` works on any corpus
    (asked for with --steps, the same steps still refuse with one line)."""
    if not any(m.steps.default and m.steps.whole_image for m in methods) or \
            all(_has_frames(data, c, None) for c in conditions):
        return methods
    import sys

    raw = [Method(m.predictor.name, m.predictor, Steps()) if m.steps.default and m.steps.whole_image else m
           for m in methods]
    print(f"warning: {data}: no whole frames stored, which the default steps ({DEFAULT_RENDERED}) fit each "
          "object on; scoring without steps (--steps none)", file=sys.stderr)
    return raw


def _has_frames(data: Path, cond: str, why: str | None) -> bool:
    """Whether the condition's whole frames are stored; `why` (a step that fits them) makes it required."""
    from msps_render.data import iter_frames

    try:
        next(iter(iter_frames(data, condition=cond)), None)
        return True
    except InputError:
        if why:
            raise InputError(data, f"{why} fits each object on its whole frame; this dataset has no "
                                   "whole frames (render a preset with store_frames = true)") from None
        return False


def _frames(data: Path, cond: str) -> list:
    from msps_render.data import iter_frames

    return list(iter_frames(data, condition=cond))


def _score_patches(ds, methods: list[Method], fits: dict | None, max_patches: int | None, bar=None) -> dict:
    """Every method on the condition's patches: pooled errors, SSIM, and error sums per frame (units)."""
    names = [m.name for m in methods]
    errs = {n: [] for n in names}
    ssims = {n: 0.0 for n in names}
    usum: dict = defaultdict(lambda: np.zeros(len(methods)))
    upix: dict = defaultdict(float)
    seen = 0
    from msps_render.data import make_loader

    for b in make_loader(ds, 64, shuffle=False):
        g = b["normal"].numpy().transpose(0, 2, 3, 1)
        mk = b["mask"].numpy()
        keys = list(zip(b["shard"].tolist(), b["frame"].tolist()))
        bfits = None if fits is None else [fits[(ds.shards[s][0].name, f)] for s, f in keys]
        for k, px in zip(keys, mk[:, 0].sum((1, 2))):
            upix[k] += float(px)
        memo, scored = Memo(), {}
        for j, m in enumerate(methods):
            p = patch_normals(m, j, b, bfits, memo)
            if id(p) not in scored:  # columns whose normals are the very same array share their scores
                scored[id(p)] = (p, angular_error_deg(p, g),
                                 _ssim_masked(p.transpose(0, 3, 1, 2), g.transpose(0, 3, 1, 2), mk))
            e, ssim = scored[id(p)][1:]
            errs[m.name].append(e[mk[:, 0] > 0])
            ssims[m.name] += ssim * len(p)
            for k, s in zip(keys, (e * mk[:, 0]).sum((1, 2))):
                usum[k][j] += float(s)
        seen += len(g)
        if bar:
            bar.advance(len(g))
        if max_patches and seen >= max_patches:
            break
    return {"errs": errs, "ssims": ssims, "usum": usum, "upix": upix, "seen": seen}


def _patch_stats(cond: str, methods: list[Method], sc: dict) -> tuple[dict, tuple]:
    """Per method the condition's patch statistics (with the frame-bootstrap CI); and its units."""
    ukeys = sorted(sc["upix"])
    num = np.stack([sc["usum"][k] for k in ukeys], 1) if ukeys else np.zeros((len(methods), 0))
    den = np.array([sc["upix"][k] for k in ukeys])
    ci = bootstrap_ci(num, den, f"patches:{cond}")
    out = {}
    for j, m in enumerate(methods):
        e_all = np.concatenate(sc["errs"][m.name]) if sc["errs"][m.name] else np.zeros(0)
        stats = error_stats(e_all)
        stats.update(hist_deg=error_histogram(e_all), ssim=float(sc["ssims"][m.name] / max(sc["seen"], 1)),
                     n_patches=sc["seen"], n_frames=len(ukeys), ci95_deg=ci[j].tolist())
        out[m.name] = stats
    return out, ([(cond, *k) for k in ukeys], num, den)


def _frame_stats(per: dict, cond: str, methods: list[Method], rows: dict, errs: dict) -> None:
    """Whole-frame statistics and the per-object table of one condition, with their CIs, into `per`."""
    names = [m.name for m in methods]
    for n in names:
        c = per[n]["conditions"][cond]
        c["frames"] = error_stats(np.concatenate(errs[n]))
        c["frames"]["n_frames"] = len(rows[n])
        det = per_object_detail(rows[n])  # models/report.py
        c["per_object"] = {k: v["mae_deg"] for k, v in det.items()}
        c["per_object_detail"] = det
    _frame_cis(per, names, rows, cond)


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


def evaluate(data: str | Path, out: str | Path, methods: list[Method] | None = None, *,
             max_patches: int | None = None, verify: bool = True, progress: bool = False) -> dict:
    """Score `methods` (default: the shipped checkpoint with the default steps) on a dataset.

    Per condition: every method on the whole frames (when stored; the steps' fits come from them), then
    on the patches.  Writes metrics.json, table.md, per_object.csv and the figures into `out`; returns
    the report.  `progress`: a rich progress line per stage on stderr."""
    from msps_render.data import PatchDataset

    methods = methods or resolve_methods()
    data, out = Path(data), Path(out)
    man = load_manifest(data, need_complete=False)
    conditions = [c.name for c in man.conditions]
    sets = {c: PatchDataset(data, condition=c, verify=verify) for c in conditions}  # every check before any work
    methods = _defaults_without_frames(methods, data, conditions)  # (its warning after the data checked out)
    names = [m.name for m in methods]
    if len(set(names)) != len(names):
        raise InputError("--checkpoint", f"method names must differ: {', '.join(names)}")
    why = _whole_frame_step(methods)
    per = {n: {"conditions": {}} for n in names}
    units: dict = {}  # condition -> patches: (unit keys, (M, U) error sums, (U,) pixels); frames: rows
    stored = {c: _has_frames(data, c, why) for c in conditions}
    with Bar(progress) as bar:
        for cond in conditions:
            ds, frames = sets[cond], _frames(data, cond) if stored[cond] else []
            rows, errs, fits = frame_pass(frames, methods, bar.task(f"{cond or data.name}: frames", len(frames)))
            n_patches = len(ds) if not max_patches else min(len(ds), max_patches)
            sc = _score_patches(ds, methods, fits if why else None, max_patches,
                                bar.task(f"{cond or data.name}: patches", n_patches))
            stats, units_p = _patch_stats(cond, methods, sc)
            units[cond] = {"patches": units_p, "frames": rows if frames else []}
            for n in names:
                per[n]["conditions"][cond] = {"patches": stats[n]}
            if frames:
                _frame_stats(per, cond, methods, rows, errs)
    report = _report(data, man, methods, per, units, conditions)
    return _write(report, out)


def _report(data: Path, man: Manifest, methods: list[Method], per: dict, units: dict,
            conditions: list[str]) -> dict:
    """metrics.json's content: per method, pooled over conditions, the comparison table (and the format-1
    keys of a single-method run, what robust_table.py and older readers take)."""
    names = [m.name for m in methods]
    for m in methods:
        if len(conditions) > 1:
            per[m.name]["robustness"] = robustness(per[m.name], man)
        per[m.name] = {"kind": m.kind, **m.info, **per[m.name]}
    report: dict = {"format": FORMAT, "data": str(data), "dataset": dataset_name(man), "methods": per,
                    "ci": CI_NOTE}
    report["pooled"] = _pooled(units, names, conditions)
    report["table"] = comparison_table(report)
    if len(methods) == 1:
        only = per[names[0]]
        report.update({"method": methods[0].kind, "checkpoint": only.get("checkpoint"),
                       "conditions": only["conditions"]})
        if "robustness" in only:
            report["robustness"] = only["robustness"]
    if any(c.get("per_object") for v in per.values() for c in v["conditions"].values()):
        report["per_object_note"] = PER_OBJECT_NOTE
    return report


def _write(report: dict, out: Path) -> dict:
    """metrics.json (atomically: a crash leaves the old one or the new one), the tables and the figures."""
    out.mkdir(parents=True, exist_ok=True)
    with atomic_write(out / "metrics.json") as tmp:
        tmp.write_text(json.dumps(report, indent=1))
    report["files"] = [str(out / "metrics.json")] + [str(p) for p in write_tables(report, out)] + \
        [str(p) for p in write_plots(report, out)]
    return report


def _frame_cis(per: dict, names: list[str], rows: dict, cond: str) -> None:
    """CI of the frame-pooled MAE and of each object's mean of frame MAEs (bootstrap over its frames)."""
    num = np.array([[r.error_sum for r in rows[n]] for n in names])
    den = np.array([r.n_pixels for r in rows[names[0]]], np.float64)
    key = f"frames:{cond}"
    ci = bootstrap_ci(num, den, key)
    objs = [r.object for r in rows[names[0]]]
    for j, n in enumerate(names):
        c = per[n]["conditions"][cond]
        c["frames"]["ci95_deg"] = ci[j].tolist()
    for o in sorted(set(objs)):
        idx = [i for i, x in enumerate(objs) if x == o]
        oci = bootstrap_ci(np.array([[rows[n][i].mae_deg for i in idx] for n in names]), np.ones(len(idx)),
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
        fnum = np.array([[r.error_sum for r in rows[n]] for n in names])
        fden = np.array([r.n_pixels for r in rows[names[0]]], np.float64)
        fci = bootstrap_ci(fnum, fden, "frames:*")
        objs = [r.object for r in rows[names[0]]]
        for j, n in enumerate(names):
            out[n]["frames"] = {"mae_deg": float(fnum[j].sum() / fden.sum()), "ci95_deg": fci[j].tolist(),
                                "n_frames": len(objs)}
            out[n]["per_object"] = {}
        for o in sorted(set(objs)):
            idx = [i for i, x in enumerate(objs) if x == o]
            vals = np.array([[rows[n][i].mae_deg for i in idx] for n in names])
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
