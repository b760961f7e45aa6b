"""Choose the self-calibration's one-albedo share (selfcal.MIN_SHARE) on validation frames (docs/history.md "Stage 9").

    python experiments/selfcal_share_sweep.py --data data/val-frames --data data/val-frames-grey \
        --data data/val-frames-colour --model models/dualcue-cpu-v0.4.pt --out runs/9-valsweep.json

Fits every frame once with no share condition, predicts the image as rendered and, where the fit
accepts, the rescaled image, then scores each `min_share` of the grid: pixel-pooled MAE of
+selfcal+refine (the documented pipeline) per dataset and their mean.  The rule (written before the
sweep, runs/9-decision.txt): the lowest mean wins; within 0.02 deg the lower share.  Validation sets
only (procedural shapes, training materials), never a test set.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

GRID = [0.0, 0.5, 0.6, 0.7, 0.8, 0.9]


def scored_frames(data: Path, model) -> list[dict]:
    """Each frame's fit (no share condition) and the refined normals with and without its factor."""
    from msps_render.data import iter_frames
    from msps_render.models.metrics import angular_error_deg
    from msps_render.models.predict import predict_image
    from msps_render.models.refine import refine_normals
    from msps_render.models.selfcal import apply_colour_fit, fit_albedo_colour

    def refined_error(img, fr, m):
        n = predict_image(model, img, m, rig=fr.crosstalk @ fr.light_dirs)
        n = refine_normals(img, m, n, fr.light_dirs, fr.crosstalk)[0]
        return angular_error_deg(n[m], fr.normal[m])

    out = []
    for fr in iter_frames(data):
        m = fr.mask.astype(bool)
        fit = fit_albedo_colour(fr.image, m, fr.light_dirs, fr.crosstalk, min_share=0.0)
        plain = refined_error(fr.image, fr, m)
        scaled = refined_error(apply_colour_fit(fr.image, fit), fr, m) if fit.applied else plain
        out.append({"object": fr.object, "applied": fit.applied, "share": fit.share, "plain": plain,
                    "scaled": scaled})
    return out


def pooled_mae(frames: list[dict], min_share: float) -> float:
    return float(np.concatenate([f["scaled"] if f["applied"] and f["share"] >= min_share else f["plain"]
                                 for f in frames]).mean())


def choose(rows: list[dict]) -> dict:
    best = min(r["mean"] for r in rows)
    return min((r for r in rows if r["mean"] <= best + 0.02), key=lambda r: r["min_share"])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", action="append", required=True, type=Path)
    ap.add_argument("--model", required=True)
    ap.add_argument("--out", required=True, type=Path)
    a = ap.parse_args(argv)
    from msps_render.models.checkpoint import load_checkpoint

    model = load_checkpoint(a.model)[0]
    sets = {d.name: scored_frames(d, model) for d in a.data}
    rows = []
    for t in GRID:
        scores = {n: pooled_mae(fr, t) for n, fr in sets.items()}
        rows.append({"min_share": t, "scores": scores, "mean": float(np.mean(list(scores.values()))),
                     "applied": {n: sum(f["applied"] and f["share"] >= t for f in fr) for n, fr in sets.items()}})
    frames = {n: [{k: f[k] for k in ("object", "applied", "share")} for f in fr] for n, fr in sets.items()}
    report = {"model": a.model, "grid": GRID, "rows": rows, "chosen": choose(rows), "frames": frames}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(report, indent=1))
    for r in rows:
        print(f"min_share {r['min_share']:.2f}: mean {r['mean']:.3f}  {r['scores']}  applied {r['applied']}")
    print(f"chosen: min_share {report['chosen']['min_share']}")


if __name__ == "__main__":
    main()
