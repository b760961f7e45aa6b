"""Probe: does a corpus worker's render kernel cost what the bare kernel of the same frame costs?

bench_breakdown compares the pipeline's median frame with the median bare kernel (`mi.render` of a fresh
scene, second call). Kernel time varies 6x between frames of one preset (measured tables, shapes), so
this pairs them frame by frame: the render stage as a worker runs it (`render_shard`, the worker's scene
pool and BSDF slots, unbatched) and drjit's own execution time of its kernels (kernel history), against
the same frame's bare kernel.

    MSPS_THREADS=1 PYTHONPATH=. .venv/bin/python experiments/kernel_parity_probe.py train 3

Prints one row per frame and the medians (ms: CPU clock for the stages; drjit's execution times are wall
clock, so they mean something only on a quiet machine).
"""
from __future__ import annotations

import gc
import statistics
import sys
import tempfile
import time
from pathlib import Path

import drjit as dr

import msps_render.render.render as R
from msps_render.pipeline.config import load_config
from msps_render.pipeline.execute import WorkerSettings, render_shard
from msps_render.pipeline.plan import frame_rngs, frame_seed, plan
from msps_render.render.pool import ScenePool
from msps_render.render.scene_dict import build_scene_dict
from msps_render.render.variant import activate, resolve_variant
from msps_render.scene.sample import sample_scene


def _jit_ms() -> float:
    return sum(k["execution_time"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT)


def main(preset: str, n_shards: int) -> None:
    cfg = load_config(preset, [f"dataset.n_shards={n_shards}"])
    variant = resolve_variant("rgb")
    mi = activate(variant, 1)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    rows = []
    one_pass = R.render_emitters_one_pass

    def timed(*a, **k):  # the worker's render stage, with its kernels' own execution time
        dr.kernel_history()
        t = time.process_time()
        out = one_pass(*a, **k)
        rows.append(((time.process_time() - t) * 1e3, _jit_ms()))
        return out

    R.render_emitters_one_pass = timed
    scenes = ScenePool()
    with tempfile.TemporaryDirectory() as out:
        (Path(out) / "shards").mkdir()
        ws = WorkerSettings(out_dir=out, variant=variant, threads=1)
        for task in plan(cfg):
            render_shard(task, ws, scenes=scenes)
    R.render_emitters_one_pass = one_pass
    scenes.clear()
    gc.collect()
    fps = cfg.dataset.frames_per_shard
    specs = [sample_scene(cfg.scene, rng, seed=frame_seed(t, j), frame_index=t.shard_in_condition * fps + j)
             for t in plan(cfg) for j, rng in enumerate(frame_rngs(t, fps))]
    bare = []
    for spec in specs:  # bench_breakdown's bare kernel: a fresh scene, the second call timed
        scene = mi.load_dict(build_scene_dict(spec, mi))
        dr.eval(mi.render(scene, spp=spec.integrator.spp, seed=spec.integrator.seed))
        dr.sync_thread()
        dr.kernel_history()
        t = time.process_time()
        dr.eval(mi.render(scene, spp=spec.integrator.spp, seed=spec.integrator.seed))
        dr.sync_thread()
        bare.append(((time.process_time() - t) * 1e3, _jit_ms()))
        del scene
        gc.collect()
    if len(rows) != len(bare):
        sys.exit(f"{len(rows)} worker renders for {len(bare)} frames: is {preset} batched or pooled here?")
    print("| frame | worker render stage (CPU) | its kernels (wall) | bare mi.render (CPU) | its kernels (wall) | "
          "CPU, worker / bare |")
    print("|---|---|---|---|---|---|")
    for i, ((ws_, wk), (bs_, bk)) in enumerate(zip(rows, bare)):
        print(f"| {i} | {ws_:.1f} | {wk:.1f} | {bs_:.1f} | {bk:.1f} | {ws_ / bs_:.2f} |")
    med = statistics.median
    print(f"medians: worker stage {med(r[0] for r in rows):.1f}, bare {med(b[0] for b in bare):.1f} CPU ms; "
          f"per frame, worker / bare: CPU {med(r[0] / b[0] for r, b in zip(rows, bare)):.3f}, "
          f"kernels {med(r[1] / b[1] for r, b in zip(rows, bare)):.3f} (wall: only on a quiet machine)")


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 3)
