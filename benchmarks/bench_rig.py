"""Any rig: one pass for N lights -- time per frame and per light image against N, the 96-light
one-pass frame against 32 three-light passes of the same scene, and a render worker's peak memory.

Usage:  PYTHONPATH=. .venv/bin/python benchmarks/bench_rig.py [--n-lights 1 3 8 32 96] [--scenes 5]
            [--split-scenes 3] [--memory-lights 3 96] [--memory-runs 2] [--memory-frames 4] [--no-cold]
            [--parts 1,2,3] [--quick] [--threads 2] [--variant llvm_ad_rgb] [--seed 0] [--set key=value ...]

Takes ~3 minutes on the 2-core development machine (`--quick`: ~1 minute).

Scenes: `--preset` (classic-train: 128x128, procedural "mixed" shapes -- `scene.shape.source =
procedural` is set here, the preset sweeps blobby/procedural --, 1-2 measured materials
(merl_fraction 1.0), `path` max_depth 4, 8 spp multijitter, white directional hemisphere lights
drawn anew per frame, sequential capture), with `scene.rig.n_lights = N`.  Scene i is drawn from
the same seed for every N, so shape, rotation, materials and split are the same; only the lights
differ.  The reference "three-light rig" is today's default path: no [scene.rig], `SceneConfig()`
defaults (three coloured lights, one multiplexed RGB shot) with the preset's shape, materials,
camera and integrator (the same seeds give the same object).

1. Time per frame (`render_frame`, wall clock) against N, median over `--scenes` scenes, and per
   light image (frame / N).  Warm kernels: every (scene, configuration) is rendered once before the
   timed round (drjit compiles one kernel per N and per number of materials; the measured tables are
   loaded then too), and the kernels compiled during the timed frames are counted (expected 0).  The
   per-process cache of canonical meshes is cleared before every timed frame, so each frame pays
   its shape's generation as a corpus worker does for a new scene.  Configurations are interleaved
   (scene i renders them in an order rotated by i) so machine load hits them alike.  The "render"
   column is the `render` stage alone (`mi.render` + reading the film's AOVs).
2. The issue's target: the N=96 sequential rig's 96 images from ONE pass against the same 96 images
   as 32 three-light passes of the same SceneSpec (lights 3k..3k+2, a RigSpec of those 3 lights and
   3 sequential shots), each pass a full `render_frame` (scene build + render; the canonical mesh
   cache is cleared before the first pass of each mode, so both pay the shape's generation once).
   The 96 images of both must agree: with the same seed every light's image sees the same random
   numbers in either pass (max |difference| reported).  Median over `--split-scenes` scenes.
3. Peak RSS of a render worker: `msps render PRESET --out TMP --set scene.rig.n_lights=N --set
   dataset.n_shards=2 --set dataset.frames_per_shard=4 --workers 1` (`--memory-frames`) in a child (with
   --workers 1 the render runs in that process), peak from the kernel (wait4 ru_maxrss), each N in
   `--memory-lights` run `--memory-runs` times (the first run may compile kernels the drjit disk
   cache ~/.drjit lacks), and the largest N once more with an empty drjit disk cache (HOME in a
   temporary folder, the baked tables where they are: every kernel compiled by LLVM in the worker;
   `--no-cold` skips it).  Then the same render once more in a child that wraps `render_shard`
   with a stage hook reading VmRSS/VmHWM (the peak counter reset at every phase): where the memory
   goes, phase by phase, for the smallest and the largest N.
Results: docs/benchmarks.md, "Any rig: one pass for N lights".
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

PRESET_SETS = ["scene.shape.source=procedural"]
TARGET_SPLIT_RATIO = 0.7
TARGET_WORKER_MIB = 600.0


# --------------------------------------------------------------------------- scenes
def rig_config(preset: str, n: int, extra: list[str]):
    from msps_render.pipeline.config import load_config

    return load_config(preset, [*PRESET_SETS, f"scene.rig.n_lights={n}", *extra]).scene


def three_light_config(scene_cfg):
    """Today's default path: no [scene.rig], SceneConfig() defaults with the same shape, materials,
    camera and integrator."""
    from msps_render.scene.sample import SceneConfig

    return SceneConfig(shape=scene_cfg.shape, materials=scene_cfg.materials, camera=scene_cfg.camera,
                       integrator=scene_cfg.integrator)


def draw(scene_cfg, seed: int, i: int):
    from msps_render.scene.sample import sample_scene

    return sample_scene(scene_cfg, np.random.default_rng([seed, i]))


def split_into_passes(spec, per_pass: int = 3) -> list:
    """The same SceneSpec as N/per_pass specs of `per_pass` lights each, sequential shots: what a
    renderer without the one-pass N-light integrator renders (validated, not copied blindly)."""
    from msps_render.rig import RigSpec
    from msps_render.scene.spec import SceneSpec

    r = spec.rig
    n = len(spec.lights)
    if r is None or n % per_pass or tuple(r.shots) != tuple((k,) for k in range(n)):
        raise SystemExit(f"bench_rig: split needs a sequential rig of a multiple of {per_pass} lights")
    out = []
    for k in range(0, n, per_pass):
        sl = slice(k, k + per_pass)
        rig = RigSpec.model_validate({**r.model_dump(), "shots": [[j] for j in range(per_pass)],
                                      "nominal_dirs": r.nominal_dirs[sl], "nominal_rgb": r.nominal_rgb[sl],
                                      "anisotropy": r.anisotropy[sl] if r.anisotropy else (),
                                      "axes": r.axes[sl] if r.axes else ()})
        d = spec.model_dump()
        d["lights"] = d["lights"][sl]
        d["rig"] = rig.model_dump()
        out.append(SceneSpec.model_validate(d))
    return out


def clear_mesh_cache() -> None:
    from msps_render.scene import shapes

    shapes._CANONICAL.clear()


def load_tables(specs) -> None:
    from msps_render.render.materials import to_mitsuba

    for s in specs:
        for m in s.materials:  # measured tables: loaded once per process, outside the timing
            to_mitsuba(m)


class Timed:
    """One `render_frame` timed: wall and CPU seconds, its stages, kernels compiled during it."""

    def __init__(self, log):
        from msps_render.timing import StageTimer

        self.log = log
        self.timer = StageTimer()

    def __call__(self, spec, variant: str, threads: int):
        from msps_render.render import render_frame

        self.log.frame_counts()
        c0, t0 = time.process_time(), time.perf_counter()
        frame = render_frame(spec, variant=variant, threads=threads, timer=self.timer)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        stages = self.timer.end_frame()
        counts = self.log.frame_counts()
        return frame, {"wall": wall, "cpu": cpu, "render": stages.get("render", 0.0),
                       "compiled": counts["compiled"] + counts["disk_loads"], "llvm": counts["compiled"],
                       "disk": counts["disk_loads"], "compile_s": counts["compile_seconds"]}


# --------------------------------------------------------------------------- 1. time against N
def time_against_n(a, log) -> list[dict]:
    configs = [("3-light rig (no [scene.rig])", 3, three_light_config(rig_config(a.preset, 3, a.set)))]
    configs += [(f"N = {n}", n, rig_config(a.preset, n, a.set)) for n in a.n_lights]
    specs = {name: [draw(c, a.seed, i) for i in range(a.scenes)] for name, _, c in configs}
    for name, _, _ in configs:  # same object for every configuration
        assert [s.shape for s in specs[name]] == [s.shape for s in specs[configs[0][0]]], name
        load_tables(specs[name])
    timed = Timed(log)
    t0 = time.perf_counter()
    warm = {name: [] for name, _, _ in configs}
    for i in range(a.scenes):  # warm-up round: every kernel (per N, per material count) compiled or loaded
        for name, _, _ in configs:
            warm[name].append(timed(specs[name][i], a.variant, a.threads)[1])
    print(f"warm-up round: {time.perf_counter() - t0:.0f} s", flush=True)
    res = {name: [] for name, _, _ in configs}
    for i in range(a.scenes):
        order = configs[i % len(configs):] + configs[:i % len(configs)]
        for name, _, _ in order:
            clear_mesh_cache()
            _, r = timed(specs[name][i], a.variant, a.threads)
            res[name].append(r)
    rows = []
    for name, n, _ in configs:
        rs = res[name]
        rows.append({"config": name, "n": n, "images": len(specs[name][0].rig.shots) if specs[name][0].rig else 1,
                     "wall": statistics.median(r["wall"] for r in rs), "cpu": statistics.median(r["cpu"] for r in rs),
                     "render": statistics.median(r["render"] for r in rs),
                     "compiled": sum(r["compiled"] for r in rs),
                     "warm_llvm": sum(r["llvm"] for r in warm[name]), "warm_disk": sum(r["disk"] for r in warm[name]),
                     "warm_compile_s": sum(r["compile_s"] for r in warm[name]),
                     "per_scene": [round(r["wall"], 3) for r in rs]})
    return rows


def print_against_n(rows: list[dict], a) -> bool:
    base = next((r for r in rows if r["config"] == "N = 1"), None)
    print(f"\n### 1. Time per frame against N (median over {a.scenes} scenes, warm kernels, wall clock)\n")
    print("| configuration | images | frame s | render stage s | frame CPU s | s per light image | "
          "per image vs N = 1 | kernels compiled/loaded in timed frames | warm-up: kernels LLVM-compiled / "
          "from disk (codegen + compile s) | per scene (wall s) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        per = r["wall"] / r["n"]
        rel = f"{per / base['wall']:.3f}" if base else "-"
        print(f"| {r['config']} | {r['images']} | {r['wall']:.3f} | {r['render']:.3f} | {r['cpu']:.3f} | "
              f"{per:.4f} | {rel} | {r['compiled']} | "
              f"{r['warm_llvm']} / {r['warm_disk']} ({r['warm_compile_s']:.2f}) | "
              f"{', '.join(map(str, r['per_scene']))} |")
    rig = [r for r in rows if r["config"].startswith("N =")]
    per = [r["wall"] / r["n"] for r in rig]
    falls = all(b < x for x, b in zip(per, per[1:]))
    print(f"\ntime per light image falls as N grows: {'yes' if falls else 'NO'} "
          f"({' > '.join(f'{p:.4f}' for p in per)} s)")
    return falls


# --------------------------------------------------------------------------- 2. one pass vs 32 passes
def one_vs_split(a, log) -> list[dict]:
    n = max(a.n_lights)
    cfg = rig_config(a.preset, n, a.set)
    specs = [draw(cfg, a.seed, i) for i in range(a.split_scenes)]
    splits = [split_into_passes(s) for s in specs]
    load_tables(specs)
    timed = Timed(log)
    for s, parts in zip(specs, splits):  # warm-up: the N-light kernel and the 3-light one
        timed(s, a.variant, a.threads)
        timed(parts[0], a.variant, a.threads)
    rows = []
    for i, (spec, parts) in enumerate(zip(specs, splits)):
        out = {}
        for mode in (("one", "split") if i % 2 == 0 else ("split", "one")):
            clear_mesh_cache()
            if mode == "one":
                frame, r = timed(spec, a.variant, a.threads)
                out["one"], out["one_shots"], out["one_render"], out["one_compiled"] = (
                    r["wall"], frame.shots, r["render"], r["compiled"])
            else:
                wall = render = 0.0
                shots, compiled = [], 0
                for p in parts:
                    frame, r = timed(p, a.variant, a.threads)
                    wall, render, compiled = wall + r["wall"], render + r["render"], compiled + r["compiled"]
                    shots.append(frame.shots)
                out["split"], out["split_shots"], out["split_render"], out["split_compiled"] = (
                    wall, np.concatenate(shots), render, compiled)
        d = np.abs(out["one_shots"] - out["split_shots"])
        rows.append({"scene": i, "object": spec.shape.name, "materials": len(spec.materials), "passes": len(parts),
                     "one": out["one"], "split": out["split"], "ratio": out["one"] / out["split"],
                     "one_render": out["one_render"], "split_render": out["split_render"],
                     "compiled": out["one_compiled"] + out["split_compiled"],
                     "max_diff": float(d.max()),
                     "rel_diff": float(d.mean() / max(np.abs(out["one_shots"]).mean(), 1e-30))})
    return rows


def print_split(rows: list[dict], n: int) -> bool:
    print(f"\n### 2. {n} sequential images: one pass vs {rows[0]['passes']} three-light passes of the same scene\n")
    print("| scene | object, materials | one pass s | passes s (sum) | one / passes | render stage: one / passes s | "
          "kernels compiled in timed frames | max abs diff of the images (mean rel.) |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['scene']} | {r['object']}, {r['materials']} | {r['one']:.3f} | {r['split']:.3f} | "
              f"{r['ratio']:.3f} | {r['one_render']:.3f} / {r['split_render']:.3f} | {r['compiled']} | "
              f"{r['max_diff']:.2e} ({r['rel_diff']:.1e}) |")
    med = statistics.median(r["ratio"] for r in rows)
    ok = med <= TARGET_SPLIT_RATIO
    print(f"\nmedian one / passes: {med:.3f} (target <= {TARGET_SPLIT_RATIO}: {'met' if ok else 'NOT met'}); "
          f"ratio of the medians "
          f"{statistics.median(r['one'] for r in rows) / statistics.median(r['split'] for r in rows):.3f}")
    return ok


# --------------------------------------------------------------------------- 3. worker memory
def render_cmd(a, n: int, out: Path) -> list[str]:
    return [sys.executable, "-m", "msps_render.cli", "render", a.preset, "--out", str(out), "--force",
            "--set", f"scene.rig.n_lights={n}", "--set", "dataset.n_shards=2",
            "--set", f"dataset.frames_per_shard={a.memory_frames}", "--workers", "1",
            *[x for s in a.set for x in ("--set", s)]]


# Linux counts the RSS peak of the address space a process had before `exec` in its maxrss, and
# subprocess forks (vfork) from this process, whose RSS after parts 1-2 is itself ~600 MiB: so the
# command runs under a small Python that forks it and reports the command's own wait4 maxrss.
_WAIT4 = ("import os, sys, subprocess\n"
          "p = subprocess.Popen(sys.argv[2:])\n"
          "_, st, ru = os.wait4(p.pid, 0)\n"
          "open(sys.argv[1], 'w').write(str(ru.ru_maxrss))\n"
          "sys.exit(os.waitstatus_to_exitcode(st))\n")


def run_peak(cmd: list[str], env: dict) -> tuple[float, float, str]:
    """(peak RSS MiB of the command from wait4, wall s, stdout) -- the exact peak, no polling."""
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        peak_file = os.path.join(tmp, "maxrss")
        proc = subprocess.run([sys.executable, "-c", _WAIT4, peak_file, *cmd], env=env, capture_output=True,
                              text=True)
        if proc.returncode != 0:
            raise SystemExit(f"bench_rig: {' '.join(cmd)} failed ({proc.returncode}): {proc.stderr.strip()[-2000:]}")
        peak = int(Path(peak_file).read_text()) / 1024.0
    return peak, time.perf_counter() - t0, proc.stdout


def worker_memory(a) -> dict:
    import shutil

    root = Path(tempfile.mkdtemp(prefix="bench-rig-mem-"))
    try:
        return _worker_memory(a, root)
    finally:
        shutil.rmtree(root, ignore_errors=True)  # the rendered datasets (~100 MB)


def _worker_memory(a, root: Path) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1", MSPS_THREADS=str(a.threads))
    peaks = {}
    for run in range(a.memory_runs):
        for n in a.memory_lights:
            cmd = render_cmd(a, n, root / f"n{n}")
            peak, wall, _ = run_peak(cmd, env)
            peaks.setdefault(n, []).append((peak, wall))
            print(f"memory: N = {n}, run {run + 1}: worker peak {peak:.0f} MiB, {wall:.0f} s", flush=True)
    cold = None
    if a.cold:  # drjit's disk cache (~/.drjit) empty: every kernel of the run compiled by LLVM in the worker
        home = root / "home"
        home.mkdir()
        cache = os.environ.get("MSPS_CACHE_DIR") or os.path.join(
            os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "msps")  # baked tables stay
        n = max(a.memory_lights)
        peak, wall, _ = run_peak(render_cmd(a, n, root / f"cold{n}"), dict(env, HOME=str(home), MSPS_CACHE_DIR=cache))
        cold = (n, peak, wall)
        print(f"memory: N = {n}, empty drjit disk cache: worker peak {peak:.0f} MiB, {wall:.0f} s", flush=True)
    phases = {}
    for n in sorted({min(a.memory_lights), max(a.memory_lights)}):
        js = root / f"phases-{n}.json"
        cmd = [sys.executable, os.path.abspath(__file__), "--_phases", str(js), "--preset", a.preset,
               "--threads", str(a.threads), *[x for s in a.set for x in ("--set", s)],
               "--memory-lights", str(n), "--memory-frames", str(a.memory_frames), "--_out", str(root / f"p{n}")]
        run_peak(cmd, env)  # its wait4 peak is not the peak: resetting VmHWM resets the kernel's maxrss too
        phases[n] = json.loads(js.read_text())
    return {"peaks": peaks, "cold": cold, "phases": phases}


def print_memory(mem: dict, a) -> bool:
    print(f"\n### 3. Render worker peak RSS (`msps render {a.preset} --set scene.rig.n_lights=N "
          f"--set dataset.n_shards=2 --set dataset.frames_per_shard={a.memory_frames} --workers 1`)\n")
    print("| N | peak RSS per run (MiB) | wall per run (s) | target <= 600 MiB |")
    print("|---|---|---|---|")
    ok = True
    for n, runs in mem["peaks"].items():
        met = max(p for p, _ in runs) <= TARGET_WORKER_MIB
        ok &= met if n == max(mem["peaks"]) else True
        print(f"| {n} | {' / '.join(f'{p:.0f}' for p, _ in runs)} | {' / '.join(f'{w:.0f}' for _, w in runs)} | "
              f"{'met' if met else 'NOT met'} |")
    if mem["cold"]:
        n, p, w = mem["cold"]
        ok &= p <= TARGET_WORKER_MIB
        print(f"| {n}, empty drjit disk cache (every kernel compiled by LLVM in the worker) | {p:.0f} | {w:.0f} | "
              f"{'met' if p <= TARGET_WORKER_MIB else 'NOT met'} |")
    ns = sorted(mem["phases"])
    print("\nWhere it goes: the same render once more per N in a child whose `render_shard` stages are hooked "
          "(MiB; VmHWM read and reset at every phase boundary, so 'peak' is the highest RSS inside the phase; "
          "'rise' = peak - RSS at the phase's start; the largest over the run's frames; 'after <stage>' is the "
          "code between two stages, e.g. `render_frame` composing the shots after its `render` stage).\n")
    print("| phase | " + " | ".join(f"N = {n}: peak | rise | count" for n in ns) + " |")
    print("|---|" + "---|---|---|" * len(ns))
    names = []
    for n in ns:
        for k in mem["phases"][n]["phases"]:
            if k not in names:
                names.append(k)
    for k in names:
        cells = []
        for n in ns:
            p = mem["phases"][n]["phases"].get(k)
            cells.append("- | - | -" if p is None else f"{p['peak']:.0f} | {p['rise']:+.0f} | {p['count']}")
        print(f"| {k} | " + " | ".join(cells) + " |")
    for n in ns:
        ph = mem["phases"][n]
        print(f"\nN = {n}: highest phase peak {ph['top'][1]:.0f} MiB in '{ph['top'][0]}' (shard {ph['top'][2]}, "
              f"frame {ph['top'][3]}); RSS after imports {ph['after_import']:.0f}, after Mitsuba's variant "
              f"{ph['after_activate']:.0f}, after validation and planning (first shard's start) "
              f"{ph['first_shard']:.0f}")
        print("RSS at each frame's start (anon + file-backed): " + ", ".join(
            f"s{s}f{f} {r:.0f} ({an:.0f} + {fi:.0f})" for s, f, r, an, fi in ph["frame_starts"]))
        print(f"at the highest render-stage end ({ph['smaps']['rss']:.0f} MiB): " + ", ".join(
            f"{k} {v:.0f}" for k, v in ph["smaps"]["groups"]))
        print(f"one shard's patches: {ph['patches']} patches x {ph['images']} images x 32x32x3 float32 = "
              f"{ph['patch_mib']:.1f} MiB (held as {ph['storage']} from the frame that cut them until the shard "
              f"is written, block by block); film: {ph['film_channels']} channels x 128x128 float32 = "
              f"{ph['film_mib']:.1f} MiB; one frame of this N on a fresh scene: {ph['render_detail']}")
    return ok


# ---- the child of `--_phases`: one `msps render` in this process, every stage hooked
def _status() -> dict[str, float]:
    out = {}
    with open("/proc/self/status") as f:
        for line in f:
            k, _, v = line.partition(":")
            if k in ("VmRSS", "VmHWM", "RssAnon", "RssFile", "RssShmem"):
                out[k] = int(v.split()[0]) / 1024.0
    return out


def _kib(field: str) -> float:
    return _status()[field]


def _reset_peak() -> None:
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")  # resets VmHWM to the current RSS


def _smaps_groups() -> dict:
    """Resident MiB of this process by kind of mapping (/proc/self/smaps)."""
    groups: dict[str, float] = {}
    name = ""
    with open("/proc/self/smaps") as f:
        for line in f:
            head = line.split()
            if head and "-" in head[0] and len(head) >= 5 and not head[0].endswith(":"):
                path = head[5] if len(head) > 5 else ""
                if "/brdf/" in path or path.endswith(".npy"):
                    name = "measured tables (mapped .npy)"
                elif ".so" in path:
                    name = "shared libraries (.so)"
                elif path == "[heap]":
                    name = "[heap] (glibc main arena)"
                elif path.startswith("["):
                    name = "other " + path
                elif path:
                    name = "other files"
                else:
                    name = "anonymous mappings (drjit/LLVM/numpy/thread arenas)"
            elif line.startswith("Rss:"):
                groups[name] = groups.get(name, 0.0) + int(line.split()[1]) / 1024.0
    return {"rss": sum(groups.values()), "groups": sorted(groups.items(), key=lambda kv: -kv[1])}


class MemoryHook:
    """Duck-typed `StageTimer` for `render_shard`: VmHWM read and reset at every phase boundary (the
    peak of nested phases folds into their parent); the code between two stages is its own phase
    'after <stage>', the shard's concat + HDF5 write (after the last frame) is one too."""

    clock = staticmethod(time.perf_counter)

    def __init__(self):
        self.frames: list[dict] = []
        self.phases: dict[str, dict] = {}
        self.top = ("", 0.0, 0, 0)
        self.frame_starts: list = []
        self.smaps = {"rss": 0.0, "groups": []}
        self.shard, self.frame = -1, 0
        self._stack: list[list] = []
        self._gap = None
        self._new_frame = True

    def _record(self, name: str, start: float, peak: float) -> None:
        p = self.phases.setdefault(name, {"peak": 0.0, "rise": 0.0, "count": 0})
        p["peak"], p["rise"], p["count"] = max(p["peak"], peak), max(p["rise"], peak - start), p["count"] + 1
        if peak > self.top[1]:
            self.top = (name, peak, self.shard, self.frame)

    def _close_gap(self, next_gap=None) -> float:
        s = _status()
        if self._gap is not None:
            self._record(self._gap[0], self._gap[1], s["VmHWM"])
        self._gap = next_gap if next_gap is None else (next_gap, s["VmRSS"])
        return s["VmHWM"]

    @contextmanager
    def stage(self, name: str):
        if self._new_frame:
            self._new_frame = False
            s = _status()
            self.frame_starts.append((self.shard, self.frame, s["VmRSS"], s["RssAnon"], s["RssFile"]))
        hwm = self._close_gap() if not self._stack else _kib("VmHWM")
        if self._stack:
            self._stack[-1][2] = max(self._stack[-1][2], hwm)
        _reset_peak()
        start = _kib("VmRSS")
        self._stack.append([name, start, start])
        try:
            yield
        finally:
            name, start, peak = self._stack.pop()
            peak = max(peak, _kib("VmHWM"))
            end = _kib("VmRSS")
            if name == "render" and end > self.smaps["rss"]:
                self.smaps = _smaps_groups()
            self._record(name, start, peak)
            if self._stack:
                self._stack[-1][2] = max(self._stack[-1][2], peak)
            else:
                self._gap = (f"after {name}", end)
            _reset_peak()

    def end_frame(self, extra=None) -> dict:
        self._close_gap("shard write (after its last frame)")
        _reset_peak()
        self.frames.append({})
        self.frame += 1
        self._new_frame = True
        return {}

    def start_shard(self) -> None:
        self._close_gap()
        self.shard, self.frame = self.shard + 1, 0
        _reset_peak()

    def end_shard(self) -> None:
        self._close_gap()
        _reset_peak()


