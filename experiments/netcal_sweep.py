"""Choose the network-colour loop's settings on validation frames (docs/history.md "Stage 13").

    python experiments/netcal_sweep.py --data data/val-frames --data data/val-frames-grey \
        --data data/val-frames-colour --data data/val-frames-texture --model models/dualcue-cpu.pt \
        --out runs/netcal-sweep.json

Pipeline: selfcal -> network -> [estimate colour from the normals, divide, predict again] x rounds
-> refine, pixel-pooled MAE per set.  Each shade floor needs its own predictions; the rounds are
read off one loop (the normals after each round are kept) and the gate `min_colour` only decides,
per frame, whether the loop's result or the first prediction is used, so neither needs re-predicting.
Validation only: procedural shapes and training materials, never the unseen test meshes.
"""
from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np


def main(argv=None) -> None:
    from msps_render.data import iter_frames
    from msps_render.models.checkpoint import load_checkpoint
    from msps_render.models.metrics import angular_error_deg
    from msps_render.models.netcal import (NetcalSettings, chroma_agreement, divide_out, estimate_colour,
                                          pixel_ratios)
    from msps_render.models.predict import predict_image
    from msps_render.models.refine import refine_normals
    from msps_render.models.selfcal import self_calibrated

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", action="append", required=True, type=Path)
    ap.add_argument("--model", required=True, type=Path)
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--rounds", type=int, default=3, help="the most rounds tried (1..N are read off)")
    ap.add_argument("--shade-floor", type=float, nargs="+", default=[0.2])
    ap.add_argument("--min-colour", type=float, nargs="+", default=[0.0, 0.02, 0.05])
    ap.add_argument("--chroma-tol", type=float, nargs="+", default=[0.05, 0.1, 0.2])
    ap.add_argument("--min-agree", type=float, nargs="+", default=[0.0, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8])
    a = ap.parse_args(argv)
    model = load_checkpoint(a.model)[0]
    frames = []
    for d in a.data:
        for fr in iter_frames(d):
            m = fr.mask.astype(bool)
            rig = fr.crosstalk @ fr.light_dirs
            img = self_calibrated(fr.image, m, fr.light_dirs, fr.crosstalk)
            predict = lambda x: predict_image(model, x, m, rig=rig)  # noqa: E731

            def err(x, n):  # refined, as the pipeline ends
                n = refine_normals(x, m, n, fr.light_dirs, fr.crosstalk)[0]
                return float(angular_error_deg(n[m], fr.normal[m]).sum())

            n0 = predict(img)
            rec = {"set": d.name, "pixels": int(m.sum()), "base": err(img, n0), "floors": []}
            for floor in a.shade_floor:
                st = NetcalSettings(shade_floor=floor)
                scale, n, errs, first = np.ones(3), n0, [], None
                r0 = pixel_ratios(img, m, n0, rig, st)
                agree = {str(t): chroma_agreement(r0, t) for t in a.chroma_tol}
                for _ in range(a.rounds):
                    rho, _px, _ag = estimate_colour(img * scale, m, n, rig, st)
                    if rho is None:
                        break
                    scale = divide_out(scale, rho)
                    first = float(np.abs(np.log(scale)).max()) if first is None else first
                    x = (img * scale).astype(np.float32)
                    n = predict(x)
                    errs.append(err(x, n))
                rec["floors"].append({"floor": floor, "first": first, "errs": errs, "scale": scale.tolist(),
                                     "agree": agree})
            frames.append(rec)
            print(d.name, len(frames), f"{rec['base'] / rec['pixels']:.2f}",
                  [[f"{e / rec['pixels']:.2f}" for e in f["errs"]] for f in rec["floors"]], flush=True)
    sets = sorted({f["set"] for f in frames})
    rows = [{"settings": None, **{s: sum(f["base"] for f in frames if f["set"] == s)
                                  / sum(f["pixels"] for f in frames if f["set"] == s) for s in sets}}]
    grid = itertools.product(enumerate(a.shade_floor), range(1, a.rounds + 1), a.min_colour, a.chroma_tol,
                             a.min_agree)
    for (i, floor), r, g, tol, agree in grid:
        if agree == 0.0 and tol != a.chroma_tol[0]:
            continue  # no agreement gate: the tolerance does not matter
        row = {"settings": {"shade_floor": floor, "rounds": r, "min_colour": g, "chroma_tol": tol,
                            "min_agree": agree}}
        for s in sets:
            fs = [f for f in frames if f["set"] == s]
            tot, used = 0.0, 0
            for f in fs:
                fl = f["floors"][i]
                ok = (fl["first"] is not None and fl["first"] > g and len(fl["errs"]) >= 1
                      and fl["agree"][str(tol)] >= agree)
                tot += fl["errs"][min(r, len(fl["errs"])) - 1] if ok else f["base"]
                used += int(ok)
            row[s] = tot / sum(f["pixels"] for f in fs)
            row[s + ":applied"] = used
        rows.append(row)
    for r in rows:
        print(json.dumps(r))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps({"frames": frames, "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
