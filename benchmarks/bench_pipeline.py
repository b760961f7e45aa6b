"""Dataset pipeline efficiency and throughput.

Usage: .venv/bin/python benchmarks/bench_pipeline.py [--shards 6] [--preset paper-train] [--out /tmp/bench-pipe]

In one run:
1. `msps render` (render_dataset) of the first N shards of the preset, with
   (workers=1, threads=2) and (workers=2, threads=1): wall time, patches/s,
   and the projected time for the paper's 1.3e5 + 1.44e4 patches.
2. The same scenes rendered serially with bare `mi.render` (2 threads): the
   scene is loaded outside the timer and only the `mi.render` calls (one per
   light, exactly the work the pipeline asks Mitsuba for) are summed.
   Efficiency = sum of bare render times / pipeline wall time.
3. Storage: bytes per patch for lzf / gzip / none, and the error of float16
   storage (normals in degrees, radiance relative).
"""
from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import h5py
import numpy as np

from msps_render.dataset import schema as K  # the shard's HDF5 keys
from msps_render.pipeline.config import load_config
from msps_render.pipeline.run import render_dataset


def bare_render_seconds(root: Path, variant: str, threads: int) -> tuple[float, int]:
    import mitsuba as mi

    from msps_render.render.scene_dict import build_scene_dict
    from msps_render.render.variant import activate
    from msps_render.scene.spec import SceneSpec

    activate(variant, threads)
    total, n = 0.0, 0
    for p in sorted((root / "shards").glob("shard-*.h5")):
        with h5py.File(p, "r") as h:
            specs = [SceneSpec.model_validate_json(s) for s in h[K.FRAME_SCENE_JSON].asstr()[()]]
        for spec in specs:
            scene = mi.load_dict(build_scene_dict(spec, mi))
            params = mi.traverse(scene)
            names = [f"light{k}" for k in range(len(spec.lights))]
            for on in names:
                for k in names:
                    params[f"{k}.sampling_weight"] = 1.0 if k == on else 0.0
                params.update()
                t = time.perf_counter()
                img = mi.render(scene, spp=spec.integrator.spp, seed=spec.integrator.seed)
                np.array(img)  # force evaluation
                total += time.perf_counter() - t
            n += 1
    return total, n


def storage_table(root: Path) -> list[tuple[str, float]]:
    from msps_render.dataset import SHARD_DIR, ShardContent, read_patch_rows, write_shard

    p = sorted((root / SHARD_DIR).glob("shard-*.h5"))[0]
    pat, fi = read_patch_rows(p)
    rows = []
    tmp = root.parent / "storage-test"
    tmp.mkdir(exist_ok=True)
    for comp in ("lzf", "gzip", "none"):
        for dt in ("float16", "float32"):
            out = tmp / f"s-{comp}-{dt}.h5"
            t = time.perf_counter()
            write_shard(out, ShardContent(pat, fi, []), comp, dt, dt)
            w = time.perf_counter() - t
            rows.append((f"{comp}/{dt}", out.stat().st_size / len(pat), w))
    shutil.rmtree(tmp)
    return rows


def float16_error(root: Path) -> dict:
    """Re-render one frame in float32 and compare with what float16 storage keeps."""
    from msps_render.render import render_frame
    from msps_render.scene.spec import SceneSpec

    p = sorted((root / "shards").glob("shard-*.h5"))[0]
    with h5py.File(p, "r") as h:
        spec = SceneSpec.model_validate_json(h[K.FRAME_SCENE_JSON].asstr()[0])
    f = render_frame(spec)
    n32 = f.normal[f.mask]
    n16 = n32.astype(np.float16).astype(np.float32)
    cos = (n32 * n16).sum(-1) / np.linalg.norm(n16, axis=-1)
    ang = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    i32 = f.image[f.mask]
    i16 = i32.astype(np.float16).astype(np.float32)
    rel = np.abs(i16 - i32)[i32 > 1e-4] / i32[i32 > 1e-4]
    return {"normal_deg_mean": float(ang.mean()), "normal_deg_max": float(ang.max()),
            "unit_norm_dev_max": float(np.abs(np.linalg.norm(n16, axis=-1) - 1).max()),
            "image_rel_mean": float(rel.mean()), "image_rel_max": float(rel.max())}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="paper-train")
    ap.add_argument("--shards", type=int, default=6)
    ap.add_argument("--out", default="/tmp/bench-pipe")
    a = ap.parse_args()
    from msps_render.render.variant import resolve_variant

    variant = resolve_variant("rgb")
    base = Path(a.out)
    shutil.rmtree(base, ignore_errors=True)
    cfg = load_config(a.preset, [f"dataset.n_shards={a.shards}"])
    results = {}
    for workers, threads in ((1, 2), (2, 1)):
        root = base / f"w{workers}"
        t = time.perf_counter()
        m = render_dataset(cfg, root, workers=workers, threads=threads, variant=variant, progress=False)
        wall = time.perf_counter() - t
        results[(workers, threads)] = (wall, m["n_patches"], m["n_frames"])
    bare, nframes = bare_render_seconds(base / "w1", variant, threads=2)
    print(f"preset {a.preset}, {a.shards} shards, variant {variant}")
    print("| run | wall (s) | frames | patches | patches/s | bare mi.render sum (s) | efficiency | "
          "projected 1.3e5+1.44e4 patches (min) |")
    print("|---|---|---|---|---|---|---|---|")
    for (w, th), (wall, npat, nfr) in results.items():
        rate = npat / wall
        print(f"| workers={w}, threads={th} | {wall:.1f} | {nfr} | {npat} | {rate:.0f} | {bare:.1f} | "
              f"{bare / wall:.2f} | {(1.3e5 + 1.44e4) / rate / 60:.1f} |")
    print()
    print("| storage | bytes/patch | write s |")
    print("|---|---|---|")
    for name, b, w in storage_table(base / "w1"):
        print(f"| {name} | {b:.0f} | {w:.3f} |")
    print()
    print("float16 storage error:", json.dumps(float16_error(base / "w1")))


if __name__ == "__main__":
    main()