def phases_child(a) -> None:
    after_import = _kib("VmRSS")
    import msps_render.pipeline.execute as ex
    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.run import render_dataset
    from msps_render.render.variant import activate

    activate(a.variant, a.threads)
    after_activate = _kib("VmRSS")
    n = a.memory_lights[0]
    cfg = load_config(a.preset, [f"scene.rig.n_lights={n}", "dataset.n_shards=2",
                                 f"dataset.frames_per_shard={a.memory_frames}", *a.set])
    hook = MemoryHook()
    first = []
    original = ex.render_shard

    def hooked(task, ws, timer=None, scenes=None):
        first.append(_kib("VmRSS"))
        hook.start_shard()
        info = original(task, ws, timer=hook, scenes=scenes)
        hook.end_shard()
        return info

    ex.render_shard = hooked
    render_dataset(cfg, a._out, workers=1, force=True, progress=False)
    ex.render_shard = original
    detail, channels = _render_detail(cfg, a)  # the film's size and the render stage's own steps
    import h5py

    counts = []
    for p in sorted(Path(a._out, "shards").glob("*.h5")):
        with h5py.File(p, "r") as f:
            counts.append(len(f["patches/yx"]))
    images = len(cfg.scene.rig.shot_list(cfg.scene.rig.count())) if cfg.scene.rig else 1
    m = max(counts) if counts else 0
    st = cfg.dataset.storage
    Path(a._phases).write_text(json.dumps({
        "phases": hook.phases, "top": hook.top, "frame_starts": hook.frame_starts, "smaps": hook.smaps,
        "after_import": after_import, "after_activate": after_activate, "first_shard": first[0] if first else 0,
        "patches": m, "images": images, "patch_mib": m * images * cfg.dataset.patches.size ** 2 * 3 * 4 / 2**20,
        "storage": f"{st.image_dtype} {st.compression}", "film_channels": channels,
        "film_mib": 128 * 128 * channels * 4 / 2**20, "render_detail": detail}))


