"""Where a frame's time goes, and how many drjit kernels each frame compiles (issue 12).

Usage:
  MSPS_THREADS=1 .venv/bin/python benchmarks/bench_breakdown.py [--preset paper-train[,train,...]]
      [--frames 32] [--threads 1] [--warmup 8] [--bare-frames 12] [--fresh-disk-cache]

Issue 37: per preset it also times, on frames after the warm-up, Mitsuba's own costs of the same
frames built as fresh scenes -- the bare render kernel (`mi.render` of an already-built scene,
second call) and the bare scene build (`mi.load_dict`, plugins + Embree BVH) -- and prints the
pipeline's median seconds per frame over the bare kernel's on the same frames (kernel compiles
included), all presets in one run and one process.

Renders the first ceil(frames / frames_per_shard) shards of the preset in THIS
process through the pipeline's own `render_shard` (one worker, the variant
resolved as `msps render` resolves it), with a `StageTimer` passed in, and
prints per stage the median and mean seconds per frame and the share of the
total.  Stages: sample (SceneSpec from config + rng), mesh (mesh generation and
Mitsuba mesh buffers), materials (BSDF construction; MERL tables read or baked
on first use), scene dict (the rest of the scene description), scene load
(`mi.load_dict`), kernel compile (codegen + LLVM time of kernels not found in
drjit's in-memory cache, moved out of whichever stage launched them), ground
truth, render, sensor, patchify, release memory, frame record, write (HDF5,
shared evenly over a shard's frames).

Frames in batches (`--set dataset.batch_frames=8`, issue 45): a batch's stage times are shared out
evenly over its frames, and the worker's batch scene is freed before the bare kernel is timed (drjit
compiles every BSDF and shape alive into a kernel, so a live batch scene slowed it by half).

Kernel counts come from drjit's kernel history (`msps_render.render.kernels`):
launches, compiled by LLVM, loaded from the on-disk cache (~/.drjit), and new
kernel hashes, per 100 frames over all frames and after `--warmup` frames.
`--fresh-disk-cache` points drjit's disk cache at an empty temporary HOME (this
script re-executes itself), so every kernel not in memory is really compiled.
"""
from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

STAGES = ("sample", "mesh", "materials", "scene dict", "scene load", "scene update", "kernel compile", "ground truth", "render",
          "sensor", "patchify", "release memory", "frame record", "write")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="paper-train",
                    help="one preset, or several separated by commas (e.g. paper-train,train,train-colour): "
                         "one run, the same process, each with its bare kernel and scene build")
    ap.add_argument("--frames", type=int, default=32)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--warmup", type=int, default=8, help="frames excluded from the 'after warm-up' counts "
                                                          "and from the pipeline / kernel ratio")
    ap.add_argument("--bare-frames", type=int, default=10 ** 6,
                    help="at most this many frames after warm-up are timed again bare, kernel and scene "
                         "build, and the ratio is taken on them (default: all; 0: skip)")
    ap.add_argument("--fresh-disk-cache", action="store_true")
    ap.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                    help="stage times in wall seconds or this process's CPU seconds (robust under load)")
    ap.add_argument("--set", action="append", default=[], help="config override key=value (repeatable)")
    a = ap.parse_args()
    if a.fresh_disk_cache and not os.environ.get("MSPS_BENCH_FRESH_HOME"):
        home = tempfile.mkdtemp(prefix="msps-bench-home-")
        # keep baked MERL/NBRDF tables where they were (they live under ~/.cache unless set)
        cache = os.environ.get("MSPS_CACHE_DIR") or os.path.join(
            os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "msps")
        env = {**os.environ, "HOME": home, "MSPS_BENCH_FRESH_HOME": home, "MSPS_CACHE_DIR": cache}
        os.execve(sys.executable, [sys.executable, *sys.argv], env)
    summary = [run_preset(p.strip(), a) for p in a.preset.split(",") if p.strip()]
    if a.bare_frames > 0:
        print()
        print(f"## Pipeline per frame against the bare kernel (one run, {a.clock} clock; medians over the "
              f"same frames after {a.warmup} warm-up frames of each preset)")
        print()
        print("| preset | frames | pipeline s/frame | bare kernel s | bare scene build s | pipeline / kernel | "
              "build / kernel | pooled frames | batches |")
        print("|---|---|---|---|---|---|---|---|---|")
        for r in summary:
            print(f"| {r['preset']} | {r['n']} | {r['pipeline']:.4f} | {r['kernel']:.4f} | {r['build']:.4f} | "
                  f"**{r['pipeline'] / r['kernel']:.2f}x** | {r['build'] / r['kernel']:.2f}x | {r['pooled']} | "
                  f"{r['batched']} |")


