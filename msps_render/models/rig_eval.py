"""`msps eval` on a dataset of any rig (format-2 shards): methods scored on its whole frames.

Why a path of its own: the three-light evaluation (`models.evaluate`) scores one RGB image per patch
through the dual-cue network's test-time steps; a rig frame has S images x M channels and N lights,
read by methods that take the rig itself -- calibrated least squares and the classic (order-agnostic)
network.  Every method sees the NOMINAL rig (what a user's calibration gives; the truth differs only
when the preset adds calibration errors) and is scored against the exact ground-truth normals.

One number per frame (its mean angular error over the object's pixels); objects and the dataset are
means over frames; a method's ratio to the baseline is the ratio of those means (one definition, as
bench-real's).  Methods are one registry (`RIG_METHODS`): a name and a function
(frame -> normals); a classic-network checkpoint adds its own entry (`checkpoint_method`).
"""
from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from msps_render.dataset.schema import RigFrame
from msps_render.errors import InputError

FORMAT = "msps-rig-eval-1"
ROBUST_DISCARD = (0.2, 0.1)  # darkest 20 % of the shots (shadows), brightest 10 % (highlights): fixed a priori


@dataclass(frozen=True)
class RigMethod:
    name: str
    normals: Callable[[RigFrame], np.ndarray]  # (H, W, 3) unit normals, camera frame
    info: dict


def _lambertian(frame: RigFrame) -> np.ndarray:
    from msps_render.models.baseline import lambertian_ps_rig

    return lambertian_ps_rig(frame.shots, frame.nominal, frame.mask, frame.points)


def _lambertian_robust(frame: RigFrame) -> np.ndarray:
    from msps_render.models.baseline import lambertian_ps_rig

    return lambertian_ps_rig(frame.shots, frame.nominal, frame.mask, frame.points, discard=ROBUST_DISCARD)


RIG_METHODS: dict[str, RigMethod] = {
    "lambertian": RigMethod("lambertian", _lambertian, {"kind": "baseline", "what": "calibrated least squares "
                                                        "over every reading (Woodham), grey albedo"}),
    "lambertian-robust": RigMethod("lambertian-robust", _lambertian_robust, {
        "kind": "baseline", "what": f"least squares without each pixel's darkest {ROBUST_DISCARD[0]:.0%} and "
                                    f"brightest {ROBUST_DISCARD[1]:.0%} shots"}),
}


def resolve_rig_methods(methods=(), checkpoints=(), classic_fits: bool = False) -> list[RigMethod]:
    """`--method NAME` (a registry entry, or net) and `--checkpoint [NAME=]PATH` (a classic network) ->
    methods.  Nothing given: the baseline, and the shipped classic network when the rig is one it reads
    (`classic_fits`: one image per light, far lights, three channels); `--method net` alone: the shipped one."""
    out = []
    for m in methods:
        if m == "net":
            continue  # the checkpoints below
        if m not in RIG_METHODS:
            raise InputError("--method", f"unknown method '{m}' for a rig dataset (known: "
                                         f"{', '.join(RIG_METHODS)}, net)")
        out.append(RIG_METHODS[m])
    from msps_render.models.runner import classic_predictors

    default = ("net" in methods or (not methods and classic_fits)) and not checkpoints
    for p in classic_predictors(checkpoints, default=default):
        out.append(RigMethod(p.name, p.model.predict_frame, {"kind": "network", "checkpoint": p.info["checkpoint"],
                                                              **p.model.info}))
    if not methods:
        out.insert(0, RIG_METHODS["lambertian"])
    names = [m.name for m in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError("--method", f"method '{dup[0]}' given twice")
    return out


def classic_reads(data: str | Path) -> bool:
    """Whether the classic network reads this rig dataset (its first frame's rig): one image per light, far
    lights, three channels."""
    from msps_render.dataset import load_manifest
    from msps_render.dataset.reader import open_shard, read_rigs, shard_errors

    man = load_manifest(Path(data), need_complete=False)
    for e in man.shards_of():
        p = man.shard_path(e.name)
        if p.exists():
            with shard_errors(p), open_shard(p) as h:
                _, nominal = read_rigs(h)
            r = nominal[0]
            return (r.shot_list == tuple((k,) for k in range(r.n_lights)) and not r.has_point_lights
                    and r.n_channels == 3)
    return False


def is_rig_dataset(data: str | Path) -> bool:
    """True when the dataset's shards are format 2 (any rig)."""
    from msps_render.dataset import load_manifest
    from msps_render.dataset.reader import format_version, open_shard, shard_errors

    if not (Path(data) / "dataset.json").is_file():
        return False  # not a dataset: the three-light path says what is wrong with it
    man = load_manifest(Path(data), need_complete=False)
    for e in man.shards_of():
        p = man.shard_path(e.name)
        if p.exists():
            with shard_errors(p), open_shard(p) as h:
                return format_version(h) == 2
    return False


def _angular_error(n: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((n[mask] * gt[mask]).sum(-1), -1.0, 1.0)))


