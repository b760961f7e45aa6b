"""Scene load (Embree BVH build) time against triangle count: icospheres loaded alone.

Usage:  MSPS_THREADS=1 PYTHONPATH=. .venv/bin/python benchmarks/bench_bvh.py

Why: in a paper-train frame `mi.load_dict` is ~0.057 s, most of it building the BVH of the
20,480-triangle blobby mesh (icosphere subdivision 5); this shows how it scales.
"""
from __future__ import annotations

import statistics
import time

import numpy as np

from msps_render.render.variant import activate
from msps_render.scene.geometry import icosphere


def main() -> None:
    import drjit as dr

    mi = activate("llvm_ad_rgb", 1)
    for sub in (3, 4, 5, 6):
        v, f = icosphere(sub)
        times = []
        for _ in range(5):
            m = mi.Mesh("m", len(v), len(f), has_vertex_normals=False)
            p = mi.traverse(m)
            p["vertex_positions"] = dr.ravel(mi.TensorXf(v.astype(np.float32)))
            p["faces"] = dr.ravel(mi.TensorXu(f.astype(np.uint32)))
            p.update()
            t0 = time.perf_counter()
            mi.load_dict({"type": "scene", "m": m})
            times.append(time.perf_counter() - t0)
        print(f"subdivision {sub}: {len(f):>6} triangles, scene load median {statistics.median(times) * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
