"""One-pass integrator vs one render per light: time per frame and noise per light at equal spp.

Usage:  PYTHONPATH=. .venv/bin/python benchmarks/bench_onepass.py [--frames 20] [--noise-frames 4]
            [--preset paper-train] [--variant llvm_ad_rgb] [--threads 2] [--set key=value ...]

Scenes are drawn from the preset (paper-train: 128x128, 32 spp `path`, three coloured
directional lights, blobby shapes with 2-3 materials, half of them MERL-plugin).  Both
modes render every scene in the same run, alternating which goes first; the measured
material tables are loaded before timing (a per-process cache either mode would fill).
Reported, as medians over `--frames` frames after two warm-up frames:
- `render_frame`, first render of a new scene: what a dataset frame costs today, including
  the kernel compilation a new scene needs (~0.2-0.3 s in either mode, because per-scene
  literals such as MERL lobe parameters and the directional lights' scene bound change the
  kernel; one-pass kernels do not depend on the scene bound);
- `render_frame` again on the same scene (kernels cached): the per-frame cost once kernels
  are reused across scenes;
- the render calls alone on a loaded scene (one `mi.render` vs one per emitter; RGB only:
  spectral per-light renders load one scene per light, so there the frame rows say it all).
`--seed` defaults to a fresh random seed (printed): drjit also caches kernels on disk, so
re-running with the same scenes would time cached kernels as "first render".

Noise: per light k and pixel (colours summed), the variance of one render is estimated
from two independent, far-apart seeds (other seeds for each mode), var = (a1 - a2)^2 / 2,
averaged over the mask ("pooled"; a single firefly pixel of a spiky measured material can
dominate it), and robustly as the median |a1 - a2| / (0.6745 sqrt 2) over the mask; the
table gives the noise ratio one-pass / per-light per light (1 = same noise) both ways.
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
# far apart (consecutive seeds share structure in Mitsuba's independent sampler) and different per
# mode: with equal seeds an RGB `path` one-pass image equals its per-light render sample by sample
NOISE_SEEDS = {"one-pass": (1_000_003, 7_000_009), "per-light": (3_000_017, 9_000_011)}


def _seed(spec, seed: int):
    return spec.model_copy(update={"integrator": spec.integrator.model_copy(update={"seed": seed})})


def _render_only(mi, spec) -> float:
    """Seconds of the render call(s) alone on a loaded scene (second call: kernels cached)."""
    import drjit as dr

    scene = mi.load_dict(build_scene_dict(spec, mi))
    ids = emitter_ids(spec)

    def run():
        if spec.integrator.lights == "one-pass":
            render_emitters_one_pass(mi, scene, ids, spec.integrator.spp, spec.integrator.seed)
        else:
            render_emitters_separately(mi, scene, spec)
        dr.sync_thread()

    run()
    t0 = time.perf_counter()
    run()
    return time.perf_counter() - t0


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="paper-train")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--noise-frames", type=int, default=4)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=None, help="scene seed (default: random, printed)")
    ap.add_argument("--set", action="append", default=[], help="config override key=value")
    args = ap.parse_args()
    mi = activate(args.variant, args.threads)
    cfg = load_config(args.preset, args.set)
    seed = args.seed if args.seed is not None else int(np.random.SeedSequence().entropy % 2**31)
    rng = np.random.default_rng(seed)
    specs = [sample_scene(cfg.scene, rng) for _ in range(args.frames + 2)]
    s0 = specs[0]
    print(f"{args.preset}: {s0.camera.width}x{s0.camera.height}, {s0.integrator.spp} spp {s0.integrator.kind} "
          f"(max_depth {s0.integrator.max_depth}), {len(s0.lights)} lights, env "
          f"{'on' if s0.environment else 'off'}, {args.variant}, {args.threads} threads, scene seed {seed}")

    first_t = {m: [] for m in MODES}
    cached_t = {m: [] for m in MODES}
    render_t = {m: [] for m in MODES}
    for i, spec in enumerate(specs):
        for m in spec.materials:  # measured tables: loaded once per process, outside the timing
            to_mitsuba(m)
        order = MODES if i % 2 == 0 else MODES[::-1]
        for mode in order:
            s = with_lights(spec, mode)
            run = lambda: render_frame(s, variant=args.variant, threads=args.threads)  # noqa: E731
            first, cached = _timed(run), _timed(run)
            if i >= 2:  # two warm-up frames
                first_t[mode].append(first)
                cached_t[mode].append(cached)
                if spec.mode == "rgb":  # spectral per-light renders build one scene per light
                    render_t[mode].append(_render_only(mi, s))
    rows = (("render_frame, new scene (incl. kernel compile)", first_t),
            ("render_frame, kernels cached", cached_t), ("render calls only", render_t))
    print(f"\n| median over {args.frames} frames (s) | one-pass | per-light | speed-up |")
    print("|---|---|---|---|")
    for name, t in rows:
        if not t["one-pass"]:
            continue
        a, b = statistics.median(t["one-pass"]), statistics.median(t["per-light"])
        print(f"| {name} | {a:.3f} | {b:.3f} | {b / a:.2f}x |")

    print(f"\nnoise at equal spp ({args.noise_frames} frames, two seeds each; relative = noise / mean over the mask):")
    print("| frame | light | rel. noise one-pass | rel. noise per-light | ratio (pooled) | ratio (robust) |")
    print("|---|---|---|---|---|---|")
    pooled, robust = [], []
    for i, spec in enumerate(specs[2:2 + args.noise_frames]):
        var, rob, mean = {}, {}, {}
        for mode in MODES:
            a, b = (render_frame(_seed(with_lights(spec, mode), sd), variant=args.variant, threads=args.threads,
                                 per_light=True) for sd in NOISE_SEEDS[mode])
            m = a.mask
            d = [(a.per_light[k] - b.per_light[k])[m].sum(-1) for k in range(len(spec.lights))]
            var[mode] = [float((x ** 2).mean() / 2) for x in d]
            # median |difference| / (0.6745 sqrt 2): sigma of a Gaussian, insensitive to rare fireflies
            rob[mode] = [float(np.median(np.abs(x)) / (0.6745 * np.sqrt(2))) for x in d]
            mean[mode] = [float(0.5 * (a.per_light[k] + b.per_light[k])[m].sum(-1).mean())
                          for k in range(len(spec.lights))]
        for k in range(len(spec.lights)):
            rp = float(np.sqrt(var["one-pass"][k] / var["per-light"][k]))
            rr = rob["one-pass"][k] / rob["per-light"][k]
            pooled.append(rp)
            robust.append(rr)
            print(f"| {i} | {k} | {np.sqrt(var['one-pass'][k]) / mean['one-pass'][k]:.4f} | "
                  f"{np.sqrt(var['per-light'][k]) / mean['per-light'][k]:.4f} | {rp:.3f} | {rr:.3f} |")
    print(f"median noise ratio one-pass/per-light: pooled {statistics.median(pooled):.3f} "
          f"(range {min(pooled):.3f}-{max(pooled):.3f}), robust {statistics.median(robust):.3f} "
          f"(range {min(robust):.3f}-{max(robust):.3f})")

if __name__ == "__main__":
    main()
