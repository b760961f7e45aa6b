"""Built-in measured materials: bake cost, table-lookup vs network-evaluation cost, binning error.

Why the toolkit bakes the Neural-BRDF fits into MERL tables instead of evaluating the network
inside the BSDF: both are evaluated here in numpy on the same random direction pairs (median of
`--repeats`, interleaved), together with the one-off bake and the relative difference between
the baked lookup and the network (MERL's binning) on directions above the horizon.

Usage:  .venv/bin/python benchmarks/bench_nbrdf.py [--n 1000000] [--repeats 5] [--materials 4]
"""
from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--materials", type=int, default=4)
    a = ap.parse_args()
    os.environ.setdefault("MSPS_CACHE_DIR", tempfile.mkdtemp(prefix="msps-bench-nbrdf-"))
    from msps_render.brdf import merl, nbrdf

    rng = np.random.default_rng(0)

    def hemi(n):
        v = rng.normal(size=(n, 3))
        v[:, 2] = np.abs(v[:, 2])
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    wi, wo = hemi(a.n), hemi(a.n)
    th, _, td, pd = merl.half_diff_angles(wi, wo)
    names = nbrdf.builtin_names()[:: max(1, 80 // a.materials)][: a.materials]
    print(f"{a.n:,} direction pairs, materials: {', '.join(names)}")
    print("| material | bake (s) | table lookup (ms) | network eval (ms) | ratio | median rel. diff | p95 rel. diff |")
    print("|---|---|---|---|---|---|---|")
    for name in names:
        w = nbrdf.read_weights(nbrdf.weights_path(name))
        t0 = time.perf_counter()
        table = merl.read_merl(nbrdf.baked_table(nbrdf.weights_path(name)))
        bake = time.perf_counter() - t0
        tl, tn = [], []
        for _ in range(a.repeats):
            t0 = time.perf_counter(); lk = merl.lookup(table, wi, wo); tl.append(time.perf_counter() - t0)
            t0 = time.perf_counter(); nv = nbrdf.evaluate(w, th, td, pd); tn.append(time.perf_counter() - t0)
        lum = lambda x: x @ np.array([0.2126, 0.7152, 0.0722])
        ok = lum(nv) > 1e-3
        rel = np.abs(lum(lk)[ok] - lum(nv)[ok]) / lum(nv)[ok]
        ml, mn = statistics.median(tl) * 1e3, statistics.median(tn) * 1e3
        print(f"| {name} | {bake:.2f} | {ml:.0f} | {mn:.0f} | {mn / ml:.1f}x | {np.median(rel):.4f} | "
              f"{np.percentile(rel, 95):.4f} |")


if __name__ == "__main__":
    main()