def bare_costs(specs, variant: str, threads: int, clock=time.perf_counter) -> tuple[list[float], list[float]]:
    """Per spec: the bare render kernel (`mi.render` of an already-built fresh scene, 2nd call, synced)
    and the bare scene build (`mi.load_dict` of its description: plugins + Embree BVH), in `clock`
    seconds (the stage timer's: wall, or this process's CPU over all its threads)."""
    import gc

    import drjit as dr

    from msps_render.render.scene_dict import build_scene_dict
    from msps_render.render.variant import activate

    mi = activate(variant, threads)
    kernel, build = [], []
    for spec in specs:
        bands = None
        if spec.mode == "spectral":  # the one-pass spectral scene, as `render.spectral` renders it
            from msps_render.render.spectral import camera_bands, light_responses, one_pass_dict
            from msps_render.spectral.spectra import GRID

            S = camera_bands(spec)[1]
            d, _, bands = one_pass_dict(mi, spec, S, *light_responses(mi, spec, S), None)
        else:
            d = build_scene_dict(spec, mi)
        dr.sync_thread()
        t = clock()
        scene = mi.load_dict(d)
        dr.sync_thread()
        build.append(clock() - t)
        if bands is not None:
            scene.integrator().set_bands(GRID, bands)
        dr.eval(mi.render(scene, spp=spec.integrator.spp, seed=spec.integrator.seed))  # compiles if new
        dr.sync_thread()
        t = clock()
        dr.eval(mi.render(scene, spp=spec.integrator.spp, seed=spec.integrator.seed))
        dr.sync_thread()
        kernel.append(clock() - t)
        del scene, d
        gc.collect()
    return kernel, build


