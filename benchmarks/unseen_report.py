"""Per-object table and side-by-side normal maps on whole-frame test sets (docs/history.md).

For each test dataset (stored with whole frames) and each method — checkpoints
given as NAME=PATH, plus the calibrated Lambertian baseline — predicts every
frame, and reports per object the mean over its frames of the per-frame MAE
(object pixels), plus the pixel-pooled MAE over all frames and the ratio of
each method to the baseline. Writes `report.json`, `report.md` and one PNG per
dataset with the first frame of every object: image, ground truth, each method.

    python benchmarks/unseen_report.py --data data/unseen-test --data data/unseen-test-grey \
        --model dual=runs/dual/best.pt --model scn=runs/scn/best.pt --model pcn=runs/pcn/best.pt \
        --out runs/report

The per-object table (with 95 % CIs, patch-level numbers and figures) is also what one
`msps eval --data D --checkpoint dual=... --checkpoint scn=... --method lambertian` writes
(table.md, metrics.json); this script adds the normal-map sheet and several datasets at once.
"""
from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np


def _methods(models: list[str], steps: list[str], **old: bool):
    """NAME=PATH checkpoints and the baseline, each under every --steps value (or the old step flags), as
    `msps eval` builds its columns (msps_render.models.runner.methods)."""
    from msps_render.models.runner import checkpoint_predictor, lambertian_predictor, methods
    from msps_render.models.steps import Steps, from_flags

    preds = [checkpoint_predictor(path, name) for name, path in (spec.split("=", 1) for spec in models)]
    return methods(preds + [lambertian_predictor()], from_flags(True, **old) or [Steps.parse(s) for s in steps]
                   or [Steps()])


def report(data: Path, methods: list) -> tuple[dict, list]:
    from msps_render.calibration import Rig
    from msps_render.data import iter_frames
    from msps_render.models.metrics import angular_error_deg
    from msps_render.models.runner import Memo, run

    preds = [m.name for m in methods]

    per_obj = {k: defaultdict(list) for k in preds}
    pooled = {k: [] for k in preds}
    shown: dict[str, dict] = {}
    for fr in iter_frames(data):
        m = fr.mask.astype(bool)
        memo = Memo()
        for meth in methods:
            name, n = meth.name, run(meth, fr.image, fr.mask, Rig.of(fr), memo).normals
            e = angular_error_deg(n[m], fr.normal[m])
            per_obj[name][fr.object].append(float(e.mean()))
            pooled[name].append(e)
            if fr.object not in shown or name not in shown[fr.object]["pred"]:
                shown.setdefault(fr.object, {"image": fr.image, "normal": fr.normal, "mask": m, "pred": {}})
                if name not in shown[fr.object]["pred"]:
                    shown[fr.object]["pred"][name] = (n, float(e.mean()))
    res = {"data": str(data), "methods": {}}
    base = float(np.concatenate(pooled["lambertian"]).mean())
    for name in preds:
        mae = float(np.concatenate(pooled[name]).mean())
        res["methods"][name] = {"mae_deg": mae, "ratio_to_lambertian": mae / base,
                                "median_deg": float(np.median(np.concatenate(pooled[name]))),
                                "per_object": {o: float(np.mean(v)) for o, v in sorted(per_obj[name].items())},
                                "n_frames": sum(len(v) for v in per_obj[name].values())}
    return res, sorted(shown.items())


def figure(shown: list, out: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = list(shown[0][1]["pred"])
    cols = 2 + len(methods)
    fig, axes = plt.subplots(len(shown), cols, figsize=(1.9 * cols, 1.9 * len(shown)), squeeze=False)
    for r, (obj, s) in enumerate(shown):
        img = s["image"] / max(float(np.percentile(s["image"][s["mask"]], 99)), 1e-6)
        tiles = [(np.clip(img, 0, 1) ** (1 / 2.2), f"{obj}"), ((s["normal"] + 1) / 2 * s["mask"][..., None], "truth")]
        tiles += [((n + 1) / 2 * s["mask"][..., None], f"{k} {e:.1f}°") for k, (n, e) in s["pred"].items()]
        for c, (t, lab) in enumerate(tiles):
            ax = axes[r, c]
            ax.imshow(np.clip(t, 0, 1))
            ax.set_title(lab, fontsize=8)
            ax.axis("off")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    plt.close(fig)


def markdown(res: dict) -> str:
    methods = list(res["methods"])
    objs = list(res["methods"]["lambertian"]["per_object"])
    lines = [f"`{res['data']}` — MAE (°), per object = mean over its frames; all = pixel-pooled", "",
             "| object | " + " | ".join(methods) + " |", "|---" * (len(methods) + 1) + "|"]
    for o in objs:
        lines.append(f"| {o} | " + " | ".join(f"{res['methods'][k]['per_object'][o]:.2f}" for k in methods) + " |")
    lines.append("| **all** | " + " | ".join(f"**{res['methods'][k]['mae_deg']:.2f}**" for k in methods) + " |")
    lines.append("| ratio to Lambertian | " + " | ".join(f"{res['methods'][k]['ratio_to_lambertian']:.2f}"
                                                         for k in methods) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", action="append", required=True, type=Path)
    ap.add_argument("--model", action="append", default=[], help="NAME=checkpoint.pt")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--steps", action="append", default=[], help="test-time steps, e.g. selfcal+netcal+refine "
                    "or none; repeat to compare (as `msps eval --steps`)")
    for name in ("selfcal", "segments", "netcal", "mirror", "refine"):  # the old flags, as `msps eval` keeps them
        ap.add_argument(f"--{name}", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    methods = _methods(a.model, a.steps, selfcal=a.selfcal, segments=a.segments, netcal=a.netcal, mirror=a.mirror,
                       refine=a.refine)
    all_res, md = [], []
    for d in a.data:
        res, shown = report(d, methods)
        all_res.append(res)
        md.append(markdown(res))
        figure(shown, a.out / f"{d.name}.png", f"{d.name}: normal maps (MAE per frame)")
        print(md[-1])
    (a.out / "report.json").write_text(json.dumps(all_res, indent=1))
    (a.out / "report.md").write_text("\n".join(md))


if __name__ == "__main__":
    main()
