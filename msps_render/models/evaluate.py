"""Evaluation like the paper: angular-error statistics, SSIM, per-object tables, robustness.

Patch-level metrics pool every object pixel of every patch. Whole-frame test
sets (stored with `store_frames = true`) are also predicted image by image
(tiles blended, `predict.predict_image`) for the per-object table.  With a
sweep (several conditions), MAE per condition and the paper's fluctuation
ratio alpha = |chi - chi'| / chi against the reference condition are reported
and plotted.
"""
from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from msps_render.dataset import Manifest, load_manifest
from msps_render.errors import InputError
from msps_render.models.baseline import lambertian_ps
from msps_render.models.metrics import angular_error_deg, error_stats
from msps_render.models.report import PER_OBJECT_NOTE, error_histogram, per_object_detail, write_plots


def _ssim_masked(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> float:
    """Mean SSIM over object pixels (kornia, as in the training loss)."""
    import torch

    from msps_render.models.losses import masked_ssim

    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, np.float32))
    return float(masked_ssim(t(pred), t(gt), t(mask)))


class _Predictor:
    def __init__(self, checkpoint: str | Path | None, method: str):
        self.method = method
        self.model = None
        if method == "net":
            from msps_render.models.checkpoint import load_checkpoint

            self.model, self.cfg, _ = load_checkpoint(checkpoint)

    def patches(self, b) -> np.ndarray:
        """(B, 3, P, P) normals for a batch dict."""
        if self.method == "lambertian":
            img = b["image"].numpy().transpose(0, 2, 3, 1)
            out = np.stack([lambertian_ps(img[i], b["light_dirs"][i].numpy(), b["crosstalk"][i].numpy())
                            for i in range(len(img))])
            return out.transpose(0, 3, 1, 2)
        import torch

        with torch.no_grad():
            pred, _ = self.model(b["image"], b["mask"])
        return pred.numpy()

    def frame(self, fr) -> np.ndarray:
        if self.method == "lambertian":
            return lambertian_ps(fr.image, fr.light_dirs, fr.crosstalk, fr.mask)
        from msps_render.models.predict import predict_image

        return predict_image(self.model, fr.image, fr.mask)


def evaluate(data: str | Path, out: str | Path, checkpoint: str | Path | None = None, method: str = "net",
             max_patches: int | None = None, verify: bool = True) -> dict:
    """Evaluate a checkpoint (`method="net"`) or the Lambertian baseline on a dataset directory."""
    from msps_render.data import PatchDataset, iter_frames, make_loader

    if method not in ("net", "lambertian"):
        raise InputError("--method", f"unknown method '{method}' (net or lambertian)")
    if method == "net" and checkpoint is None:
        from msps_render.models.predict import default_checkpoint

        checkpoint = default_checkpoint()
    data, out = Path(data), Path(out)
    m = load_manifest(data, need_complete=False)
    pred = _Predictor(checkpoint, method)
    conditions = [c.name for c in m.conditions]
    report: dict = {"data": str(data), "method": method, "checkpoint": str(checkpoint) if checkpoint else None,
                    "conditions": {}}
    for cond in conditions:
        ds = PatchDataset(data, condition=cond, verify=verify)
        errs, ssims, seen = [], [], 0
        for b in make_loader(ds, 64, shuffle=False):
            p = pred.patches(b)
            g = b["normal"].numpy()
            mk = b["mask"].numpy()
            e = angular_error_deg(p.transpose(0, 2, 3, 1), g.transpose(0, 2, 3, 1))
            errs.append(e[mk[:, 0] > 0])
            ssims.append(_ssim_masked(p, g, mk) * len(p))
            seen += len(p)
            if max_patches and seen >= max_patches:
                break
        stats = error_stats(np.concatenate(errs) if errs else np.zeros(0))
        stats["hist_deg"] = error_histogram(np.concatenate(errs) if errs else np.zeros(0))
        stats["ssim"] = float(np.sum(ssims) / max(seen, 1))
        stats["n_patches"] = seen
        report["conditions"][cond] = {"patches": stats}
        # whole frames, when stored: per-object table
        try:
            frames = list(iter_frames(data, condition=cond))
        except InputError:
            frames = []
        if frames:
            per_obj = defaultdict(list)
            all_err, rows = [], []
            for fr in frames:
                n = pred.frame(fr)
                e = angular_error_deg(n[fr.mask], fr.normal[fr.mask])
                per_obj[fr.object].append(float(e.mean()))
                all_err.append(e)
                rows.append((fr.object, float(e.mean()), int(e.size), float(e.sum())))
            report["conditions"][cond]["frames"] = error_stats(np.concatenate(all_err))
            report["conditions"][cond]["per_object"] = {k: float(np.mean(v)) for k, v in sorted(per_obj.items())}
            report["conditions"][cond]["per_object_detail"] = per_object_detail(rows)  # models/report.py
    if len(conditions) > 1:
        report["robustness"] = robustness(report, m)
    out.mkdir(parents=True, exist_ok=True)
    if any(v.get("per_object") for v in report["conditions"].values()):
        report["per_object_note"] = PER_OBJECT_NOTE
    (out / "metrics.json").write_text(json.dumps(report, indent=1))
    _write_tables(report, out)
    report["files"] = [str(out / "metrics.json")] + [str(p) for p in write_plots(report, out)] + \
        [str(out / n) for n in ("per_object.csv", "robustness.png") if (out / n).is_file()]
    return report


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


def _write_tables(report: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = []
    for cond, r in report["conditions"].items():
        for obj, v in r.get("per_object", {}).items():
            rows.append(f"{cond},{obj},{v:.3f}")
    if rows:
        (out / "per_object.csv").write_text("condition,object,mae_deg\n" + "\n".join(rows) + "\n")
    rb = report.get("robustness")
    if rb:
        names = list(rb["mae_deg"])
        values = rb.get("values", {})
        xs = [float(values[n]) if _is_number(values.get(n)) else float(i) for i, n in enumerate(names)]
        label = (rb.get("key") or "condition").split(".")[-1]
        fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
        ax[0].plot(xs, [rb["mae_deg"][n] for n in names], "o-")
        ax[0].set(xlabel=label, ylabel="MAE (deg)", title=report["method"])
        ax[1].plot(xs, [rb["alpha"][n] for n in names], "o-", color="C1")
        ax[1].set(xlabel=label, ylabel="fluctuation ratio alpha")
        fig.tight_layout()
        fig.savefig(out / "robustness.png", dpi=90)
        plt.close(fig)