def run_preset(preset: str, a) -> dict:
    """Render the first frames of `preset` through `render_shard` with a StageTimer; print the tables."""
    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.execute import WorkerSettings, render_shard
    from msps_render.pipeline.plan import frame_rngs, frame_seed, plan
    from msps_render.render.kernels import COMPILE_STAGE, KernelLog
    from msps_render.render.variant import activate, resolve_variant
    from msps_render.scene.sample import sample_scene
    from msps_render.timing import StageTimer

    try:  # older trees (before issue 37) have no scene pool: run them as they are, for comparisons
        from msps_render.render.pool import ScenePool
    except ImportError:
        ScenePool = None

    assert COMPILE_STAGE in STAGES
    probe_cfg = load_config(preset, a.set)
    fps = probe_cfg.dataset.frames_per_shard
    n_shards = math.ceil(a.frames / fps)
    cfg = load_config(preset, [*a.set, f"dataset.n_shards={n_shards}"])
    variant = resolve_variant("spectral" if cfg.scene.mode == "spectral" else "rgb")
    activate(variant, a.threads)
    log = KernelLog()
    clock = time.process_time if a.clock == "cpu" else time.perf_counter
    # drjit reports compile times in wall ms: with the CPU clock they stay inside the stage that
    # launched the kernels (compiling is CPU work of this process), only their counts are kept
    timer = StageTimer(probe=log.probe if a.clock == "wall" else None, frame_counts=log.frame_counts, clock=clock)
    walls = []
    scenes = ScenePool() if ScenePool else None  # one worker: its loaded scenes are kept across its shards
    pool_kw = {"scenes": scenes} if scenes is not None else {}
    with tempfile.TemporaryDirectory(prefix="msps-breakdown-") as out:
        (Path(out) / "shards").mkdir()
        ws = WorkerSettings(out_dir=out, variant=variant, threads=a.threads)
        t_all, c_all = time.perf_counter(), time.process_time()
        for task in plan(cfg):
            info = render_shard(task, ws, timer=timer, **pool_kw)
            walls.append(info["wall_seconds"])
        t_all, c_all = time.perf_counter() - t_all, time.process_time() - c_all
    log.close()
    frames = timer.frames
    n = len(frames)
    print()
    print(f"# preset {preset}, {n} frames ({n_shards} shards), variant {variant}, threads {a.threads}, "
          f"disk cache {'fresh' if os.environ.get('MSPS_BENCH_FRESH_HOME') else '~/.drjit'}, clock {a.clock}, "
          f"load average {os.getloadavg()[0]:.1f}; scene pool: "
          f"{f'{scenes.built} built, {scenes.reused} reused' if scenes is not None else 'none (older tree)'}")
    names = [s for s in STAGES if any(s in f for f in frames)] + sorted(
        {k for f in frames for k in f} - set(STAGES))
    per = {s: [f.get(s, 0.0) for f in frames] for s in names}
    total = sum(sum(v) for v in per.values())
    print()
    print("| stage | median s/frame | mean s/frame | share of total |")
    print("|---|---|---|---|")
    for s in names:
        print(f"| {s} | {statistics.median(per[s]):.4f} | {statistics.mean(per[s]):.4f} | "
              f"{100 * sum(per[s]) / total:.1f}% |")
    frame_totals = [sum(f.values()) for f in frames]
    print(f"| **total** | {statistics.median(frame_totals):.4f} | {total / n:.4f} | 100% |")
    setup = [f.get("mesh", 0) + f.get("materials", 0) + f.get("scene dict", 0) + f.get("scene load", 0)
             + f.get(COMPILE_STAGE, 0) for f in frames]
    setup_nc = [f.get("mesh", 0) + f.get("materials", 0) + f.get("scene dict", 0) + f.get("scene load", 0)
                for f in frames]
    print()
    print(f"wall {t_all:.1f} s, CPU {c_all:.1f} s for {n} frames ({t_all / n:.3f} / {c_all / n:.3f} s/frame); "
          f"shards' own wall sum {sum(walls):.1f} s, "
          f"stages account for {total:.1f} s")
    print(f"scene set-up per frame (mesh + materials + scene dict + scene load + kernel compile): median "
          f"{statistics.median(setup):.4f} s, mean {statistics.mean(setup):.4f} s; without compile: median "
          f"{statistics.median(setup_nc):.4f} s")
    w = min(a.warmup, n - 1)
    print()
    print("| kernels | launches | not in memory | compiled (LLVM) | loaded from disk cache | new hashes | "
          "compile s |")
    print("|---|---|---|---|---|---|---|")
    for label, rows in ((f"all {n} frames", timer.counts), (f"after {w} warm-up frames", timer.counts[w:])):
        m = len(rows)
        tot = {k: sum(r.get(k, 0) for r in rows) for k in ("launches", "compiled", "disk_loads", "new_hashes",
                                                           "compile_seconds")}
        k100 = 100.0 / max(m, 1)
        print(f"| {label}, per 100 frames | {tot['launches'] * k100:.0f} | "
              f"{(tot['compiled'] + tot['disk_loads']) * k100:.0f} | {tot['compiled'] * k100:.0f} | "
              f"{tot['disk_loads'] * k100:.0f} | {tot['new_hashes'] * k100:.0f} | "
              f"{tot['compile_seconds'] * k100:.1f} |")
    print()
    print("per frame (compiled / disk / new hashes / launches):",
          " ".join(f"{int(c['compiled'])}/{int(c['disk_loads'])}/{int(c['new_hashes'])}/{int(c['launches'])}"
                   for c in timer.counts))
    batched = getattr(scenes, "batches", None)
    result = {"preset": preset, "n": 0, "pooled": f"{scenes.built + scenes.reused}/{n}" if scenes is not None else "-",
              "batched": f"{batched.built} scene builds" if batched is not None else "-"}
    del batched  # the bare kernel runs alone: drjit compiles every BSDF and shape alive into it
    if scenes is not None:
        scenes.clear()
        import gc

        gc.collect()
    if a.bare_frames > 0:  # the same frames again, each as a fresh scene: Mitsuba's own costs
        specs = [sample_scene(cfg.scene, rng, seed=frame_seed(t, j), frame_index=t.shard_in_condition * fps + j)
                 for t in plan(cfg) for j, rng in enumerate(frame_rngs(t, fps))][w:w + a.bare_frames]
        kernel, build = bare_costs(specs, variant, a.threads, clock)
        same = frame_totals[w:w + len(specs)]  # the pipeline's own times of exactly these frames
        result.update(n=len(specs), pipeline=statistics.median(same), kernel=statistics.median(kernel),
                      build=statistics.median(build))
        print(f"frames {w + 1}..{w + len(specs)}: pipeline per frame median {result['pipeline']:.4f} s, bare kernel "
              f"(mi.render of a built scene) median {result['kernel']:.4f} s, bare scene build (mi.load_dict) "
              f"median {result['build']:.4f} s: pipeline / kernel {result['pipeline'] / result['kernel']:.2f}x")
    return result


if __name__ == "__main__":
    main()
