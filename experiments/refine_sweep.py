"""Choose the Lambertian refinement's thresholds on validation frames (docs/history.md "Stage 8").

    python experiments/refine_sweep.py --data data/val-frames --data data/val-frames-grey \
        --data data/val-frames-colour --model models/dualcue-cpu-v0.4.pt --out runs/8-valsweep.json

Predicts every frame once (after the albedo-colour self-calibration, as `--selfcal --refine` does), then
scores each setting of the grid: pixel-pooled MAE per dataset and their mean.  The rule (written before
the sweep): the lowest mean wins; within 0.01 deg the more conservative setting (higher share, lower
agreement angle).  Only validation sets (procedural shapes, training materials) belong here, never a
test set.
"""
from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np

GRID = {"shadow_floor": [0.05, 0.1, 0.2], "albedo_tol": [0.05, 0.1, 0.2], "agree_deg": [15.0, 30.0, 45.0],
        "uniform_share": [0.7, 0.8, 0.85, 0.9, 0.95]}


def predicted_frames(data: Path, model) -> list[dict]:
    """Each frame's self-calibrated image, mask, rig, truth and the network's normals."""
    from msps_render.data import iter_frames
    from msps_render.models.predict import predict_image
    from msps_render.models.selfcal import self_calibrated

    out = []
    for fr in iter_frames(data):
        m = fr.mask.astype(bool)
        img = self_calibrated(fr.image, m, fr.light_dirs, fr.crosstalk)
        out.append({"image": img, "mask": m, "light_dirs": fr.light_dirs, "crosstalk": fr.crosstalk,
                    "normal": fr.normal, "net": predict_image(model, img, m, rig=fr.crosstalk @ fr.light_dirs)})
    return out


def pooled_mae(frames: list[dict], settings=None) -> float:
    """Pixel-pooled MAE of the network's normals, refined with `settings` (None: not refined)."""
    from msps_render.models.metrics import angular_error_deg
    from msps_render.models.refine import refine_normals

    errs = []
    for f in frames:
        n = f["net"] if settings is None else \
            refine_normals(f["image"], f["mask"], f["net"], f["light_dirs"], f["crosstalk"], settings)[0]
        errs.append(angular_error_deg(n[f["mask"]], f["normal"][f["mask"]]))
    return float(np.concatenate(errs).mean())


def choose(rows: list[dict]) -> dict:
    best = min(r["mean"] for r in rows)
    near = [r for r in rows if r["mean"] <= best + 0.01]
    return min(near, key=lambda r: (-r["settings"]["uniform_share"], r["settings"]["agree_deg"], r["mean"]))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", action="append", required=True, type=Path)
    ap.add_argument("--model", required=True)
    ap.add_argument("--out", required=True, type=Path)
    a = ap.parse_args(argv)
    from msps_render.models.checkpoint import load_checkpoint
    from msps_render.models.refine import RefineSettings

    model = load_checkpoint(a.model)[0]
    sets = {d.name: predicted_frames(d, model) for d in a.data}
    rows = []
    for vals in itertools.product(*GRID.values()):
        st = dict(zip(GRID, vals))
        scores = {n: pooled_mae(fr, RefineSettings(**st)) for n, fr in sets.items()}
        rows.append({"settings": st, "scores": scores, "mean": float(np.mean(list(scores.values())))})
    report = {"model": a.model, "net": {n: pooled_mae(fr) for n, fr in sets.items()}, "grid": GRID,
              "rows": rows, "chosen": choose(rows)}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(report, indent=1))
    print(f"network alone: {report['net']}")
    print(f"chosen: {report['chosen']['settings']} -> {report['chosen']['scores']} (mean {report['chosen']['mean']:.3f})")


if __name__ == "__main__":
    main()
