"""Render-stage timing: llvm_ad_rgb vs scalar_rgb, path vs direct, spp 16/64.

Usage:  .venv/bin/python benchmarks/bench_render.py [--repeats 5] [--threads 2]

Renders the demo scene (seed 0 of the default SceneConfig, 128x128, three
coloured lights, two materials) with `render_frame` and reports the median
wall time per configuration and its ratio to llvm_ad_rgb/direct/spp16, all
measured in one run (timings on shared machines are noisy; ratios are not).
The first render of each configuration (JIT compilation) is reported apart.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from msps_render.render import render_frame
from msps_render.scene.sample import SceneConfig, sample_scene
from msps_render.scene.spec import CameraSpec


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--variants", default="llvm_ad_rgb,scalar_rgb")
    args = ap.parse_args()
    base = sample_scene(SceneConfig(camera=CameraSpec(width=128, height=128)), np.random.default_rng(0))
    rows = []
    for variant in args.variants.split(","):
        for kind in ("direct", "path"):
            for spp in (16, 64):
                spec = base.model_copy(update={"integrator": base.integrator.model_copy(
                    update={"kind": kind, "spp": spp})})
                t0 = time.perf_counter()
                render_frame(spec, variant=variant, threads=args.threads)
                first = time.perf_counter() - t0
                times = []
                for _ in range(args.repeats):
                    t0 = time.perf_counter()
                    render_frame(spec, variant=variant, threads=args.threads)
                    times.append(time.perf_counter() - t0)
                rows.append((variant, kind, spp, first, statistics.median(times)))
    ref = rows[0][4]
    print(f"| variant | integrator | spp | first render (s) | median (s) | ratio to {rows[0][0]}/{rows[0][1]}/spp{rows[0][2]} |")
    print("|---|---|---|---|---|---|")
    for v, k, spp, first, med in rows:
        print(f"| {v} | {k} | {spp} | {first:.3f} | {med:.3f} | {med / ref:.2f} |")


if __name__ == "__main__":
    main()
