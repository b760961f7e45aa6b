"""Procedural shape families: generation cost per shape, and a normal-map contact sheet.

    .venv/bin/python benchmarks/bench_shapes.py time [--seeds 10]
    .venv/bin/python benchmarks/bench_shapes.py preview [--seeds 6 --size 128 --out docs/img/shape-families.png]

`time` builds each family's mesh for `--seeds` seeds with a cold cache and reports the median
(and max) of (a) the generator alone and (b) the full `build_mesh` (normalise, rotate,
crease-aware normals), plus face/vertex counts.  One-off per-process setup (icosphere and SH
basis tables) is warmed up first so the numbers are the per-shape cost.

`preview` renders the ground-truth normal map of `--seeds` shapes per family (one row per
family, colour (n+1)/2, background black) with the default scene config and writes one PNG.
"""
from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from msps_render.scene import families as FM  # noqa: E402
from msps_render.scene.shapes import build_mesh  # noqa: E402
from msps_render.scene.spec import ShapeSpec  # noqa: E402


def spec_for(name: str, seed: int) -> ShapeSpec:
    return ShapeSpec(kind="procedural", name=name, params={"seed": float(seed),
                                                         "version": float(FM.FAMILY_VERSIONS[name])},
                     radius=0.95)


def bench_time(n_seeds: int) -> None:
    for name in FM.SHAPE_FAMILIES:  # warm-up: per-process tables (icospheres, SH bases)
        for s in range(3):
            build_mesh(spec_for(name, 10_000 + s))
    print(f"# {platform.processor() or platform.machine()}, numpy {np.__version__}; {n_seeds} seeds per family, "
          f"cold mesh cache")
    print(f"{'family':<10} {'gen median':>11} {'gen max':>8} {'build median':>13} {'build max':>10} "
          f"{'faces (median)':>15} {'verts out':>10}")
    for name in FM.SHAPE_FAMILIES:
        gen, full, faces, verts = [], [], [], []
        for s in range(n_seeds):
            FM._generate.cache_clear()
            t0 = time.perf_counter()
            FM.procedural_mesh(name, {"seed": s})
            t1 = time.perf_counter()
            FM._generate.cache_clear()
            t2 = time.perf_counter()
            m = build_mesh(spec_for(name, s))
            t3 = time.perf_counter()
            gen.append(t1 - t0)
            full.append(t3 - t2)
            faces.append(len(m.faces))
            verts.append(len(m.vertices))
        print(f"{name:<10} {1e3 * np.median(gen):9.1f}ms {1e3 * max(gen):6.0f}ms {1e3 * np.median(full):11.1f}ms "
              f"{1e3 * max(full):8.0f}ms {int(np.median(faces)):>15d} {int(np.median(verts)):>10d}")


def preview(n_seeds: int, size: int, out: Path) -> None:
    from PIL import Image, ImageDraw

    from msps_render import SceneConfig, render_frame, sample_scene

    rows = []
    names = list(FM.SHAPE_FAMILIES)
    for name in names:
        cfg = SceneConfig.model_validate({"shape": {"source": "procedural", "families": [name]},
                                          "camera": {"width": size, "height": size},
                                          "integrator": {"spp": 1}})
        tiles = []
        for s in range(n_seeds):
            spec = sample_scene(cfg, np.random.default_rng([2024, s]))
            fr = render_frame(spec)
            img = np.where(fr.mask[..., None], (fr.normal + 1) / 2, 0.0)
            tiles.append((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8))
        rows.append(np.concatenate(tiles, axis=1))
        print(f"{name}: {n_seeds} rendered", flush=True)
    label_w = 90
    sheet = np.concatenate(rows, axis=0)
    canvas = Image.new("RGB", (sheet.shape[1] + label_w, sheet.shape[0]), (255, 255, 255))
    canvas.paste(Image.fromarray(sheet), (label_w, 0))
    d = ImageDraw.Draw(canvas)
    for i, name in enumerate(names):
        d.text((6, i * size + size // 2 - 6), name, fill=(0, 0, 0))
    out.parent.mkdir(parents=True, exist_ok=True)
    canvas.save(out)
    print(f"wrote {out} ({canvas.size[0]}x{canvas.size[1]})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("time")
    t.add_argument("--seeds", type=int, default=10)
    p = sub.add_parser("preview")
    p.add_argument("--seeds", type=int, default=6)
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "img" / "shape-families.png")
    a = ap.parse_args()
    if a.cmd == "time":
        bench_time(a.seeds)
    else:
        preview(a.seeds, a.size, a.out)


if __name__ == "__main__":
    main()
