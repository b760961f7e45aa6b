"""Probe, not built: the network-colour loop per colour region instead of per object (docs/history.md
"Stage 13").  Validation frames only.

    python experiments/netcal_regions_probe.py --data data/val-frames --data data/val-frames-texture \
        --data data/val-frames-colour --data data/val-frames-grey --model models/dualcue-cpu.pt

Per frame: selfcal -> network -> refine ("base"); the object-level loop (models/netcal.py, "netcal");
and regions between colour edges (models/segments.colour_regions) each divided by its own colour AND
brightness read off the network's normals (median c_k / (A n)_k over the region's pixels every light
reaches, regions of >= MIN_PIXELS such pixels, the rest from the nearest region, one common scale),
then predicted again and refined: on every frame ("regN") or only where the object-level loop refused
("regfbN").  Pixel-pooled MAE per set.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

MIN_PIXELS = (100, 300)


def region_factor(img: np.ndarray, mask: np.ndarray, normals: np.ndarray, rig: np.ndarray,
                  min_pixels: int) -> np.ndarray | None:
    """(H, W, 3) factor dividing each colour region by its own albedo, or None with fewer than 2 regions."""
    from scipy import ndimage

    from msps_render.models.segments import colour_regions

    labels, _ = colour_regions(img, mask)
    s = normals @ rig.T
    c = img.astype(np.float64)
    fac, acc, k = np.zeros(img.shape), np.zeros(mask.shape, bool), 0
    for r in range(1, labels.max() + 1):
        sel = (labels == r) & (s > 0.2).all(-1)
        if sel.sum() < min_pixels:
            continue
        rho = np.median(c[sel] / s[sel], axis=0)
        if (rho > 0).all():
            fac[labels == r], acc, k = 1.0 / rho, acc | (labels == r), k + 1
    if k < 2:
        return None
    idx = ndimage.distance_transform_edt(~acc, return_distances=False, return_indices=True)
    fac = fac[idx[0], idx[1]]
    return fac / np.median(fac[mask].mean(1))


def main(argv=None) -> None:
    from msps_render.data import iter_frames
    from msps_render.models.checkpoint import load_checkpoint
    from msps_render.models.metrics import angular_error_deg
    from msps_render.models.netcal import calibrate
    from msps_render.models.predict import predict_image
    from msps_render.models.refine import refine_normals
    from msps_render.models.selfcal import self_calibrated

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", action="append", required=True, type=Path)
    ap.add_argument("--model", required=True, type=Path)
    a = ap.parse_args(argv)
    model = load_checkpoint(a.model)[0]
    for d in a.data:
        tot = {"base": 0.0, "netcal": 0.0, **{f"{k}{p}": 0.0 for p in MIN_PIXELS for k in ("reg", "regfb")}}
        px = 0
        for fr in iter_frames(d):
            m = fr.mask.astype(bool)
            rig = fr.crosstalk @ fr.light_dirs
            img = self_calibrated(fr.image, m, fr.light_dirs, fr.crosstalk)
            predict = lambda x: predict_image(model, x, m, rig=rig)  # noqa: E731

            def err(x, n):
                n = refine_normals(x, m, n, fr.light_dirs, fr.crosstalk)[0]
                return float(angular_error_deg(n[m], fr.normal[m]).sum())

            n0 = predict(img)
            px += int(m.sum())
            e0 = err(img, n0)
            tot["base"] += e0
            nn, seen, fit = calibrate(predict, img, m, rig)
            e_nc = err(seen, nn)
            tot["netcal"] += e_nc
            for p in MIN_PIXELS:
                fac = region_factor(img, m, n0, rig, p)
                x = None if fac is None else (img * fac).astype(np.float32)
                e = e0 if x is None else err(x, predict(x))
                tot[f"reg{p}"] += e
                tot[f"regfb{p}"] += e_nc if fit.applied else e
        print(d.name, {k: round(v / px, 2) for k, v in tot.items()}, flush=True)


if __name__ == "__main__":
    main()
