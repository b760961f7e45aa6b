"""Appearance figures and the cost of textures (docs/appearance.md).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/appearance_sheet.py --out docs/img [--only gamut,sheet,cost]
        [--seeds 8] [--size 256] [--threads 1]

Writes into `--out`:
  albedo-gamut.png    3000 draws each of `brdf.families._albedo(rng, gamut=...)` for gamut
                      "moderate" and "full": hue vs channel ratio min/max (each dot in its own
                      colour), histograms of min/max and of the largest channel.
  texture-kinds.png   one procedural shape (train.toml's shape config, fixed seed), 128x128 under the
                      paper's three coloured lights, once per texture kind (smooth, noise, patches,
                      stripes, decals, a blend of two measured materials, an image texture made here
                      in a temporary folder, triplanar): rendered image (tone-mapped), ground-truth
                      albedo (the blend: its weight map), normal map.  Textures are drawn by the
                      sampler's own `scene.texturing.texture_materials`.
  texture-cost.json   seconds per frame with and without textures, ONE run, same scenes: `--seeds`
                      seeds of train-colour.toml's scene config, each sampled with
                      texture.fraction = 1 and = 0 (textures are drawn last, so shape, materials,
                      lights are identical), rendered at `--size` with the preset's integrator,
                      `--threads` threads, after one warm-up render of each variant; the two variants
                      alternate in order per seed, and the procedural-shape cache is cleared before
                      every frame (a corpus draws a new shape per frame).  Per-stage medians from
                      `StageTimer` (drjit kernel compile time moved into its own stage).
The cost table is also printed.  Whole script: ~2-3 minutes on the 2-core machine.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import colorsys  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import tomllib  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

KIND_ROWS = ("smooth", "noise", "patches", "stripes", "decals")
SHEET_SCALE = (0.25, 0.35)  # sheet only: feature sizes near the middle of the default range, comparable rows


def _scene_cfg(preset: str):
    from msps_render.scene.sample import SceneConfig

    with open(ROOT / "scenes" / f"{preset}.toml", "rb") as fh:
        return SceneConfig.model_validate(tomllib.load(fh)["scene"])


def _with_texture(cfg, **update):
    mc = cfg.materials
    return cfg.model_copy(update={"materials": mc.model_copy(update={"texture": mc.texture.model_copy(update=update)})})


# ----------------------------------------------------------------------------- gamut
def gamut_figure(out: Path, n: int = 3000) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from msps_render.brdf.families import GAMUTS, _albedo
    from msps_render.preview import srgb8

    fig, axes = plt.subplots(len(GAMUTS), 3, figsize=(14.5, 4.3 * len(GAMUTS)), constrained_layout=True)
    bins_r = np.linspace(0, 1, 41)
    bins_v = np.linspace(0, 1, 41)
    for row, gamut in enumerate(GAMUTS):
        rng = np.random.default_rng(0)
        rgb = np.array([_albedo(rng, gamut=gamut) for _ in range(n)])
        hue = np.array([colorsys.rgb_to_hsv(*c)[0] for c in rgb])
        ratio = rgb.min(1) / np.maximum(rgb.max(1), 1e-9)
        vmax = rgb.max(1)
        a0, a1, a2 = axes[row]
        a0.set_facecolor("0.5")
        a0.scatter(hue * 360, ratio, c=srgb8(rgb) / 255.0, s=6, linewidths=0)
        a0.set(xlim=(0, 360), ylim=(0, 1.02), xlabel="hue (deg; HSV of the linear albedo)",
               ylabel=f'gamut = "{gamut}"\n\nchannel ratio min/max (1 = grey)')
        a0.yaxis.label.set_fontsize(11)
        a1.hist(ratio, bins=bins_r, color="tab:blue")
        a1.set(xlim=(0, 1), xlabel="channel ratio min/max (0 = fully saturated, 1 = grey)",
               ylabel=f"count of {n} draws")
        a1.text(0.97, 0.95, f"median {np.median(ratio):.2f}\nmin {ratio.min():.2f}", transform=a1.transAxes,
                ha="right", va="top")
        a2.hist(vmax, bins=bins_v, color="tab:orange")
        a2.set(xlim=(0, 1), xlabel="largest channel (linear albedo; brightness)", ylabel=f"count of {n} draws")
        a2.text(0.03, 0.95, f"median {np.median(vmax):.2f}\nrange {vmax.min():.2f}-{vmax.max():.2f}",
                transform=a2.transAxes, ha="left", va="top")
        if row == 0:
            a0.set_title("hue vs saturation (each dot in its own colour, sRGB)")
            a1.set_title("histogram: min/max channel ratio (saturation)")
            a2.set_title("histogram: largest channel (brightness)")
    fig.suptitle(f'Albedo colours of analytic materials, [scene.materials] albedo = "moderate" (top) vs "full" '
                 f"(bottom)\n{n} draws each of brdf.families._albedo(rng, lo=0.15, hi=0.9, gamut)", fontsize=12)
    path = out / "albedo-gamut.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


# ----------------------------------------------------------------------------- texture sheet
def _test_image(folder: Path) -> Path:
    """A 256x256 8-bit sRGB test texture: a hue gradient checkered with light grey, a dark cross."""
    from msps_render.io.png16 import write_png

    H = W = 256
    y, x = np.mgrid[0:H, 0:W]
    hue = (x / W + 0.25 * y / H) % 1.0
    grad = np.array([colorsys.hsv_to_rgb(h, 0.85, 0.95) for h in hue.ravel()]).reshape(H, W, 3)
    checker = ((x // 32 + y // 32) % 2 == 0)[..., None]
    img = np.where(checker, grad, 0.85)
    img[(np.abs(x - W // 2) < 4) | (np.abs(y - H // 2) < 4)] = 0.08
    return write_png(folder / "checker-gradient.png", (img * 255 + 0.5).astype(np.uint8))


def _sheet_specs(image_folder: Path, size: int, shape_seed: int):
    from msps_render.scene.materials import sample_analytic, sample_materials
    from msps_render.scene.sample import sample_scene
    from msps_render.scene.spec import SplitSpec
    from msps_render.scene.texturing import texture_materials

    cfg = _scene_cfg("train")
    base = sample_scene(cfg, np.random.default_rng(shape_seed), seed=shape_seed)
    base = base.model_copy(update={"split": SplitSpec(),
                                   "camera": base.camera.model_copy(update={"width": size, "height": size})})
    mc = cfg.materials.model_copy(update={"albedo": "full"})
    mc = mc.model_copy(update={"texture": mc.texture.model_copy(update={"scale_range": SHEET_SCALE})})
    rows = []
    for i, kind in enumerate((*KIND_ROWS, "blend", "image")):
        rng = np.random.default_rng([7, i])
        if kind == "blend":
            mat = tuple(sample_materials(rng, 1, merl_fraction=1.0, holdout="train"))
            tc = mc.texture.model_copy(update={"fraction": 1.0, "kinds": ["patches"], "blend": True})
        else:
            m = sample_analytic("principled", rng, gamut="full")
            mat = (m.model_copy(update={"params": {**m.params, "metallic": 0.0, "specular": 0.5}}),)
            tc = mc.texture.model_copy(update={"fraction": 1.0, "kinds": [kind]} if kind != "image" else
                                       {"fraction": 1.0, "kinds": ["image"], "folder": str(image_folder),
                                        "mapping": "triplanar"})
        mats = texture_materials(mc.model_copy(update={"texture": tc}), base.shape, mat, rng)
        if mats[0].texture is None or (kind == "blend" and mats[0].blend is None):
            raise RuntimeError(f"row {kind}: the sampler gave no texture ({mats[0]})")
        rows.append((kind, base.model_copy(update={"materials": mats})))
    return base, rows


def texture_sheet(out: Path, size: int = 128, shape_seed: int = 3, threads: int = 1) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from msps_render.preview import normal_to_rgb8, srgb8, tonemap
    from msps_render.render.render import render_frame

    with tempfile.TemporaryDirectory(prefix="msps-tex-") as tmp:
        _test_image(Path(tmp))
        base, rows = _sheet_specs(Path(tmp), size, shape_seed)
        frames = [(kind, spec, render_frame(spec, threads=threads)) for kind, spec in rows]
    for kind, spec, f in frames:
        m = spec.materials[0]
        print(f"  {kind}: {m.name} texture {m.texture.kind} scale {m.texture.scale:.2f} colours {len(m.texture.colors)}"
              f"{' blend ' + m.blend.name if m.blend else ''}; albedo range {f.albedo[f.mask].min():.3f}-"
              f"{f.albedo[f.mask].max():.3f}, blend range {f.blend[f.mask].min():.2f}-{f.blend[f.mask].max():.2f}")
    fig, axes = plt.subplots(len(frames), 3, figsize=(3 * 2.3 + 1.2, len(frames) * 2.3), squeeze=False)
    for r, (kind, spec, f) in enumerate(frames):
        m = spec.materials[0]
        t = m.texture
        if kind == "blend":
            label = (f"measured blend\n{m.name.split(':')[-1]}\n+ {m.blend.name.split(':')[-1]}\n"
                     f"(weight: {t.kind})")
        elif kind == "image":
            label = f"image\n({t.mapping},\nscale {t.scale:.2f})"
        else:
            label = f"{kind}\n({len(t.colors)} colours,\nscale {t.scale:.2f})"
        axes[r, 0].imshow(tonemap(f.image, f.mask))
        if kind == "blend":
            cmap = matplotlib.colormaps["viridis"].with_extremes(bad="black")
            axes[r, 1].imshow(np.where(f.mask, f.blend, np.nan), cmap=cmap, vmin=0, vmax=1)
            axes[r, 1].text(0.5, 0.02, "BLEND WEIGHT (no albedo):\n0 = first, 1 = second", fontsize=7,
                            color="white", ha="center", va="bottom", transform=axes[r, 1].transAxes)
        else:
            axes[r, 1].imshow(srgb8(f.albedo))
        axes[r, 2].imshow(normal_to_rgb8(f.normal, f.mask))
        axes[r, 0].set_ylabel(label, fontsize=9, rotation=0, ha="right", va="center", labelpad=6)
        for a in axes[r]:
            a.set_xticks([])
            a.set_yticks([])
    for c, title in enumerate(("rendered image (tone-mapped)", "ground-truth albedo (sRGB)", "normal map")):
        axes[0, c].set_title(title, fontsize=9)
    fig.suptitle(f"Texture kinds on one procedural shape ({base.shape.name}), {size}x{size}, "
                 f"3 coloured lights, {base.integrator.spp} spp;\nfull gamut, texture scale drawn in "
                 f"{SHEET_SCALE[0]}-{SHEET_SCALE[1]}, max_edge {rows[0][1].materials[0].texture.max_edge}",
                 fontsize=10)
    fig.subplots_adjust(left=0.2, right=0.99, top=0.935, bottom=0.01, wspace=0.04, hspace=0.12)
    path = out / "texture-kinds.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


# ----------------------------------------------------------------------------- cost
def texture_cost(out: Path, n_seeds: int = 8, size: int = 256, threads: int = 1, argv: str = "") -> dict:
    from msps_render.render.kernels import KernelLog
    from msps_render.render.render import render_frame
    from msps_render.render.variant import activate, resolve_variant
    from msps_render.scene import families as FM
    from msps_render.scene.sample import sample_scene
    from msps_render.timing import StageTimer, stage

    cfg = _scene_cfg("train-colour")
    cfg = cfg.model_copy(update={"camera": cfg.camera.model_copy(update={"width": size, "height": size})})
    variants = {"textured": _with_texture(cfg, fraction=1.0), "untextured": _with_texture(cfg, fraction=0.0)}
    variant = resolve_variant("rgb")
    mi = activate(variant, threads)
    log = KernelLog()
    timer = StageTimer(probe=log.probe)

    def one(name: str, seed: int) -> tuple[float, dict, list]:
        FM._generate.cache_clear()  # a corpus frame builds a new shape
        t0 = time.perf_counter()
        with stage(timer, "sample"):
            spec = sample_scene(variants[name], np.random.default_rng(seed), seed=seed)
        render_frame(spec, variant=variant, threads=threads, timer=timer)
        wall = time.perf_counter() - t0
        mats = [m.name + (f"[{m.texture.kind}" + (f"+{m.blend.name}]" if m.blend else "]") if m.texture else "")
                for m in spec.materials]
        return wall, timer.end_frame(), [spec.shape.name, *mats]

    for name in variants:  # warm-up (excluded): first kernels, plugin registration
        one(name, 10_000)
    first_use = preload_measured(mi, cfg.materials)

    def faces(seed: int) -> tuple[int, int]:
        """Faces of the seed's mesh before and after subdivision to max_edge (outside the timing)."""
        from msps_render.render.textures import subdivide_to_edge
        from msps_render.scene.shapes import build_mesh

        spec = sample_scene(variants["textured"], np.random.default_rng(seed), seed=seed)
        if spec.shape.kind == "sphere":
            return 0, 0
        mesh = build_mesh(spec.shape)
        tex = [m.texture.max_edge for m in spec.materials if m.texture is not None]
        return len(mesh.faces), len(subdivide_to_edge(mesh, min(tex)).faces) if tex else len(mesh.faces)
    seeds = list(range(1, n_seeds + 1))
    rows = []
    for i, seed in enumerate(seeds):
        order = list(variants) if i % 2 == 0 else list(variants)[::-1]
        res = {name: one(name, seed) for name in order}
        f0, f1 = faces(seed)
        rows.append({"seed": seed, "scene": res["textured"][2], "faces": f0, "faces_subdivided": f1,
                     **{f"{n}_s": round(res[n][0], 4) for n in variants},
                     "ratio": round(res["textured"][0] / res["untextured"][0], 4),
                     **{f"{n}_stages": {k: round(v, 4) for k, v in res[n][1].items()} for n in variants}})
        print(f"seed {seed}: textured {res['textured'][0]:.2f} s, untextured {res['untextured'][0]:.2f} s, "
              f"ratio {rows[-1]['ratio']:.2f}, faces {f0} -> {f1}  {' '.join(res['textured'][2])}", flush=True)
    log.close()
    stages = sorted({k for r in rows for n in variants for k in r[f"{n}_stages"]},
                    key=lambda s: -statistics.median(r["textured_stages"].get(s, 0.0) for r in rows))
    med = {n: {s: round(statistics.median(r[f"{n}_stages"].get(s, 0.0) for r in rows), 4) for s in stages}
           for n in variants}
    result = {
        "command": f"OMP_NUM_THREADS=1 .venv/bin/python benchmarks/appearance_sheet.py {argv}".strip(),
        "preset": "train-colour (scene config)", "size": size, "spp": cfg.integrator.spp,
        "integrator": f"{cfg.integrator.kind} max_depth {cfg.integrator.max_depth}",
        "threads": threads, "variant": variant, "mitsuba": mi.__version__,
        "texture": {"textured": "texture.fraction = 1.0", "untextured": "texture.fraction = 0.0",
                    "max_edge": cfg.materials.texture.max_edge, "kinds": cfg.materials.texture.kinds},
        "seeds": seeds, "warmup_seed": 10_000,
        "measured_tables_preloaded": first_use,
        "load_average_1min_at_end": round(os.getloadavg()[0], 2),
        "median_s_per_frame": {n: round(statistics.median(r[f"{n}_s"] for r in rows), 4) for n in variants},
        "median_ratio_textured_over_untextured": round(statistics.median(r["ratio"] for r in rows), 4),
        "median_stage_s": med,
        "note": "stage medians are per stage over seeds (they need not sum to the median total); "
                "'texture' = subdivision to max_edge + texture evaluation at the vertices, 'mesh' = shape "
                "generation + Mitsuba mesh buffers, 'materials' = BSDF construction (every measured table "
                "of the train pool was loaded once before the measured frames, as in a long-running worker; "
                "their first-use cost is measured_tables_preloaded), 'scene load' = mi.load_dict (BVH), 'kernel compile' "
                "= drjit compile time of kernels not in the in-memory cache (disk cache ~/.drjit in use)",
        "per_seed": rows,
    }
    (out / "texture-cost.json").write_text(json.dumps(result, indent=1) + "\n")
    m = result["median_s_per_frame"]
    print()
    print(f"train-colour scenes, {size}x{size}, {cfg.integrator.spp} spp {cfg.integrator.kind}, {threads} thread(s), "
          f"{variant}, {len(seeds)} seeds (medians):")
    print("| stage | textured (s) | untextured (s) |")
    print("|---|---|---|")
    for s in stages:
        print(f"| {s} | {med['textured'][s]:.3f} | {med['untextured'][s]:.3f} |")
    print(f"| **frame** | {m['textured']:.3f} | {m['untextured']:.3f} |")
    print(f"median per-seed ratio textured/untextured: {result['median_ratio_textured_over_untextured']:.2f} "
          f"(range {min(r['ratio'] for r in rows):.2f}-{max(r['ratio'] for r in rows):.2f})")
    return result


