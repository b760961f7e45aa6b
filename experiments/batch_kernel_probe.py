"""Why a batched launch's render kernel costs more per frame than the same frames rendered one at a
time (issue 45 item 2, a probe, not product).

In one process: 8 paper-train frames (the 2nd shard) rendered bare (`mi.render` of each frame's own
scene, second call) and as batches of B = 2 and 8 (`render.batch.render_batch`, warm), with drjit's
kernel history: the largest kernel of a launch is the render kernel; its execution time per frame is
printed (no Python, no tracing, no film read-back).  `--materials`:
  drawn          the materials as the preset draws them (with `--set scene.materials.merl_fraction=1`:
                 measured only, the case where the gap shows)
  same           every part of every frame the same measured material (one table in the launch)
  one-per-frame  each frame one measured material on all its parts (B tables in a B-frame launch)
`--huge`: measured tables copied into anonymous memory with transparent huge pages (MADV_HUGEPAGE)
instead of memory-mapping the baked file: fewer TLB misses on the tables' random lookups.

    MSPS_THREADS=1 PYTHONPATH=. .venv/bin/python experiments/batch_kernel_probe.py \
        --materials drawn --set scene.materials.merl_fraction=1 [--huge]
"""
from __future__ import annotations

import argparse
import ctypes
import gc
import mmap

import drjit as dr
import numpy as np

from msps_render.pipeline.config import load_config
from msps_render.pipeline.plan import frame_rngs, frame_seed, plan
from msps_render.render import merl_bsdf
from msps_render.render.batch import BatchScenes, render_batch
from msps_render.render.scene_dict import build_scene_dict
from msps_render.render.variant import activate
from msps_render.scene.sample import sample_scene

HUGE = 2 << 20
MADV_HUGEPAGE = 14
_KEEP: list = []  # the probe's huge-page buffers, alive for the process


def huge_copy(a: np.ndarray) -> np.ndarray:
    """`a` copied into 2 MiB-aligned anonymous memory advised for transparent huge pages (drjit's
    LLVM arrays wrap numpy memory without a copy, so the table is read from there)."""
    size = -(-a.nbytes // HUGE) * HUGE + HUGE
    mm = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    buf = np.frombuffer(mm, dtype=np.uint8)
    off = -buf.ctypes.data % HUGE
    ctypes.CDLL("libc.so.6").madvise(ctypes.c_void_p(buf.ctypes.data + off), ctypes.c_size_t(size - off),
                                     MADV_HUGEPAGE)
    out = buf[off:off + a.nbytes].view(a.dtype).reshape(a.shape)
    out[...] = a
    _KEEP.append(mm)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--materials", choices=("drawn", "same", "one-per-frame"), default="drawn")
    ap.add_argument("--huge", action="store_true")
    ap.add_argument("--set", action="append", default=[])
    a = ap.parse_args()
    mi = activate("llvm_ad_rgb", 1)
    if a.huge:
        load = merl_bsdf._load_table
        merl_bsdf._load_table = lambda path: (huge_copy(np.asarray(load(path)[0])), *load(path)[1:])
    cfg = load_config("paper-train", ["dataset.n_shards=2", *a.set])
    task = list(plan(cfg))[1]
    specs = [sample_scene(cfg.scene, rng, seed=frame_seed(task, j), frame_index=task.shard_in_condition * 8 + j)
             for j, rng in enumerate(frame_rngs(task, 8))]
    if a.materials == "same":
        specs = [s.model_copy(update={"materials": [specs[0].materials[0]] * len(s.materials)}) for s in specs]
    elif a.materials == "one-per-frame":
        specs = [s.model_copy(update={"materials": [s.materials[0]] * len(s.materials)}) for s in specs]
    dr.set_flag(dr.JitFlag.KernelHistory, True)

    def render_kernel_ms() -> float:
        return max(k.get("execution_time", 0.0) for k in dr.kernel_history())

    bare = []
    for s in specs:
        scene = mi.load_dict(build_scene_dict(s, mi))
        dr.eval(mi.render(scene, spp=s.integrator.spp, seed=s.integrator.seed))
        dr.sync_thread()
        dr.kernel_history()
        dr.eval(mi.render(scene, spp=s.integrator.spp, seed=s.integrator.seed))
        dr.sync_thread()
        bare.append(render_kernel_ms())
        del scene
        gc.collect()
    print(f"materials {a.materials}, huge pages {a.huge}: bare render kernel {np.median(bare):.2f} ms a frame")
    for B in (2, 8):
        scenes = BatchScenes()
        groups = [specs[i:i + B] for i in range(0, len(specs), B)]
        for g in groups:
            render_batch(g, scenes=scenes)
        per_frame = []
        for _ in range(2):
            for g in groups:
                dr.kernel_history()
                render_batch(g, scenes=scenes)
                per_frame.append(render_kernel_ms() / B)
        print(f"  B = {B}: batched render kernel {np.median(per_frame):.2f} ms a frame")


if __name__ == "__main__":
    main()
