"""Noise per light against a converged reference, per sampler and spp: the spp for equal noise.

Usage:  PYTHONPATH=. .venv/bin/python benchmarks/bench_sampler.py [--preset paper-train] [--frames 6]
            [--ref-spp 1024] [--threads 1] [--set key=value ...]

Why: the one-pass integrator makes every light's direct term deterministic at each
vertex, so what noise is left comes from where a pixel's samples land (edges,
texture-free shading gradients across the footprint) and from indirect bounces --
both what stratified samplers integrate better than `independent`.  For each
scene of the preset (seed 123) a reference is rendered at `--ref-spp` with the
independent sampler; every configuration renders the scene with two far-apart
seeds; the error of light k is the RMS over the object's pixels of
(image_k - reference_k) summed over colours, relative to the reference's mean,
averaged over lights, seeds and frames (it contains the reference's own noise,
~sqrt(32 / ref_spp) of the 32-spp error, which biases ratios slightly towards 1).
Timing: the render call alone on a loaded scene with its kernels compiled
(median), and the whole `render_frame` of a new frame (median).
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from msps_render.pipeline.config import load_config
from msps_render.render import render_frame
from msps_render.render.emitters import render_emitters_one_pass
from msps_render.render.scene_dict import build_scene_dict, emitter_ids
from msps_render.render.variant import activate
from msps_render.scene.sample import sample_scene

CONFIGS = (("independent", 32), ("independent", 16), ("independent", 8), ("multijitter", 16),
           ("multijitter", 8), ("multijitter", 4), ("stratified", 9), ("ldsampler", 16), ("orthogonal", 9))
SEEDS = (5_000_011, 11_000_027)  # far apart: consecutive seeds share structure in Mitsuba's samplers


def _with(spec, sampler: str, spp: int, seed: int):
    return spec.model_copy(update={"integrator": spec.integrator.model_copy(
        update={"sampler": sampler, "spp": spp, "seed": seed})})


def _render_seconds(mi, spec) -> float:
    import drjit as dr

    scene = mi.load_dict(build_scene_dict(spec, mi))
    ids = emitter_ids(spec)
    for _ in range(2):  # the first compiles
        t0 = time.perf_counter()
        render_emitters_one_pass(mi, scene, ids, spec.integrator.spp, spec.integrator.seed)
        dr.sync_thread()
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="paper-train")
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--set", action="append", default=[], help="config override key=value")
    args = ap.parse_args()
    mi = activate(args.variant, args.threads)
    cfg = load_config(args.preset, args.set)
    rng = np.random.default_rng(123)
    specs = [sample_scene(cfg.scene, rng) for _ in range(args.frames)]
    s0 = specs[0]
    print(f"{args.preset}: {s0.camera.width}x{s0.camera.height}, {s0.integrator.kind} (max_depth "
          f"{s0.integrator.max_depth}), lights {s0.integrator.lights}, env {'on' if s0.environment else 'off'}, "
          f"{args.variant}, {args.threads} threads, {args.frames} frames, reference {args.ref_spp} spp independent")
    err = {c: [] for c in CONFIGS}
    t_render = {c: [] for c in CONFIGS}
    t_frame = {c: [] for c in CONFIGS}
    for i, spec in enumerate(specs):
        ref = render_frame(_with(spec, "independent", args.ref_spp, 777_000_001), variant=args.variant,
                           threads=args.threads, per_light=True)
        m = ref.mask
        for c in CONFIGS:
            e = []
            for sd in SEEDS:
                t0 = time.perf_counter()
                f = render_frame(_with(spec, *c, sd), variant=args.variant, threads=args.threads, per_light=True)
                t_frame[c].append(time.perf_counter() - t0)
                for k in range(len(spec.lights)):
                    d = (f.per_light[k] - ref.per_light[k])[m].sum(-1)
                    e.append(float(np.sqrt((d ** 2).mean()) / ref.per_light[k][m].sum(-1).mean()))
            err[c].append(float(np.mean(e)))
            t_render[c].append(_render_seconds(mi, _with(spec, *c, SEEDS[0])))
        print(f"frame {i}: " + ", ".join(f"{s}{n} {err[(s, n)][-1]:.4f}" for s, n in CONFIGS), flush=True)
    base = c0 = CONFIGS[0]
    base = float(np.mean(err[c0]))
    print(f"\n| sampler | spp | rel. RMS error | noise vs {c0[0]} {c0[1]} | render call s | vs {c0[0]} {c0[1]} "
          f"| render_frame s |")
    print("|---|---|---|---|---|---|---|")
    r0 = statistics.median(t_render[c0])
    for c in CONFIGS:
        e, r = float(np.mean(err[c])), statistics.median(t_render[c])
        print(f"| {c[0]} | {c[1]} | {e:.4f} | {e / base:.2f} | {r:.3f} | {r0 / r:.2f}x faster | "
              f"{statistics.median(t_frame[c]):.3f} |")


if __name__ == "__main__":
    main()
