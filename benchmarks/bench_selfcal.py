"""Cost of the colour self-calibration and the Lambertian refinement against the whole-image prediction.

    OMP_NUM_THREADS=1 python benchmarks/bench_selfcal.py --data data/unseen-test-colour --frames 8

One `fit_albedo_colour`, one `predict_image` (shipped checkpoint, 1 thread) and one `refine_normals`
per frame, interleaved; prints medians and the median of the per-frame ratios (timings are noisy here:
compare ratios).
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--frames", type=int, default=8)
    a = ap.parse_args(argv)
    import torch

    from msps_render.data import iter_frames
    from msps_render.models.checkpoint import load_checkpoint
    from msps_render.models.predict import default_checkpoint, predict_image
    from msps_render.models.refine import refine_normals
    from msps_render.models.selfcal import fit_albedo_colour

    torch.set_num_threads(1)
    model = load_checkpoint(default_checkpoint())[0]
    fit_s, pred_s, ref_s = [], [], []
    for i, f in enumerate(iter_frames(a.data)):
        if i == a.frames:
            break
        t = time.perf_counter()
        fit_albedo_colour(f.image, f.mask, f.light_dirs, f.crosstalk)
        fit_s.append(time.perf_counter() - t)
        t = time.perf_counter()
        n = predict_image(model, f.image, f.mask)
        pred_s.append(time.perf_counter() - t)
        t = time.perf_counter()
        refine_normals(f.image, f.mask, n, f.light_dirs, f.crosstalk)
        ref_s.append(time.perf_counter() - t)
    r = np.array(fit_s) / np.array(pred_s)
    q = np.array(ref_s) / np.array(pred_s)
    print(f"{len(r)} frames: fit median {np.median(fit_s):.4f} s, predict median {np.median(pred_s):.3f} s, "
          f"refine median {np.median(ref_s):.4f} s; fit / predict median {np.median(r):.3f}, "
          f"refine / predict median {np.median(q):.3f}")


if __name__ == "__main__":
    main()
