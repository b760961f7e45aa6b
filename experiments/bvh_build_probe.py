"""What building a scene around a new mesh costs in Mitsuba, by face count (issue 45).

A frame whose shape is new (train's procedural meshes) pays for Mitsuba's scene build: Embree's BVH,
built at `RTC_BUILD_QUALITY_HIGH` (hard-coded in Mitsuba 3's `src/render/scene_embree.inl`). This times
`mi.load_dict` of a scene holding only an icosphere mesh (built in memory, as `render.scene_dict` does),
at 4 sizes, CPU and wall clock, medians of the last 3 of 4 builds; and a variant and thread count.

    PYTHONPATH=. .venv/bin/python experiments/bvh_build_probe.py [VARIANT [DRJIT_THREADS]]

docs/benchmarks.md "A new machine; what a shard's write costs" has the numbers.
"""
from __future__ import annotations

import sys
import time

import numpy as np


def main() -> None:
    import drjit as dr
    import mitsuba as mi

    variant = sys.argv[1] if len(sys.argv) > 1 else "llvm_ad_rgb"
    mi.set_variant(variant)
    if len(sys.argv) > 2:
        dr.set_thread_count(int(sys.argv[2]))
    from msps_render.render.scene_dict import mitsuba_mesh
    from msps_render.scene.geometry import icosphere

    for sub in (3, 4, 5, 6):
        v, f = icosphere(sub)
        v, f = v.astype(np.float32), f.astype(np.uint32)
        times = []
        for _ in range(4):
            m, params = mitsuba_mesh(mi, "part0", v, f, v.copy())
            params.update()
            c, w = time.process_time(), time.perf_counter()
            mi.load_dict({"type": "scene", "object": m})
            times.append((time.process_time() - c, time.perf_counter() - w))
        cpu, wall = 1000 * np.median(np.array(times[1:]), axis=0)
        print(f"{variant} {len(f):>6} faces: scene build {cpu:.1f} ms CPU, {wall:.1f} ms wall "
              f"({1e6 * cpu / 1000 / len(f):.2f} us a face)")


if __name__ == "__main__":
    main()
