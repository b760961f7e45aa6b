"""MERL plugin cost vs Mitsuba's built-in `roughplastic` (issue 3), plus chi^2 p-values.

Usage:  .venv/bin/python benchmarks/bench_merl.py [--repeats 7] [--threads 2] [--res 256] [--spp 64]
                                                  [--variants llvm_ad_rgb,scalar_rgb]

Same scene for every BSDF (unit sphere filling a res x res orthographic view, one
directional light, path tracer max_depth 3, independent sampler, box filter),
same spp and variant. Each configuration is rendered once to compile (JIT), then
`--repeats` times interleaved across BSDFs, so machine-load drift hits all of them
alike; the table gives the median and the ratio to roughplastic from this one run.
scalar variants use res/8 (the Python plugin is called once per sample there).
Tables are generated into $MSPS_CACHE_DIR/brdf (default ~/.cache/msps/brdf).
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

SHINY = ("ggx", {"kd": [0.05, 0.12, 0.5], "ks": [1.0, 1.0, 1.0], "alpha": 0.08, "f0": 0.04})
DIFFUSE = ("lambert", {"albedo": [0.8, 0.8, 0.8]})


def scene_dict(mi, bsdf: dict, res: int, spp: int) -> dict:
    T = mi.ScalarTransform4f
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 3},
        "sensor": {"type": "orthographic",
                   "to_world": T().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0]) @ T().scale([1.05, 1.05, 1]),
                   "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"},
                            "pixel_format": "rgb"},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "shape": {"type": "sphere", "radius": 1.0, "bsdf": bsdf},
        "sun": {"type": "directional", "direction": [-0.5, -0.3, -0.81], "irradiance": {"type": "rgb", "value": 3.0}},
    }


def chi2_pvalues(mi) -> list[tuple[str, tuple, float]]:
    from mitsuba.chi2 import BSDFAdapter, ChiSquareTest, SphericalDomain

    from msps_render.brdf import analytic

    out = []
    for label, (model, params) in (("diffuse-like (lambert 0.8)", DIFFUSE),
                                   ("shiny (ggx alpha 0.05)", ("ggx", {"kd": [0.05] * 3, "ks": [1.0] * 3,
                                                                       "alpha": 0.05, "f0": 0.04}))):
        path = str(analytic.generated_table(model, params))
        for wi in ((0.0, 0.0, 1.0), (0.6, 0.0, 0.8), (0.9, 0.0, 0.43589)):
            sf, pf = BSDFAdapter("merl", {"type": "merl", "filename": path}, wi=mi.ScalarVector3f(*wi))
            t = ChiSquareTest(domain=SphericalDomain(), sample_func=sf, pdf_func=pf, sample_dim=3,
                              sample_count=1_000_000, res=201, ires=8)
            t.run(0.01, quiet=True)
            out.append((label, wi, float(t.p_value)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--variants", default="llvm_ad_rgb,scalar_rgb")
    args = ap.parse_args()

    import drjit as dr
    import mitsuba as mi

    from msps_render.brdf import analytic, plugin

    rows, pvals = [], []
    for variant in args.variants.split(","):
        mi.set_variant(variant)
        if dr.is_jit_v(mi.Float):
            dr.set_thread_count(args.threads)
        plugin.register()
        res = args.res if dr.is_jit_v(mi.Float) else max(8, args.res // 8)
        bsdfs = {
            "roughplastic": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.08,
                             "diffuse_reflectance": {"type": "rgb", "value": [0.05, 0.12, 0.5]}},
            "diffuse": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.8}},
            "merl (shiny table)": {"type": "merl", "filename": str(analytic.generated_table(*SHINY))},
            "merl (lambert table)": {"type": "merl", "filename": str(analytic.generated_table(*DIFFUSE))},
        }
        scenes = {k: mi.load_dict(scene_dict(mi, b, res, args.spp)) for k, b in bsdfs.items()}
        first, times = {}, {k: [] for k in scenes}
        for k, sc in scenes.items():
            t0 = time.perf_counter()
            np.asarray(mi.render(sc, seed=0))
            first[k] = time.perf_counter() - t0
        for r in range(args.repeats):
            for k, sc in scenes.items():
                t0 = time.perf_counter()
                np.asarray(mi.render(sc, seed=r + 1))
                times[k].append(time.perf_counter() - t0)
        ref = statistics.median(times["roughplastic"])
        for k in scenes:
            med = statistics.median(times[k])
            ns = med / (res * res * args.spp) * 1e9
            rows.append((variant, k, res, args.spp, first[k], med, ns, med / ref))
        if dr.is_jit_v(mi.Float) and not pvals:
            pvals = chi2_pvalues(mi)

    print("| variant | BSDF | res | spp | first render (s) | median (s) | ns / sample | ratio to roughplastic |")
    print("|---|---|---|---|---|---|---|---|")
    for v, k, res, spp, f, med, ns, ratio in rows:
        print(f"| {v} | {k} | {res}x{res} | {spp} | {f:.3f} | {med:.3f} | {ns:.1f} | {ratio:.2f} |")
    if pvals:
        print("\n| table | wi | chi^2 p-value (1e6 samples, res 201) |\n|---|---|---|")
        for label, wi, p in pvals:
            print(f"| {label} | ({wi[0]:.2f}, {wi[1]:.2f}, {wi[2]:.2f}) | {p:.3f} |")


if __name__ == "__main__":
    main()
