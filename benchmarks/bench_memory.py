"""Worker memory over many frames (issue 10): does RSS stay flat?

Usage:
  MSPS_THREADS=1 nice -n 10 .venv/bin/python benchmarks/bench_memory.py --frames 2000 --every 100 --warmup 200
  MSPS_THREADS=1 nice -n 10 .venv/bin/python benchmarks/bench_memory.py --frames 1000 --repro --cleanup none

Renders `--frames` tiny frames (32x32, 4 spp, blobby shape, 2-3 materials,
three coloured lights: the default `SceneConfig` at a small size) one after
another in THIS process, exactly like one pipeline worker (`render_frame` +
`patchify`), and prints the resident set size (VmRSS) every `--every` frames,
then a summary: RSS after warm-up (frame `--warmup`), at the end, growth in %
and MiB per 1000 frames (least-squares slope over the post-warm-up samples).

`--cleanup`: what runs after each frame — `none`; `gc` (gc.collect());
`kernel` / `malloc` (only drjit's kernel or malloc cache flush); `flush`
(gc.collect() + drjit kernel and malloc cache flush); `trim` (gc + kernel
flush + glibc malloc_trim(0)); `worker` (default: what pipeline workers do,
`msps_render.render.memory.release_frame_memory(misses_before)`: the kernel cache
is flushed only every `KERNEL_BUDGET` new kernels); `worker-flush` (the same with
the kernel cache flushed after every frame, the behaviour before issue 12).  Results: docs/benchmarks.md.
`--repro`: the same loop with only `mitsuba.load_dict` + `mitsuba.render` of a
fresh in-memory mesh each frame (no msps code, no caches of ours) — the
minimal repro used to tell whether growth is inside Mitsuba/drjit.
"""
from __future__ import annotations

import argparse
import gc
import os
import sys
import time

import numpy as np


def rss_mib() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _repro_frame(mi, dr, rng, variant_jit: bool):
    """A fresh mesh + three lights, loaded and rendered with plain Mitsuba."""
    n = 642
    v = rng.normal(size=(n, 3)).astype(np.float32)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    f = rng.integers(0, n, size=(1280, 3)).astype(np.uint32)
    m = mi.Mesh("m", n, len(f), has_vertex_normals=False)
    p = mi.traverse(m)
    p["vertex_positions"] = dr.ravel(mi.TensorXf(v))
    p["faces"] = dr.ravel(mi.TensorXu(f))
    p.update()
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 3},
        "sensor": {"type": "orthographic", "film": {"type": "hdrfilm", "width": 32, "height": 32},
                   "sampler": {"type": "independent", "sample_count": 4}},
        "shape": m,
        **{f"l{k}": {"type": "directional", "direction": [float(x) for x in rng.normal(size=3)],
                     "irradiance": {"type": "rgb", "value": [1.0, 0.5, 0.2]}} for k in range(3)}})
    img = np.array(mi.render(scene, spp=4, seed=int(rng.integers(1 << 30))))
    del scene, m, p
    return img


def _malloc_trim() -> None:
    import ctypes

    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except OSError:
        pass


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=2000)
    ap.add_argument("--every", type=int, default=100)
    ap.add_argument("--warmup", type=int, default=200)
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--cleanup", default="worker",
                    choices=("none", "gc", "kernel", "malloc", "flush", "worker", "worker-flush", "trim"))
    ap.add_argument("--repro", action="store_true", help="bare Mitsuba loop (no msps code)")
    args = ap.parse_args()

    import drjit as dr

    from msps_render.render.variant import activate, resolve_variant

    variant = resolve_variant("rgb")
    mi = activate(variant, args.threads)
    rng = np.random.default_rng(0)
    if not args.repro:
        from msps_render.patches import patchify
        from msps_render.render import render_frame
        from msps_render.render.memory import kernel_cache_misses, release_frame_memory
        from msps_render.scene.sample import SceneConfig, sample_scene
        from msps_render.scene.spec import CameraSpec, IntegratorSpec

        cfg = SceneConfig(camera=CameraSpec(width=args.size, height=args.size),
                          integrator=IntegratorSpec(spp=args.spp, max_depth=3))
    print(f"variant {variant}, {args.frames} frames of {args.size}x{args.size} at {args.spp} spp, "
          f"cleanup={args.cleanup}, repro={args.repro}, pid {os.getpid()}", flush=True)
    samples: list[tuple[int, float]] = [(0, rss_mib())]
    t0 = time.perf_counter()
    for i in range(1, args.frames + 1):
        misses0 = kernel_cache_misses() if not args.repro else 0
        if args.repro:
            _repro_frame(mi, dr, rng, True)
        else:
            spec = sample_scene(cfg, rng, seed=i)
            frame = render_frame(spec, variant=variant, threads=args.threads)
            patchify(frame, 16, 8, 0.5)
            del frame, spec
        if args.cleanup == "gc":
            gc.collect()
        elif args.cleanup == "kernel":
            dr.flush_kernel_cache()
        elif args.cleanup == "malloc":
            dr.flush_malloc_cache()
        elif args.cleanup == "flush":
            gc.collect()
            dr.flush_kernel_cache()
            dr.flush_malloc_cache()
        elif args.cleanup == "worker" and not args.repro:
            release_frame_memory(misses0)
        elif args.cleanup == "worker-flush" and not args.repro:
            release_frame_memory()
        elif args.cleanup == "trim":
            gc.collect()
            dr.flush_kernel_cache()
            _malloc_trim()
        if i % args.every == 0:
            samples.append((i, rss_mib()))
            print(f"frame {i:6d}  rss {samples[-1][1]:8.1f} MiB  {time.perf_counter() - t0:7.1f} s  "
                  f"python objects {len(gc.get_objects())}", flush=True)
    post = [(f, r) for f, r in samples if f >= args.warmup]
    if len(post) >= 2:
        f, r = np.array(post).T
        slope = np.polyfit(f, r, 1)[0] * 1000
        print(f"summary: rss at frame {int(f[0])} {r[0]:.1f} MiB, at frame {int(f[-1])} {r[-1]:.1f} MiB, "
              f"max {r.max():.1f} MiB, growth after warm-up {100 * (r[-1] - r[0]) / r[0]:+.1f}% "
              f"({slope:+.2f} MiB per 1000 frames), {time.perf_counter() - t0:.0f} s", flush=True)
    sys.exit(0)


if __name__ == "__main__":
    main()