def evaluate_rig(data: str | Path, out: str | Path, methods: list[RigMethod] | None = None, *,
                 progress: bool = False, max_frames: int | None = None) -> dict:
    """Score `methods` on every stored whole frame of a rig dataset; write metrics.json, table.md,
    per_object.csv into `out`; return the report."""
    from msps_render.dataset import load_manifest
    from msps_render.dataset.reader import iter_rig_frames
    from msps_render.progress import Bar

    data, out = Path(data), Path(out)
    methods = methods or [RIG_METHODS["lambertian"]]
    man = load_manifest(data, need_complete=False)
    shards = [man.shard_path(e.name) for e in man.shards_of() if man.shard_path(e.name).exists()]
    if not shards:
        raise InputError(data, "dataset has no rendered shard yet")
    n_frames = sum(e.n_frames for e in man.shards_of())
    if max_frames:
        n_frames = min(n_frames, max_frames)
    rows = []
    rig_text = None
    with Bar(progress) as bar:
        task = bar.task(f"{data.name}: frames", n_frames)
        for p in shards:
            for f in iter_rig_frames(p):
                if max_frames and len(rows) >= max_frames:
                    break
                rig_text = rig_text or f.nominal.describe()
                row = {"shard": f.shard, "frame": f.index, "object": f.object, "condition": f.condition,
                       "pixels": int(f.mask.sum())}
                for m in methods:
                    row[m.name] = float(_angular_error(m.normals(f), f.normal, f.mask).mean())
                rows.append(row)
                if task:
                    task.advance()
    if not rows:
        raise InputError(data, "no whole frames stored: render the preset with store_frames = true")
    names = [m.name for m in methods]
    objects = sorted({r["object"] for r in rows})
    per_object = {o: {n: float(np.mean([r[n] for r in rows if r["object"] == o])) for n in names}
                  | {"frames": sum(r["object"] == o for r in rows)} for o in objects}
    mean = {n: float(np.mean([r[n] for r in rows])) for n in names}
    base = names[0]
    report = {"format": FORMAT, "data": str(data), "rig": rig_text, "frames": len(rows),
              "methods": {m.name: m.info for m in methods}, "mean_deg": mean,
              "ratio_to": base, "ratio_of_means": {n: mean[n] / mean[base] for n in names},
              "per_object": per_object, "per_frame": rows}
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(report, indent=1) + "\n")
    (out / "table.md").write_text("\n".join(table_lines(report)) + "\n")
    with open(out / "per_object.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["object", "frames", *names])
        for o, d in per_object.items():
            w.writerow([o, d["frames"], *(f"{d[n]:.3f}" for n in names)])
    report["files"] = [str(out / f) for f in ("metrics.json", "table.md", "per_object.csv")]
    return report


def table_lines(report: dict) -> list[str]:
    """Per object and overall: each method's mean angular error (deg), and the ratio of means."""
    names = list(report["methods"])
    L = [f"Rig: {report['rig']}; {report['frames']} frames; mean angular error (deg) per frame, "
         f"averaged; ratio = ratio of means to {report['ratio_to']}", "",
         "| object | frames | " + " | ".join(names) + " |", "|---|---:|" + "---:|" * len(names)]
    for o, d in report["per_object"].items():
        L.append(f"| {o} | {d['frames']} | " + " | ".join(f"{d[n]:.2f}" for n in names) + " |")
    L.append("| **mean** | " + f"{report['frames']} | " + " | ".join(f"{report['mean_deg'][n]:.2f}" for n in names) + " |")
    L.append("| ratio | | " + " | ".join(f"{report['ratio_of_means'][n]:.3f}" for n in names) + " |")
    return L


def summary_lines(report: dict) -> list[str]:
    """What `msps eval` prints for a rig dataset: what ran on what, the numbers, where they are."""
    names = list(report["methods"])
    lines = [f"{report['data']}: {report['frames']} whole frames, rig {report['rig']} (nominal calibration)"]
    for n in names:
        lines.append(f"  {n}: mean angular error {report['mean_deg'][n]:.2f} deg "
                     f"(ratio of means to {report['ratio_to']}: {report['ratio_of_means'][n]:.3f}) -- "
                     f"{report['methods'][n].get('what') or report['methods'][n].get('checkpoint', '')}")
    return lines
