"""Choose the segment-wise self-calibration's thresholds on validation frames (docs/history.md "Stage 12").

    python experiments/segment_sweep.py --data data/val-frames-texture --data data/val-frames-grey \
        --data data/val-frames-colour --model models/dualcue-cpu-v0.4.pt --out runs/segment-sweep.json

Pipeline: selfcal -> [segment-wise fit] -> network -> refine, pixel-pooled MAE per set.  The regions'
settings (edge, min_share) need a network pass each; the object-level gates (min_regions, object_share)
only choose, per frame, between the two predictions, so they are swept without re-predicting.
Validation only: procedural shapes and training materials, never the unseen test meshes.
"""
from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np

REGION_GRID = {"edge": [0.06, 0.08, 0.12], "min_share": [0.8, 0.9], "local_floor": [0]}
GATE_GRID = {"min_regions": [1, 2, 3], "object_share": [0.0, 0.7, 0.8, 0.85, 0.9]}


def _predict(model, fr, img):
    from msps_render.models.predict import predict_image
    from msps_render.models.refine import refine_normals

    m = fr.mask.astype(bool)
    n = predict_image(model, img, m, rig=fr.crosstalk @ fr.light_dirs)
    return refine_normals(img, m, n, fr.light_dirs, fr.crosstalk)[0]


def main(argv=None) -> None:
    from msps_render.data import iter_frames
    from msps_render.models.checkpoint import load_checkpoint
    from msps_render.models.metrics import angular_error_deg
    from msps_render.models.segments import SegmentSettings, fit_segments
    from msps_render.models.selfcal import self_calibrated

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", action="append", required=True, type=Path)
    ap.add_argument("--model", required=True, type=Path)
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--edge", type=float, nargs="+", default=REGION_GRID["edge"])
    ap.add_argument("--min-share", type=float, nargs="+", default=REGION_GRID["min_share"])
    ap.add_argument("--local-floor", type=int, nargs="+", default=REGION_GRID["local_floor"])
    ap.add_argument("--fill", nargs="+", default=["nearest"], choices=["nearest", "consistent"])
    ap.add_argument("--rel-floor", type=float, nargs="+", default=[0.1])
    ap.add_argument("--min-pixels", type=int, nargs="+", default=[150])
    a = ap.parse_args(argv)
    model = load_checkpoint(a.model)[0]
    regions = list(itertools.product(a.edge, a.min_share, a.local_floor, a.fill, a.rel_floor, a.min_pixels))
    frames = []  # per frame: set, pixels, base error sum, per region setting (n_accepted, object_share, error sum)
    for d in a.data:
        for fr in iter_frames(d):
            m = fr.mask.astype(bool)
            img = self_calibrated(fr.image, m, fr.light_dirs, fr.crosstalk)
            err = lambda n: float(angular_error_deg(n[m], fr.normal[m]).sum())  # noqa: E731
            rec = {"set": d.name, "pixels": int(m.sum()), "base": err(_predict(model, fr, img)), "fits": []}
            for edge, share, lf, fill, floor, px in regions:
                fit = fit_segments(img, m, fr.light_dirs, fr.crosstalk,
                                   SegmentSettings(edge=edge, min_share=share, min_regions=1, object_share=0.0,
                                                   local_floor=lf, fill=fill, rel_floor=floor, min_pixels=px))
                e = err(_predict(model, fr, (img * fit.scale).astype(np.float32))) if fit.applied else rec["base"]
                rec["fits"].append({"accepted": len(fit.accepted), "object_share": fit.object_share,
                                    "applied": fit.applied, "err": e})
            frames.append(rec)
            print(d.name, len(frames), f"{rec['base'] / rec['pixels']:.2f}",
                  [f"{f['err'] / rec['pixels']:.2f}" for f in rec["fits"]], flush=True)
    sets = sorted({f["set"] for f in frames})
    rows = [{"settings": None, **{s: sum(f["base"] for f in frames if f["set"] == s)
                                  / sum(f["pixels"] for f in frames if f["set"] == s) for s in sets}}]
    for i, (edge, share, lf, fill, floor, px) in enumerate(regions):
        for k, osh in itertools.product(GATE_GRID["min_regions"], GATE_GRID["object_share"]):
            row = {"settings": {"edge": edge, "min_share": share, "local_floor": lf, "fill": fill, "rel_floor": floor,
                                "min_pixels": px, "min_regions": k, "object_share": osh}}
            for s in sets:
                fs = [f for f in frames if f["set"] == s]
                use = [f["fits"][i]["applied"] and f["fits"][i]["accepted"] >= k
                       and f["fits"][i]["object_share"] >= osh for f in fs]
                row[s] = sum(f["fits"][i]["err"] if u else f["base"] for f, u in zip(fs, use)) / sum(f["pixels"] for f in fs)
                row[s + ":applied"] = int(sum(use))
            rows.append(row)
    for r in rows:
        print(json.dumps(r))
    a.out.write_text(json.dumps({"frames": frames, "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
