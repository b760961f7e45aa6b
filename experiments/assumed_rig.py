"""Whole-image steps under a rig that is not the one assumed: the nominal rig given, another one true.

    python experiments/assumed_rig.py --data data/unseen-rig-crosstalk --data data/unseen-rig-jitter \
        --model v0.4=models/dualcue-cpu-v0.4.pt --out runs/assumed-rig

A user states the paper's rig (slant 30 deg, tilts 0/120/240, crosstalk 0.92/0.04); the frames of the
rig-sweep sets were rendered with another crosstalk or with jittered lights.  Every frame is predicted
with the *nominal* rig in every step (the self-calibration's fit, the refinement, the network's rig input,
Lambertian PS), and scored against its ground truth: pixel-pooled MAE per condition for NAME,
NAME+selfcal, NAME+selfcal+refine and Lambertian.  Writes OUT/assumed_rig.json and OUT/assumed_rig.md.
"""
from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", action="append", required=True, type=Path)
    ap.add_argument("--model", action="append", required=True, help="NAME=checkpoint.pt")
    ap.add_argument("--out", required=True, type=Path)
    a = ap.parse_args(argv)
    from msps_render.calibration import PAPER_CROSSTALK, direction_from_slant_tilt
    from msps_render.data import iter_frames
    from msps_render.dataset import load_manifest
    from msps_render.models.baseline import lambertian_ps
    from msps_render.models.checkpoint import load_checkpoint
    from msps_render.models.metrics import angular_error_deg
    from msps_render.models.predict import predict_image
    from msps_render.models.refine import refine_normals
    from msps_render.models.selfcal import self_calibrated

    L = np.stack([direction_from_slant_tilt(30.0, t) for t in (0.0, 120.0, 240.0)])
    M = PAPER_CROSSTALK
    models = {n: load_checkpoint(p)[0] for n, p in (s.split("=", 1) for s in a.model)}
    result: dict = {"nominal": {"light_dirs": L.tolist(), "crosstalk": M.tolist()}, "data": {}}
    md = ["Pixel-pooled MAE (deg), every step given the nominal rig (experiments/assumed_rig.py)", ""]
    for d in a.data:
        conds = [c.name for c in load_manifest(d).conditions]
        errs: dict = defaultdict(lambda: defaultdict(list))
        for cond in conds:
            for fr in iter_frames(d, condition=cond):
                m = fr.mask.astype(bool)
                cal = self_calibrated(fr.image, m, L, M)
                preds = {"lambertian": lambertian_ps(fr.image, L, M, m)}
                for name, model in models.items():
                    preds[name] = predict_image(model, fr.image, m, rig=M @ L)
                    preds[name + "+selfcal"] = n = predict_image(model, cal, m, rig=M @ L)
                    preds[name + "+selfcal+refine"] = refine_normals(cal, m, n, L, M)[0]
                for k, n in preds.items():
                    errs[cond][k].append(angular_error_deg(n[m], fr.normal[m]))
        names = list(next(iter(errs.values())))
        table = {c: {k: float(np.concatenate(v).mean()) for k, v in errs[c].items()} for c in conds}
        result["data"][d.name] = table
        md += [f"**{d.name}**", "", "| condition | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
        md += [f"| {c} | " + " | ".join(f"{table[c][k]:.2f}" for k in names) + " |" for c in conds] + [""]
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "assumed_rig.json").write_text(json.dumps(result, indent=1))
    (a.out / "assumed_rig.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
