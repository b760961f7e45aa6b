"""What one more frame per kernel launch could save on the CPU (issue 45 item 1, a probe, not a product
benchmark): the CPU seconds of `mi.render` of one paper-train frame at 128², 8x8 and 1x1 pixels
(8 spp, one thread, kernels warm).  The 1x1 time is the fixed cost per launch (tracing the one-pass
integrator in Python, kernel lookup, launch, develop) that rendering B frames in one launch would
pay once instead of B times; the rest scales with the pixels.

    MSPS_THREADS=1 PYTHONPATH=. .venv/bin/python experiments/launch_overhead.py
"""
from __future__ import annotations

import time

import drjit as dr
import numpy as np

from msps_render.pipeline.config import load_config
from msps_render.render.scene_dict import build_scene_dict
from msps_render.render.variant import activate
from msps_render.scene.sample import sample_scene

mi = activate("llvm_ad_rgb", 1)
spec = sample_scene(load_config("paper-train").scene, np.random.default_rng(3), seed=3, frame_index=0)
for res in (128, 8, 1):
    d = build_scene_dict(spec, mi)
    d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = res
    scene = mi.load_dict(d)
    ts = []
    for i in range(8):
        t = time.process_time()
        np.array(mi.render(scene, spp=8, seed=i))
        dr.sync_thread()
        ts.append(time.process_time() - t)
    print(f"{res}x{res}: median of launches 3-8 {np.median(ts[2:]) * 1e3:.1f} ms CPU (first {ts[0] * 1e3:.0f} ms)")
