"""One-pass integrator vs one render per light: time per frame and noise per light at equal spp.

Usage:  PYTHONPATH=. .venv/bin/python benchmarks/bench_onepass.py [--frames 20] [--noise-frames 4]
            [--preset paper-train] [--variant llvm_ad_rgb] [--threads 2] [--set key=value ...]

Scenes are drawn from the preset (paper-train: 128x128, 32 spp `path`, three coloured
directional lights, blobby shapes with 2-3 materials, half of them MERL-plugin).  Both
modes render every scene in the same run, alternating which goes first (the first render
of a scene pays for table and kernel caches); the measured material tables are loaded
before timing.  Reported: median `render_frame` wall time over `--frames` frames after
two warm-up frames, and the median time of the render calls alone (one `mi.render` vs
one per emitter on an already loaded scene).

Noise: per light k and pixel, the variance of one render is estimated from two
independent seeds, var = (a_seed1 - a_seed2)^2 / 2, averaged over the mask; the table
gives sqrt(var one-pass / var per-light) per light (1 = same noise) and the relative
per-pixel noise sqrt(var) / mean of each.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from msps_render.pipeline.config import load_config
from msps_render.render import render_frame
from msps_render.render.emitters import render_emitters_one_pass, render_emitters_separately
from msps_render.render.materials import to_mitsuba
from msps_render.render.scene_dict import build_scene_dict, emitter_ids, with_lights
from msps_render.render.variant import activate
from msps_render.scene.sample import sample_scene

MODES = ("one-pass", "per-light")


def _seed(spec, seed: int):
    return spec.model_copy(update={"integrator": spec.integrator.model_copy(update={"seed": seed})})


def _render_only(mi, spec) -> float:
    """Seconds of the render call(s) alone on a loaded scene (second call: kernels cached)."""
    scene = mi.load_dict(build_scene_dict(spec, mi))
    ids = emitter_ids(spec)

    def run():
        if spec.integrator.lights == "one-pass":
            render_emitters_one_pass(mi, scene, ids, spec.integrator.spp, spec.integrator.seed)
        else:
            render_emitters_separately(mi, scene, spec)

    run()
    t0 = time.perf_counter()
    run()
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="paper-train")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--noise-frames", type=int, default=4)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], help="config override key=value")
    args = ap.parse_args()
    mi = activate(args.variant, args.threads)
    cfg = load_config(args.preset, args.set)
    rng = np.random.default_rng(args.seed)
    specs = [sample_scene(cfg.scene, rng) for _ in range(args.frames + 2)]
    s0 = specs[0]
    print(f"{args.preset}: {s0.camera.width}x{s0.camera.height}, {s0.integrator.spp} spp {s0.integrator.kind} "
          f"(max_depth {s0.integrator.max_depth}), {len(s0.lights)} lights, env "
          f"{'on' if s0.environment else 'off'}, {args.variant}, {args.threads} threads")

    frame_t = {m: [] for m in MODES}
    render_t = {m: [] for m in MODES}
    for i, spec in enumerate(specs):
        for m in spec.materials:  # measured tables: loaded once per process, outside the timing
            to_mitsuba(m)
        order = MODES if i % 2 == 0 else MODES[::-1]
        for mode in order:
            s = with_lights(spec, mode)
            t0 = time.perf_counter()
            render_frame(s, variant=args.variant, threads=args.threads)
            dt = time.perf_counter() - t0
            if i >= 2:  # two warm-up frames (first compilation)
                frame_t[mode].append(dt)
                render_t[mode].append(_render_only(mi, s))
    med = {m: statistics.median(frame_t[m]) for m in MODES}
    med_r = {m: statistics.median(render_t[m]) for m in MODES}
    print(f"\n| mode | median render_frame (s) | median render calls only (s) | frames |")
    print("|---|---|---|---|")
    for m in MODES:
        print(f"| {m} | {med[m]:.3f} | {med_r[m]:.3f} | {len(frame_t[m])} |")
    print(f"speed-up one-pass vs per-light: {med['per-light'] / med['one-pass']:.2f}x per frame, "
          f"{med_r['per-light'] / med_r['one-pass']:.2f}x render calls only")

    print(f"\nnoise at equal spp ({args.noise_frames} frames, two seeds each):")
    print("| frame | light | rel. noise one-pass | rel. noise per-light | noise ratio one-pass/per-light |")
    print("|---|---|---|---|---|")
    ratios = []
    for i, spec in enumerate(specs[2:2 + args.noise_frames]):
        var, mean = {}, {}
        for mode in MODES:
            a, b = (render_frame(_seed(with_lights(spec, mode), sd), variant=args.variant, threads=args.threads,
                                 per_light=True) for sd in (101, 202))
            m = a.mask
            var[mode] = [((a.per_light[k] - b.per_light[k])[m] ** 2 / 2).mean() for k in range(len(spec.lights))]
            mean[mode] = [0.5 * (a.per_light[k] + b.per_light[k])[m].mean() for k in range(len(spec.lights))]
        for k in range(len(spec.lights)):
            r = float(np.sqrt(var["one-pass"][k] / var["per-light"][k]))
            ratios.append(r)
            print(f"| {i} | {k} | {np.sqrt(var['one-pass'][k]) / mean['one-pass'][k]:.4f} | "
                  f"{np.sqrt(var['per-light'][k]) / mean['per-light'][k]:.4f} | {r:.3f} |")
    print(f"median noise ratio one-pass/per-light: {statistics.median(ratios):.3f} "
          f"(range {min(ratios):.3f}-{max(ratios):.3f})")


if __name__ == "__main__":
    main()