def _render_detail(cfg, a) -> tuple[str, int]:
    """RSS steps of one render of this N on a fresh scene: `mi.render` (film + kernel launch + the
    developed film it returns), the per-light images read from it."""
    import drjit as dr

    from msps_render.render.multilight import read_emitter_images
    from msps_render.render.scene_dict import build_scene_dict, emitter_ids
    from msps_render.render.variant import activate

    mi = activate(a.variant, a.threads)
    spec = draw(cfg.scene, 12345, 0)
    scene = mi.load_dict(build_scene_dict(spec, mi))
    sensor = scene.sensors()[0]
    out, channels = [], 0
    for rep in range(2):
        _reset_peak()
        r0 = _kib("VmRSS")
        image = mi.render(scene, sensor=sensor, spp=spec.integrator.spp, seed=rep)
        dr.sync_thread()
        r1, h1 = _kib("VmRSS"), _kib("VmHWM")
        _reset_peak()
        imgs = read_emitter_images(image, scene.integrator().aov_names(), emitter_ids(spec))
        r2, h2 = _kib("VmRSS"), _kib("VmHWM")
        channels = int(image.shape[-1])
        out.append(f"render {rep + 1}: mi.render (the developed film, {channels} ch) peak {h1 - r0:+.0f} kept "
                   f"{r1 - r0:+.0f}, per-light read peak {h2 - r1:+.0f} kept {r2 - r1:+.0f} MiB")
        del image, imgs
    return "; ".join(out), channels