def preload_measured(mi, mc) -> dict:
    """Load every measured material of the training pool once (steady state of a long-running worker,
    whose per-process table cache holds every table after some frames); returns the first-use times."""
    from msps_render.brdf.library import held_out, load_catalogue
    from msps_render.render.materials import to_mitsuba
    from msps_render.scene.materials import _base_name, measured_pool

    test = held_out(mc.split_file)
    pool = [m for m in measured_pool(load_catalogue(mc.catalogue), mc.measured, mc.merl_dir)
            if mc.holdout == "all" or (_base_name(m) in test) == (mc.holdout == "test")]
    times = []
    for m in pool:
        t0 = time.perf_counter()
        mi.load_dict(to_mitsuba(m))
        times.append(time.perf_counter() - t0)
    print(f"preloaded {len(pool)} measured tables: median {statistics.median(times):.3f} s each on first use "
          f"(total {sum(times):.1f} s)", flush=True)
    return {"count": len(pool), "median_first_use_s": round(statistics.median(times), 4),
            "total_s": round(sum(times), 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "img")
    ap.add_argument("--only", default="gamut,sheet,cost", help="comma list of gamut, sheet, cost")
    ap.add_argument("--seeds", type=int, default=8, help="cost: scenes measured")
    ap.add_argument("--size", type=int, default=256, help="cost: frame size (px)")
    ap.add_argument("--sheet-size", type=int, default=128)
    ap.add_argument("--shape-seed", type=int, default=3, help="sheet: seed of train.toml's scene for the shape")
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    only = set(a.only.split(","))
    t0 = time.perf_counter()
    if "gamut" in only:
        print("wrote", gamut_figure(a.out), flush=True)
    if "sheet" in only:
        print("wrote", texture_sheet(a.out, a.sheet_size, a.shape_seed, a.threads), flush=True)
    if "cost" in only:
        argv = " ".join(sys.argv[1:])
        texture_cost(a.out, a.seeds, a.size, a.threads, argv)
        print("wrote", a.out / "texture-cost.json")
    print(f"total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
