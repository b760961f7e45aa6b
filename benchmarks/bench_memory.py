"""Worker memory over many frames (issue 10): does RSS stay flat?  And with many materials (issue 21)?

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

`--corpus` (issue 21): peak RSS of real `msps render PRESET` runs (child
processes: the render process, or each worker with `--workers 2`) at several
numbers of measured materials (a catalogue of the first k training-side
materials, `scene.materials.catalogue`) and worker counts, and the worker's
RSS each time a shard is finished (the plateau):
  .venv/bin/python benchmarks/bench_memory.py --corpus --materials 1 8 64 --workers 1 2 --shards 4 \
      [--table-cache 8 100000]   # bounded vs (effectively) the old unbounded table cache
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


# --------------------------------------------------------------- corpus mode (issue 21)
def _material_catalogue(k: int, out: "Path") -> list[str]:
    """A catalogue of the first `k` training-side measured materials (built-in fits), written to `out`."""
    from msps_render.brdf.library import held_out, load_catalogue
    from msps_render.scene.materials import measured_pool

    cat = load_catalogue()
    test = held_out()
    names = [e.name for e in cat.by_source("merl")]
    pool = {m.name.split(":", 1)[-1] for m in measured_pool(cat, "nbrdf")}
    chosen = [n for n in names if n in pool and n not in test][:k]
    if len(chosen) < k:
        sys.exit(f"bench_memory: only {len(chosen)} training-side measured materials, asked for {k}")
    out.write_text("version = 1\n" + "".join(
        f'\n[[material]]\nname = "{n}"\nsource = "merl:{n}.binary"\n' for n in chosen))
    return chosen


def _status_kib(pid: int, field: str) -> int:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        pass
    return 0


def _run_corpus(preset: str, k: int, workers: int, shards: int, fps: int, table_cache: str, out_root: "Path",
                cache_dir: str, extra: list[str]) -> dict:
    """One `msps render` in a child process; per-process peak RSS (VmHWM, polled) and the largest
    worker's current RSS each time a shard is finished."""
    import shutil
    import subprocess
    from pathlib import Path

    import psutil

    out = out_root / f"{preset}-m{k}-w{workers}-c{table_cache}"
    shutil.rmtree(out, ignore_errors=True)
    cat = out_root / f"catalogue-{k}.toml"
    _material_catalogue(k, cat)
    env = dict(os.environ, MSPS_CACHE_DIR=cache_dir, MSPS_TABLE_CACHE=table_cache, OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "msps_render.cli", "render", preset, "--out", str(out), "--workers", str(workers),
           "--set", f"dataset.n_shards={shards}", "--set", f"dataset.frames_per_shard={fps}",
           "--set", f"scene.materials.catalogue={cat}", *extra]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    root = psutil.Process(proc.pid)
    peak: dict[int, int] = {}  # pid -> VmHWM KiB
    trace: list[tuple[int, float]] = []  # (shards done, largest render process' VmRSS MiB)
    done = 0
    while proc.poll() is None:
        try:
            pids = [proc.pid] + [c.pid for c in root.children(recursive=True)]
        except psutil.NoSuchProcess:
            pids = [proc.pid]
        for pid in pids:
            peak[pid] = max(peak.get(pid, 0), _status_kib(pid, "VmHWM"))
        n = len(list((out / "shards").glob("*.h5"))) if (out / "shards").is_dir() else 0
        if n > done:
            done = n
            render = [p for p in pids if workers <= 1 or p != proc.pid]
            trace.append((n, max((_status_kib(p, "VmRSS") for p in render), default=0) / 1024))
        time.sleep(0.2)
    err = proc.stderr.read()
    if proc.returncode != 0:
        sys.exit(f"bench_memory: {' '.join(cmd)} failed ({proc.returncode}): {err.strip().splitlines()[-1:]}")
    workers_peak = [v for p, v in peak.items() if workers <= 1 or p != proc.pid]
    return {"materials": k, "workers": workers, "table_cache": table_cache, "shards": shards,
            "driver_peak_mib": peak.get(proc.pid, 0) / 1024, "worker_peak_mib": max(workers_peak) / 1024,
            "trace": trace, "seconds": time.perf_counter() - t0}


def corpus_main(argv: list[str]) -> None:
    """Peak RSS of `msps render` workers at several measured-material counts and worker counts."""
    import json
    import tempfile
    from pathlib import Path

    ap = argparse.ArgumentParser(prog="bench_memory.py --corpus")
    ap.add_argument("--corpus", action="store_true")
    ap.add_argument("--preset", default="train")
    ap.add_argument("--materials", type=int, nargs="+", default=[1, 8, 64])
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--shards", type=int, default=4)
    ap.add_argument("--frames-per-shard", type=int, default=8)
    ap.add_argument("--table-cache", nargs="+", default=["8"],
                    help="MSPS_TABLE_CACHE values to compare (e.g. 8 100000: bounded vs the old unbounded cache)")
    ap.add_argument("--cache-dir", default=os.environ.get("MSPS_CACHE_DIR", ""),
                    help="MSPS_CACHE_DIR of the runs (baked tables are made there first, not measured)")
    ap.add_argument("--out", default=None, help="scratch folder (default: a temporary one)")
    ap.add_argument("--set", action="append", default=[], help="extra `msps render --set k=v`")
    ap.add_argument("--json", default=None, help="also write the results here")
    a = ap.parse_args(argv)
    out_root = Path(a.out or tempfile.mkdtemp(prefix="bench-memory-"))
    out_root.mkdir(parents=True, exist_ok=True)
    cache_dir = a.cache_dir or str(out_root / "cache")
    os.environ["MSPS_CACHE_DIR"] = cache_dir
    from msps_render.brdf import nbrdf

    for name in _material_catalogue(max(a.materials), out_root / "all.toml"):  # bake first, outside the runs
        nbrdf.baked_table(nbrdf.weights_path(name))
    extra = [x for s in a.set for x in ("--set", s)]
    rows = []
    for cache in a.table_cache:
        for k in a.materials:
            for w in a.workers:
                r = _run_corpus(a.preset, k, w, a.shards, a.frames_per_shard, cache, out_root, cache_dir, extra)
                rows.append(r)
                tr = ", ".join(f"{n}: {m:.0f}" for n, m in r["trace"])
                print(f"materials {k:3d}  workers {w}  MSPS_TABLE_CACHE={cache:>6}  worker peak "
                      f"{r['worker_peak_mib']:7.1f} MiB  driver peak {r['driver_peak_mib']:6.1f} MiB  "
                      f"{r['seconds']:5.0f} s  RSS after shard n (MiB): {tr}", flush=True)
    print("| measured materials | workers | MSPS_TABLE_CACHE | shards x frames | peak RSS per worker (MiB) | "
          "driver peak (MiB) | worker RSS after each shard (MiB) |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['materials']} | {r['workers']} | {r['table_cache']} | {r['shards']} x {a.frames_per_shard} | "
              f"{r['worker_peak_mib']:.0f} | {r['driver_peak_mib']:.0f} | "
              f"{' → '.join(f'{m:.0f}' for _, m in r['trace'])} |")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    corpus_main(sys.argv[1:]) if "--corpus" in sys.argv[1:] else main()
