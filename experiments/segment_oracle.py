"""An upper bound for `--segments`: the same per-region fit, given the TRUE colour regions.

    python experiments/segment_oracle.py --data data/unseen-test-patches --model models/dualcue-cpu-v0.4.pt

Not a method and it chooses nothing: the regions come from the frame's ground-truth albedo (rounded to
3 decimals; regions >= 300 pixels), each gets the unit-norm fit of models/selfcal.py (unnormalised, so
colour and brightness), pixels outside them the median factor; then the network and the refinement.
How far the image-based segmentation (models/segments.py) is from what true regions would give
(docs/history.md "Stage 12").  Needs frames with ground-truth albedo (shards from v0.5 on).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def true_region_factors(fr, min_pixels: int = 300) -> np.ndarray:
    """(H, W, 3) unit-norm factors fitted per ground-truth colour region."""
    from msps_render.models.selfcal import fit_scale

    m = fr.mask.astype(bool)
    c = np.asarray(fr.image, np.float64)
    Ai = np.linalg.inv(fr.crosstalk @ fr.light_dirs)
    B = Ai.T @ Ai
    _, inv, counts = np.unique(np.round(np.asarray(fr.albedo, np.float64), 3)[m], axis=0, return_inverse=True,
                               return_counts=True)
    idx = np.flatnonzero(m.ravel())
    scale = np.full(c.shape, np.nan)
    for s in np.flatnonzero(counts >= min_pixels):
        pix = idx[inv.ravel() == s]
        cc = c.reshape(-1, 3)[pix]
        lit = (cc > 0.1 * np.percentile(cc, 99, axis=0)).all(1)
        if lit.sum() < 200:
            continue
        a = fit_scale(cc[lit], B)
        if np.all(a > 0):
            scale.reshape(-1, 3)[pix] = a
    have = np.isfinite(scale).all(-1)
    scale[~have] = np.nanmedian(scale[have], axis=0) if have.any() else 1.0
    return scale


def main(argv=None) -> None:
    from msps_render.data import iter_frames
    from msps_render.models.checkpoint import load_checkpoint
    from msps_render.models.metrics import angular_error_deg
    from msps_render.models.predict import predict_image
    from msps_render.models.refine import refine_normals

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, type=Path)
    ap.add_argument("--model", required=True, type=Path)
    a = ap.parse_args(argv)
    model = load_checkpoint(a.model)[0]
    err = {"network": 0.0, "true regions": 0.0, "true regions +refine": 0.0}
    count = 0
    for fr in iter_frames(a.data):
        m = fr.mask.astype(bool)
        rig = fr.crosstalk @ fr.light_dirs
        img = (np.asarray(fr.image, np.float64) * true_region_factors(fr)).astype(np.float32)
        n_reg = predict_image(model, img, m, rig=rig)
        for k, n in (("network", predict_image(model, fr.image, m, rig=rig)), ("true regions", n_reg),
                     ("true regions +refine", refine_normals(img, m, n_reg, fr.light_dirs, fr.crosstalk)[0])):
            err[k] += float(angular_error_deg(n[m], fr.normal[m]).sum())
        count += int(m.sum())
    for k, v in err.items():
        print(f"{a.data.name}: {k} {v / count:.2f} deg (pixel-pooled)")


if __name__ == "__main__":
    main()
