"""How well must a textured object's albedo colour be known for the Lambertian closed form to help?

    python experiments/chroma_oracle.py --data data/unseen-test-smooth --data data/unseen-test-patches \
        --data data/unseen-test-grey --model models/dualcue-cpu-v0.4.pt --out runs/chroma-oracle.json

An upper bound, not a method: each frame's ground-truth albedo chromaticity (log albedo minus its
channel mean, so the brightness stays unknown), box-blurred over k x k pixels inside the object, is
divided out of the image and calibrated Lambertian PS gives the normals where all three lights
reach the pixel (the network's normals elsewhere).  k = 1 is the exact colour.  If even the blurred
truth does not reach a target, no local colour estimate of that resolution will (docs/history.md
"Stage 9").  Ground-truth albedo needs frames rendered with `store_frames = true` (shards from v0.5 on).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

SIZES = [1, 8, 16, 32, 64]
SHADOW_FLOOR = 0.05  # as models/refine.py: a light reaches a pixel above this share of its 99th percentile


def blurred_chroma(albedo: np.ndarray, mask: np.ndarray, k: int) -> np.ndarray:
    """(H, W, 3) log-chromaticity of `albedo`, averaged over k x k pixels of the object."""
    from scipy.ndimage import uniform_filter

    lr = np.log(np.maximum(np.asarray(albedo, np.float64), 1e-4))
    chroma = lr - lr.mean(-1, keepdims=True)
    if k == 1:
        return chroma
    w = mask.astype(np.float64)
    den = np.maximum(uniform_filter(w, k), 1e-12)
    return np.stack([uniform_filter(chroma[..., i] * w, k) / den for i in range(3)], -1)


def frame_errors(fr, net: np.ndarray) -> dict[str, np.ndarray]:
    from msps_render.models.metrics import angular_error_deg

    m = fr.mask.astype(bool)
    c = np.asarray(fr.image, np.float64)
    shading = c @ np.linalg.inv(fr.crosstalk).T
    lit = (shading > SHADOW_FLOOR * np.percentile(shading[m], 99.0, axis=0)).all(-1) & m
    Ai = np.linalg.inv(fr.crosstalk @ fr.light_dirs)
    out = {"network": angular_error_deg(net[m], fr.normal[m])}
    for k in SIZES:
        b = (c / np.exp(blurred_chroma(fr.albedo, m, k))) @ Ai.T
        n = np.where(lit[..., None], b / np.maximum(np.linalg.norm(b, axis=-1, keepdims=True), 1e-12), net)
        out[f"truth blurred {k}px" if k > 1 else "exact truth"] = angular_error_deg(n[m], fr.normal[m])
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", action="append", required=True, type=Path)
    ap.add_argument("--model", required=True)
    ap.add_argument("--out", required=True, type=Path)
    a = ap.parse_args(argv)
    from msps_render.data import iter_frames
    from msps_render.models.checkpoint import load_checkpoint
    from msps_render.models.predict import predict_image

    model = load_checkpoint(a.model)[0]
    report = {"model": a.model, "sizes": SIZES, "sets": {}}
    for d in a.data:
        errs: dict[str, list] = {}
        for fr in iter_frames(d):
            if fr.albedo is None:
                raise SystemExit(f"{d}: frames store no ground-truth albedo (render with store_frames = true, v0.5 on)")
            net = predict_image(model, fr.image, fr.mask.astype(bool), rig=fr.crosstalk @ fr.light_dirs)
            for k, e in frame_errors(fr, net).items():
                errs.setdefault(k, []).append(e)
        report["sets"][d.name] = {k: float(np.concatenate(v).mean()) for k, v in errs.items()}
        print(d.name, {k: round(v, 2) for k, v in report["sets"][d.name].items()}, flush=True)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
