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


def main(argv=None) -> int:
    from msps_render.models.evaluate import frame_errors
    from msps_render.testing import frame_bootstrap

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", required=True, help="NAME=CHECKPOINT")
    ap.add_argument("--data-root", type=Path, default=Path("data"))
    ap.add_argument("--out", type=Path)
    a = ap.parse_args(argv)
    name, ckpt = a.model.split("=", 1)
    rows = []
    for preset, sr in CLAIMS:
        net, base, count = frame_errors(a.data_root / preset, Path(ckpt), "none" if sr == "net" else sr)
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
