"""CUDA vs LLVM on the same frames: pixels within Monte-Carlo noise, ground truth to float tolerance.

A GPU machine often has no shared libLLVM (the H200 test machine has none), so the LLVM side is rendered
where it runs and carried over:

    .venv/bin/python benchmarks/gpu_check.py reference --out gpu-ref          # here (LLVM), ~1 min on 2 cores
    python3 benchmarks/gpu_check.py check --ref gpu-ref --out result.json     # on the GPU (cuda_ad_*)

`reference` draws one frame of each preset (`paper-train`, `train-colour`, `spectral-train`), renders it
with the LLVM variant at two integrator seeds (s, s+1), and saves the SceneSpecs and arrays.  `check`
renders the same specs with the CUDA variant at both seeds and reports, per preset:

- `noise_rms`: RMS(llvm[s] - llvm[s+1]) over object pixels -- the Monte-Carlo noise of one frame;
- `same_seed_rms`: RMS(cuda[s] - llvm[s]) -- both backends draw the same PCG32 streams, so this is rounding;
- `other_seed_rms`: RMS(cuda[s+1] - llvm[s]) -- should equal `noise_rms` (same noise, nothing extra);
- ratios to `noise_rms` (the issue's bar: <= 1.2) and the ground-truth differences (normal angle, mask,
  depth, albedo).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

PRESETS = {"paper-train": "rgb", "train-colour": "rgb", "spectral-train": "spectral"}
BACKEND_VARIANT = {("llvm", "rgb"): "llvm_ad_rgb", ("llvm", "spectral"): "llvm_ad_spectral",
                   ("cuda", "rgb"): "cuda_ad_rgb", ("cuda", "spectral"): "cuda_ad_spectral"}


def preset_spec(name: str, frame_seed: int = 7):
    from msps_render.scene.sample import load_scene_config, sample_scene

    cfg = load_scene_config(ROOT / "scenes" / f"{name}.toml")
    return sample_scene(cfg, np.random.default_rng(frame_seed), seed=frame_seed)


def with_seed(spec, seed: int):
    from msps_render.scene.spec import SceneSpec

    d = json.loads(spec.to_json())
    d["integrator"]["seed"] = seed
    return SceneSpec.from_json(json.dumps(d))


def arrays(frame) -> dict[str, np.ndarray]:
    out = {"image": frame.image, "normal": frame.normal, "mask": frame.mask, "depth": frame.depth}
    if frame.albedo is not None:
        out["albedo"] = frame.albedo
    return out


def render(spec, backend: str) -> tuple[dict, float]:
    from msps_render.render import render_frame

    variant = BACKEND_VARIANT[(backend, spec.mode)]
    t = time.perf_counter()
    f = render_frame(spec, variant=variant)
    return arrays(f), time.perf_counter() - t


def reference(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for name in PRESETS:
        spec = preset_spec(name)
        s = spec.integrator.seed
        (out / f"{name}.json").write_text(spec.to_json())
        for k, seed in (("a", s), ("b", s + 1)):
            a, dt = render(with_seed(spec, seed), "llvm")
            np.savez_compressed(out / f"{name}-{k}.npz", **a)
            print(f"{name} seed {seed}: llvm {dt:.2f} s")


def _rms(x: np.ndarray, y: np.ndarray, m: np.ndarray) -> float:
    return float(np.sqrt(np.mean((x[m] - y[m]) ** 2)))


def compare(ref_a: dict, ref_b: dict, cu_a: dict, cu_b: dict) -> dict:
    m = ref_a["mask"] & cu_a["mask"]
    noise = _rms(ref_a["image"], ref_b["image"], m)
    same = _rms(cu_a["image"], ref_a["image"], m)
    other = _rms(cu_b["image"], ref_a["image"], m)
    cos = np.clip((ref_a["normal"][m] * cu_a["normal"][m]).sum(-1), -1, 1)
    ang = np.degrees(np.arccos(cos))
    r = {"pixels": int(m.sum()), "mean_radiance": float(ref_a["image"][m].mean()),
         "noise_rms": noise, "same_seed_rms": same, "other_seed_rms": other,
         "same_seed_ratio": same / noise, "other_seed_ratio": other / noise,
         "total_radiance_ratio": float(cu_a["image"][m].sum() / ref_a["image"][m].sum()),
         "mask_disagree": float((ref_a["mask"] != cu_a["mask"]).mean()),
         "normal_deg_p99": float(np.percentile(ang, 99)), "normal_deg_max": float(ang.max()),
         "depth_max_rel": float(np.max(np.abs(ref_a["depth"][m] - cu_a["depth"][m])
                                       / np.maximum(np.abs(ref_a["depth"][m]), 1e-6)))}
    if "albedo" in ref_a and "albedo" in cu_a:
        r["albedo_max_abs"] = float(np.abs(ref_a["albedo"][m] - cu_a["albedo"][m]).max())
    return r


def check(ref: Path, out: Path) -> int:
    from msps_render.scene.spec import SceneSpec

    results = {}
    for name in PRESETS:
        spec = SceneSpec.from_json((ref / f"{name}.json").read_text())
        s = spec.integrator.seed
        ra, rb = (dict(np.load(ref / f"{name}-{k}.npz")) for k in "ab")
        try:
            render(with_seed(spec, s), "cuda")  # first render of a variant compiles its kernels: not timed
            ca, dt = render(with_seed(spec, s), "cuda")
            cb, _ = render(with_seed(spec, s + 1), "cuda")
        except Exception as e:  # one preset's failure must not hide the others' results
            results[name] = {"error": f"{type(e).__name__}: {e}"}
            continue
        results[name] = {**compare(ra, rb, ca, cb), "cuda_frame_s_warm": dt}
        print(name, json.dumps(results[name]))
    out.write_text(json.dumps(results, indent=1))
    ok = all("error" not in r and r["same_seed_ratio"] <= 1.2 and r["other_seed_ratio"] <= 1.2
             and r["normal_deg_p99"] < 0.1 for r in results.values())
    print("PASS" if ok else "FAIL", "(CUDA within Monte-Carlo noise of LLVM, ground truth equal)")
    return 0 if ok else 1


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("reference")
    r.add_argument("--out", type=Path, required=True)
    c = sub.add_parser("check")
    c.add_argument("--ref", type=Path, required=True)
    c.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    if a.cmd == "reference":
        reference(a.out)
        return 0
    return check(a.ref, a.out)


if __name__ == "__main__":
    raise SystemExit(main())
