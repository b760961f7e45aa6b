"""Spectral/paper-mode timing (issue 4): one paper-mode render vs the three-render mix,
and spectral vs RGB mode, as ratios of medians measured in one run.

Usage:  .venv/bin/python benchmarks/bench_spectral.py [--repeats 5] [--threads 2]

Scene: seed 0 of the default SceneConfig at 128x128 (blobby shape, 2-3 analytic
materials, three directional lights at slant 30, path tracing, max_depth 6, spp 32).
* paper, one render: `render_frame` of the scene with coloured lights (RGB = irradiance·M[:, k]);
* three-render mix: three `render_frame` calls, one white light each, then
  channel i = Σ_k M[i, k]·channel i of render k (numpy);
* spectral: the same scene sampled with mode="spectral" (LEDs 630/20, 530/30,
  465/20 nm, Nikon 5100), default emission-in-film wavelength sampling, and the
  literal set-up (`emission_in_film=False`) for comparison.
Each configuration is warmed up once (JIT), then timed `--repeats` times.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from msps_render.render import render_frame
from msps_render.scene.sample import SceneConfig, sample_scene
from msps_render.scene.spec import CameraSpec


def timed(fn, repeats):
    fn()  # warm-up (JIT compilation)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--spp", type=int, default=32)
    args = ap.parse_args()
    cam = CameraSpec(width=128, height=128)
    rgb_cfg = SceneConfig(camera=cam)
    spec = sample_scene(rgb_cfg, np.random.default_rng(0))
    spec = spec.model_copy(update={"integrator": spec.integrator.model_copy(update={"spp": args.spp})})
    M = np.asarray(spec.crosstalk)
    irr = rgb_cfg.lights.irradiance
    whites = [spec.model_copy(update={"lights": (l.model_copy(update={"rgb": (irr, irr, irr)}),),
                                      "crosstalk": None}) for l in spec.lights]

    def paper_one():
        return render_frame(spec, variant="llvm_ad_rgb", threads=args.threads).image

    def paper_mix():
        imgs = [render_frame(w, variant="llvm_ad_rgb", threads=args.threads).image for w in whites]
        return sum(M[:, k] * imgs[k] for k in range(len(imgs)))

    sspec = sample_scene(SceneConfig(camera=cam, mode="spectral"), np.random.default_rng(0))
    sspec = sspec.model_copy(update={"integrator": spec.integrator})

    def spectral():
        return render_frame(sspec, variant="llvm_ad_spectral", threads=args.threads).image

    def spectral_literal():
        import mitsuba as mi

        from msps_render.render.variant import activate
        from msps_render.render.spectral import render_spectral_frame

        activate("llvm_ad_spectral", args.threads)
        return render_spectral_frame(sspec, mi, "llvm_ad_spectral", emission_in_film=False).image

    diff = np.abs(paper_one() - paper_mix()).mean() / paper_mix().mean()
    rows = [("paper mode, one render (llvm_ad_rgb)", timed(paper_one, args.repeats)),
            ("three white renders + mix (llvm_ad_rgb)", timed(paper_mix, args.repeats)),
            ("spectral, emission-in-film (llvm_ad_spectral)", timed(spectral, args.repeats)),
            ("spectral, literal lights+camera bands (llvm_ad_spectral)", timed(spectral_literal, args.repeats))]
    base = rows[0][1]
    print(f"scene: seed 0 default SceneConfig, 128x128, {spec.integrator.kind} depth "
          f"{spec.integrator.max_depth}, spp {args.spp}, threads {args.threads}, repeats {args.repeats}")
    print(f"paper one-render vs three-render mix: mean relative difference {diff:.2e}")
    print("| configuration | median (s) | ratio to paper one-render |")
    print("|---|---|---|")
    for name, t in rows:
        print(f"| {name} | {t:.3f} | {t / base:.2f} |")


if __name__ == "__main__":
    main()
