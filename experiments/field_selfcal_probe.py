"""Can the unit length of the normals pin a *spatially varying* albedo colour, as it pins a uniform one?

    python experiments/field_selfcal_probe.py --data data/unseen-test-smooth --data data/unseen-test-patches \
        --out runs/field-selfcal.json

A probe, not a method (docs/history.md "Stage 11").  `models/selfcal.py` fits one albedo
a = 1/rho per object from || A^-1 diag(a) c(x) || = 1 over its lit pixels.  Here a(x) is a smooth
field instead: log a on a `--grid` x `--grid` lattice, bilinear over the frame, a squared-gradient
penalty `--lam`, fitted by L-BFGS from the grey start.  Per frame it reports the normals' error where
all three lights reach (pixels also above 10 % of each channel's 99th percentile) for calibrated
Lambertian PS with no albedo, with the fitted field, and with the true per-pixel albedo; and the
data loss of the fit against the data loss of the truth.  When the fit's loss is as low as the
truth's with normals far from it, the constraint cannot tell the two apart: the ambiguity, not the
optimiser, is what is left.  Needs frames stored with their albedo (`store_frames`, shards from v0.5).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def unit_norm_loss(c, a, lit, Ai):
    """mean over lit pixels of (|A^-1 diag(a) c|^2 - 1)^2 (torch tensors)."""
    b = (c * a)[lit] @ Ai.T
    r = (b * b).sum(-1) - 1.0
    return (r * r).mean()


def fit_field(image: np.ndarray, lit: np.ndarray, A: np.ndarray, grid: int, lam: float, iters: int):
    """(fitted a (H, W, 3), its data loss): log a on a grid, bilinear, smoothness `lam`."""
    import torch
    import torch.nn.functional as F

    H, W, _ = image.shape
    Ai = torch.tensor(np.linalg.inv(A), dtype=torch.float32)
    c = torch.tensor(image, dtype=torch.float32)
    lt = torch.tensor(lit)
    u = torch.zeros(1, 3, grid, grid)
    u -= torch.log((c[lt] @ Ai.T).norm(dim=-1).median())  # the grey start: median |b| = 1
    u.requires_grad_(True)
    opt = torch.optim.LBFGS([u], lr=1, max_iter=iters, line_search_fn="strong_wolfe")

    def field():
        return torch.exp(F.interpolate(u, size=(H, W), mode="bilinear", align_corners=True))[0].permute(1, 2, 0)

    def closure():
        opt.zero_grad()
        smooth = ((u[:, :, 1:] - u[:, :, :-1]) ** 2).mean() + ((u[:, :, :, 1:] - u[:, :, :, :-1]) ** 2).mean()
        loss = unit_norm_loss(c, field(), lt, Ai) + lam * smooth
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        a = field()
        return a.numpy().astype(np.float64), float(unit_norm_loss(c, a, lt, Ai))


def frame_row(fr, grid: int, lam: float, iters: int) -> dict:
    import torch

    from msps_render.models.metrics import angular_error_deg

    img, gt, m = fr.image.astype(np.float64), fr.normal.astype(np.float64), fr.mask
    A = fr.crosstalk.astype(np.float64) @ fr.light_dirs.astype(np.float64)
    top = np.percentile(img[m], 99.0, axis=0)
    lit = m & (img > 0.1 * top).all(-1) & ((gt @ fr.light_dirs.T) > 0.02).all(-1)
    Ai = np.linalg.inv(A)
    a_true = 1.0 / np.maximum(fr.albedo.astype(np.float64), 1e-4)
    a_true /= np.median(np.linalg.norm((img * a_true)[lit] @ Ai.T, axis=-1))
    a_fit, loss_fit = fit_field(img, lit, A, grid, lam, iters)
    t = torch.tensor
    loss_true = float(unit_norm_loss(t(img, dtype=torch.float32), t(a_true, dtype=torch.float32), t(lit),
                                     t(Ai, dtype=torch.float32)))

    def err(a):
        return float(angular_error_deg((img * a) @ Ai.T, gt)[lit].mean())

    return {"object": fr.object, "pixels": int(lit.sum()), "grey_deg": err(np.ones(3)),
            "field_deg": err(a_fit), "true_albedo_deg": err(a_true), "loss_field": loss_fit, "loss_true": loss_true}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", action="append", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--grid", type=int, default=16)
    ap.add_argument("--lam", type=float, default=1e-2)
    ap.add_argument("--iters", type=int, default=200)
    ap.add_argument("--frames-per-shard", type=int, default=1)
    a = ap.parse_args(argv)
    from msps_render.dataset import iter_whole_frames

    report = {"grid": a.grid, "lam": a.lam, "iters": a.iters, "sets": {}}
    for d in a.data:
        rows = []
        for shard in sorted(Path(d, "shards").glob("*.h5")):
            for i, fr in enumerate(iter_whole_frames(shard)):
                if i >= a.frames_per_shard:
                    break
                rows.append(frame_row(fr, a.grid, a.lam, a.iters))
                r = rows[-1]
                print(f"{Path(d).name} {r['object']}: grey {r['grey_deg']:.2f}  field {r['field_deg']:.2f}  "
                      f"true albedo {r['true_albedo_deg']:.2f} deg | loss field {r['loss_field']:.2e} "
                      f"true {r['loss_true']:.2e}", flush=True)
        mean = {k: float(np.mean([r[k] for r in rows])) for k in ("grey_deg", "field_deg", "true_albedo_deg")}
        below = sum(r["loss_field"] <= r["loss_true"] for r in rows)
        report["sets"][Path(d).name] = {"frames": rows, "mean": mean, "fit_loss_at_or_below_truth": below}
        print(f"{Path(d).name} mean: {mean}; fit loss <= truth loss on {below}/{len(rows)} frames")
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