# --------------------------------------------------------------------------- main
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", default="classic-train")
    ap.add_argument("--n-lights", type=int, nargs="+", default=[1, 3, 8, 32, 96])
    ap.add_argument("--scenes", type=int, default=5, help="scenes per N (part 1)")
    ap.add_argument("--split-scenes", type=int, default=3, help="scenes of the one-pass vs 32-pass comparison")
    ap.add_argument("--memory-lights", type=int, nargs="+", default=[3, 96])
    ap.add_argument("--memory-runs", type=int, default=2)
    ap.add_argument("--memory-frames", type=int, default=4, help="dataset.frames_per_shard of the memory runs "
                                                                "(the preset's own is 8)")
    ap.add_argument("--parts", default="1,2,3", help="which parts to run (1: time against N, 2: one pass vs "
                                                      "three-light passes, 3: worker memory)")
    ap.add_argument("--quick", action="store_true", help="2 scenes, 1 split scene, one memory run (~2 min)")
    ap.add_argument("--no-cold", dest="cold", action="store_false",
                    help="skip the memory run with an empty drjit disk cache (kernels compiled in the worker)")
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0, help="scene seed (the same scenes for every N)")
    ap.add_argument("--set", action="append", default=[], help="config override key=value (every part)")
    ap.add_argument("--_phases", help=argparse.SUPPRESS)
    ap.add_argument("--_out", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a._phases:
        phases_child(a)
        return
    if a.quick:
        a.scenes, a.split_scenes, a.memory_runs, a.cold = 2, 1, 1, False
    a.n_lights = sorted(set(a.n_lights))
    from msps_render.render.kernels import KernelLog
    from msps_render.render.variant import activate

    mi = activate(a.variant, a.threads)
    log = KernelLog()
    c = rig_config(a.preset, max(a.n_lights), a.set)
    print(f"{a.preset} ({', '.join(PRESET_SETS + a.set)}): {c.camera.width}x{c.camera.height}, {c.integrator.spp} spp "
          f"{c.integrator.sampler} {c.integrator.kind} (max_depth {c.integrator.max_depth}), shapes "
          f"{c.shape.source} {c.shape.families}, merl_fraction {c.materials.merl_fraction}, rig {c.rig.describe()} "
          f"(sampling {c.rig.sampling}); {a.variant} (Mitsuba {mi.__version__}), {a.threads} threads, "
          f"scene seed {a.seed}; load average {' '.join(f'{x:.1f}' for x in os.getloadavg())}", flush=True)
    parts = {int(x) for x in a.parts.split(",") if x.strip()}
    t0 = time.perf_counter()
    falls = ok_split = ok_mem = None
    if 1 in parts:
        rows = time_against_n(a, log)
        falls = print_against_n(rows, a)
        print(f"(part 1: {time.perf_counter() - t0:.0f} s; load average {os.getloadavg()[0]:.1f})", flush=True)
    if 2 in parts:
        t1 = time.perf_counter()
        split = one_vs_split(a, log)
        ok_split = print_split(split, max(a.n_lights))
        print(f"(part 2: {time.perf_counter() - t1:.0f} s; load average {os.getloadavg()[0]:.1f})", flush=True)
    if 3 in parts:
        t2 = time.perf_counter()
        mem = worker_memory(a)
        ok_mem = print_memory(mem, a)
        print(f"(part 3: {time.perf_counter() - t2:.0f} s; load average {os.getloadavg()[0]:.1f})", flush=True)
    verdict = {None: "-", True: "met", False: "NOT met"}
    print(f"\nsummary: per-light time falls with N: {verdict[falls]}; one pass <= {TARGET_SPLIT_RATIO} x the "
          f"three-light passes: {verdict[ok_split]}; worker peak <= {TARGET_WORKER_MIB:.0f} MiB at N = "
          f"{max(a.memory_lights)}: {verdict[ok_mem]}; total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
