"""`msps bench-real --lights all|K`: classic photometric stereo on real captures with their own lights.

Real photographs are for VALIDATION ONLY (as `models.realbench`): read here to score methods, never
to train or tune one.  Each DiLiGenT-layout folder is read with all its photos (or the first K of
an even spread, `--lights K`), each photo with its calibrated direction and RGB intensity; methods
get the photos, the directions and the intensities (the rig: C[m, n] = intensity of light n in
channel m) and predict normals, scored against Normal_gt over the mask (unknown, zero normals left
out, as `realbench`).  The table's mean row is the ratio of means (one definition, as everywhere).

DiLiGenT's known quirks, handled the same way for every method and said in the report: bear's first
20 photos are corrupted and left out (as PS-FCN, CNN-PS and later work do); harvest's normal.txt is
flipped upside down, so ground truth is read from Normal_gt.mat (`realbench.read_normal_gt` prefers
it) -- never from normal.txt.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msps_render.errors import InputError
from msps_render.rig import Rig

FORMAT = "msps-realbench-lights-1"
QUIRKS = {"bear": "first 20 photos left out (corrupted in DiLiGenT; the same for every method)"}
BEAR_SKIP = 20


@dataclass
class Capture:
    name: str
    shots: np.ndarray  # (N, H, W, 3) float32 linear
    rig: Rig  # directions (N, 3), C (3, N) = intensities transposed, sequential
    mask: np.ndarray
    normal_gt: np.ndarray
    valid: np.ndarray
    used: list[int]  # 1-based rows of light_directions.txt
    note: str = ""


def spread(light_dirs: np.ndarray, k: int) -> np.ndarray:
    """k indices spread evenly over the lights (farthest-point order from the one nearest the view axis):
    a fixed, reproducible subset, not a random one."""
    L = np.asarray(light_dirs, np.float64)
    chosen = [int(np.argmax(L[:, 2]))]
    d = np.full(len(L), np.inf)
    while len(chosen) < k:
        d = np.minimum(d, np.arccos(np.clip(L @ L[chosen[-1]], -1, 1)))
        chosen.append(int(np.argmax(d)))
    return np.sort(np.array(chosen))


def load_capture(folder: str | Path, lights: str | int = "all", name: str | None = None,
                 need_truth: bool = True) -> Capture:
    """A DiLiGenT-layout folder with its lights (one line naming the file on any problem).  `need_truth`
    False (`msps predict` on a folder): mask.png optional (else the pixels any photo lights), no Normal_gt."""
    from msps_render.compose import read_capture, read_mask, read_photo
    from msps_render.models.realbench import ZERO_NORMAL_NORM, object_name, read_normal_gt

    cap = read_capture(folder)
    name = name or object_name(cap.root)
    if cap.mask_path is None and need_truth:
        raise InputError(cap.root / "mask.png", "missing: the benchmark scores the pixels inside the mask")
    keep = np.arange(len(cap.images))
    note = ""
    if name == "bear" and len(keep) > BEAR_SKIP:
        keep, note = keep[BEAR_SKIP:], QUIRKS["bear"]
    if lights != "all":
        k = int(lights)
        if not 3 <= k <= len(keep):
            raise InputError(cap.root, f"--lights {k}: the capture has {len(keep)} usable lights (need 3..{len(keep)})")
        keep = keep[spread(cap.light_dirs[keep], k)]
    for i in keep:
        if not cap.images[i].is_file():
            raise InputError(cap.images[i], "image file not found (listed in filenames.txt)")
    shots = np.stack([read_photo(cap.images[i], radiometric=cap.radiometric) for i in keep]).astype(np.float32)
    mask = read_mask(cap.mask_path, shots.shape[1:3]) if cap.mask_path else (shots > 0).any(axis=(0, 3))
    shots *= mask[None, ..., None]
    if need_truth:
        gt, _ = read_normal_gt(cap.root, mask.shape)
        valid = mask & (np.linalg.norm(gt, axis=-1) >= ZERO_NORMAL_NORM)
    else:
        gt, valid = np.zeros(mask.shape + (3,)), np.zeros(mask.shape, bool)
    rig = Rig(cap.light_dirs[keep], cap.intensities[keep].T, shots=tuple((j,) for j in range(len(keep))))
    return Capture(name, shots, rig, mask, gt, valid, [int(i) + 1 for i in keep], note)


def _methods(checkpoints) -> list[tuple[str, str, object]]:
    """(name, what, normals(capture)) per method: each checkpoint, then calibrated least squares (the baseline)."""
    from msps_render.models.baseline import lambertian_ps_rig
    from msps_render.models.runner import classic_predictors

    out = [(p.name, p.info["checkpoint"], lambda c, m=p.model: m.normals(c.shots, c.rig.light_dirs,
                                                                          np.asarray(c.rig.crosstalk).T, c.mask))
           for p in classic_predictors(checkpoints, default=True)]
    out.append(("lambertian", "calibrated least squares over every photo (Woodham)",
                lambda c: lambertian_ps_rig(c.shots, c.rig, c.mask)))
    return out


def run_bench_real_lights(folders, out: str | Path, checkpoints=(), lights: str | int = "all",
                          progress: bool = False) -> dict:
    """Score every checkpoint (classic networks) and the baseline on every capture; write results.json and
    results.md into OUT (new or empty; all-or-nothing)."""
    from msps_render.io.staging import check_new_out, staged_dir
    from msps_render.models.realbench import VALIDATION_NOTE, capture_names
    from msps_render.progress import Bar

    out = Path(out)
    check_new_out(out)
    folders, names = capture_names(folders)
    methods = _methods(checkpoints)  # every checkpoint loads before any photo is read
    from msps_render.compose import read_capture

    for f in folders:  # every folder validated before any work
        read_capture(f)
    per: dict[str, dict] = {}
    with Bar(progress) as bar:
        task = bar.task("objects", len(folders))
        for f, n in zip(folders, names):
            c = load_capture(f, lights, n)
            row = {"lights": len(c.used), "pixels": int(c.valid.sum()), "note": c.note}
            for mname, _, fn in methods:
                nrm = fn(c)
                cos = np.clip((nrm[c.valid] * c.normal_gt[c.valid]).sum(-1) /
                              np.maximum(np.linalg.norm(c.normal_gt[c.valid], axis=-1), 1e-12), -1, 1)
                row[mname] = float(np.degrees(np.arccos(cos)).mean())
            per[n] = row
            if task:
                task.advance()
    mnames = [n for n, _, _ in methods]
    mean = {m: float(np.mean([per[o][m] for o in per])) for m in mnames}
    summary = {"format": FORMAT, "note": VALIDATION_NOTE, "lights": str(lights), "objects": per, "mean_deg": mean,
               "ratio_of_means_to_lambertian": {m: mean[m] / mean["lambertian"] for m in mnames},
               "quirks": {o: per[o]["note"] for o in per if per[o]["note"]},
               "methods": {n: what for n, what, _ in methods}}
    with staged_dir(out) as stage:
        (stage / "results.json").write_text(json.dumps(summary, indent=1) + "\n")
        (stage / "results.md").write_text("\n".join(table_lines(summary)) + "\n")
    summary["files"] = [str(out / "results.json"), str(out / "results.md")]
    return summary


def table_lines(s: dict) -> list[str]:
    ms = list(s["mean_deg"])
    L = [f"Real captures, {s['lights']} lights per object; mean angular error (deg) over the mask; "
         "mean row: mean over objects; ratio: ratio of means to lambertian", "",
         "| object | lights | " + " | ".join(ms) + " |", "|---|---:|" + "---:|" * len(ms)]
    for o, r in s["objects"].items():
        L.append(f"| {o} | {r['lights']} | " + " | ".join(f"{r[m]:.2f}" for m in ms) + " |")
    L.append("| **mean** | | " + " | ".join(f"{s['mean_deg'][m]:.2f}" for m in ms) + " |")
    L.append("| ratio | | " + " | ".join(f"{s['ratio_of_means_to_lambertian'][m]:.3f}" for m in ms) + " |")
    for o, q in s["quirks"].items():
        L.append(f"\n{o}: {q}")
    L.append(f"\n{s['note']}")
    return L


def predict_folder(folder: str | Path, out: str | Path, checkpoint: str | Path | None = None,
                   method: str = "net", lights: str | int = "all") -> list[Path]:
    """`msps predict CAPTURE_DIR`: normals from a folder of per-light photos with their lights (DiLiGenT
    layout; mask.png optional): the classic network (default: models/classic-cpu.pt) or calibrated least
    squares.  Writes OUT.npy (H, W, 3) and OUT.png; every check runs before anything is written."""
    from msps_render.atomic import save_array
    from msps_render.io.images import write_png
    from msps_render.models.baseline import lambertian_ps_rig
    from msps_render.models.classic import load_classic
    from msps_render.models.predict import out_paths
    from msps_render.preview import normal_to_rgb8
    from msps_render.models.runner import default_classic_checkpoint

    if method not in ("net", "lambertian"):
        raise InputError("--method", f"unknown method '{method}' (net or lambertian)")
    model = load_classic(checkpoint or default_classic_checkpoint()) if method == "net" else None
    c = load_capture(folder, lights, need_truth=False)
    n = (model.normals(c.shots, c.rig.light_dirs, np.asarray(c.rig.crosstalk).T, c.mask) if model is not None
         else lambertian_ps_rig(c.shots, c.rig, c.mask))
    paths = out_paths(out)
    paths["npy"].parent.mkdir(parents=True, exist_ok=True)
    save_array(paths["npy"], n.astype(np.float32))
    return [paths["npy"], write_png(paths["png"], normal_to_rgb8(n, c.mask))]
