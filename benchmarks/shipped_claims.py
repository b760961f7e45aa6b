"""The claims of tests/test_shipped_targets.py for one checkpoint, from already rendered test sets.

Why: the slow tests re-render the unseen sets from their presets (deterministic, the same frames as
`msps render unseen-test[-grey|-colour]`) and check that a model's measured ratio to Lambertian lies
within claim +- margin.  Before replacing the shipped model, the new claims and their margins (the larger
side of the 95 % frame-bootstrap interval) are measured here from the stored renders in one pass, in the
tests' own terms: the network alone on unseen-test and unseen-test-grey, with --selfcal --refine on
unseen-test-grey and unseen-test-colour, and with --selfcal --netcal --refine on those two and
unseen-test-texture.

    python benchmarks/shipped_claims.py --model NAME=CKPT [--data-root data] [--out claims.json]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

# (test set, pipeline) as the tests measure them
CLAIMS = [("unseen-test", "net"), ("unseen-test-grey", "net"), ("unseen-test-grey", "selfcal+refine"),
          ("unseen-test-colour", "selfcal+refine"), ("unseen-test-grey", "selfcal+netcal+refine"),
          ("unseen-test-colour", "selfcal+netcal+refine"), ("unseen-test-texture", "selfcal+netcal+refine")]


def per_frame_errors(data: Path, model, pipeline: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame: summed angular error of the model through `pipeline` ("net", "selfcal+refine",
    "selfcal+netcal+refine"), of calibrated Lambertian PS on the raw image, pixels."""
    from msps_render.data import iter_frames
    from msps_render.models.baseline import lambertian_ps
    from msps_render.models.metrics import angular_error_deg
    from msps_render.models.netcal import calibrate
    from msps_render.models.predict import predict_image
    from msps_render.models.refine import refine_normals
    from msps_render.models.selfcal import self_calibrated

    net, base, count = [], [], []
    for fr in iter_frames(data):
        m = fr.mask.astype(bool)
        if pipeline != "net":
            rig = fr.crosstalk @ fr.light_dirs
            img = self_calibrated(fr.image, m, fr.light_dirs, fr.crosstalk)
            if "netcal" in pipeline:
                n, img, _ = calibrate(lambda x: predict_image(model, x, m, rig=rig), img, m, rig)
            else:
                n = predict_image(model, img, m, rig=rig)
            n, _ = refine_normals(img, m, n, fr.light_dirs, fr.crosstalk)
        else:
            n = predict_image(model, fr.image, fr.mask)
        net.append(angular_error_deg(n[m], fr.normal[m]).sum())
        base.append(angular_error_deg(lambertian_ps(fr.image, fr.light_dirs, fr.crosstalk, m)[m],
                                      fr.normal[m]).sum())
        count.append(m.sum())
    return np.array(net, np.float64), np.array(base, np.float64), np.array(count, np.float64)


def main(argv=None) -> int:
    from msps_render.models.checkpoint import load_checkpoint
    from msps_render.testing import frame_bootstrap

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", required=True, help="NAME=CHECKPOINT")
    ap.add_argument("--data-root", type=Path, default=Path("data"))
    ap.add_argument("--out", type=Path)
    a = ap.parse_args(argv)
    name, ckpt = a.model.split("=", 1)
    model = load_checkpoint(Path(ckpt))[0]
    rows = []
    for preset, sr in CLAIMS:
        net, base, count = per_frame_errors(a.data_root / preset, model, sr)
        sr = "" if sr == "net" else sr
        ratio = float(net.sum() / base.sum())
        lo, hi = frame_bootstrap(net, base)
        margin = max(ratio - lo, hi - ratio)
        rows.append({"set": preset, "pipeline": sr or "net", "mae_deg": float(net.sum() / count.sum()),
                     "lambertian_deg": float(base.sum() / count.sum()), "ratio": ratio, "ci95": [lo, hi],
                     "margin": margin, "n_frames": len(net)})
        print(f"{name} {preset}{' +' + sr if sr else ''}: {net.sum() / count.sum():.2f} vs "
              f"{base.sum() / count.sum():.2f} deg, ratio {ratio:.4f} [{lo:.4f}, {hi:.4f}], margin {margin:.4f}",
              flush=True)
    if a.out:
        a.out.write_text(json.dumps({"model": name, "checkpoint": ckpt, "claims": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
