"""`msps bench-real`: checkpoints and calibrated Lambertian PS scored on real captures (DiLiGenT layout).

Real photographs are for VALIDATION ONLY: this module reads them to measure a
trained network against ground truth, never to train or tune one.

Each capture folder (`<object>PNG/`: one photo per white light, `filenames.txt`,
`light_directions.txt`, `light_intensities.txt`, `mask.png`, `Normal_gt.mat` or
`Normal_gt.png`) becomes one pseudo-multispectral image exactly as `msps compose`
makes it (`msps_render.compose.compose_arrays`: the three front lights nearest
the rig's layout, each photo divided by its light's intensity, mixed through
the crosstalk matrix, 0 outside the mask).  Every method predicts normals for
it; the score is the angle to the ground-truth normal over the mask's pixels,
leaving out pixels whose ground-truth normal is the zero vector (DiLiGenT marks
unknown normals so) and counting them.

`load_real_object` -> `RealObject`; `evaluate_real(objects, methods)` -> `RealBench`
(the JSON summary plus the normal and error maps); `write_report` writes
results.json, results.md, per-object PNGs and figure.png into a directory;
`run_bench_real` validates everything first and writes OUT all-or-nothing.
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from msps_render.calibration import Rig
from msps_render.errors import InputError
from msps_render.models.runner import (LAMBERTIAN, NET, Memo, Method, Predictor, lambertian_predictor,
                                       methods as make_methods, resolve_predictors, run)
from msps_render.models.steps import DEFAULT_PHOTOS, STEPS, Steps

FORMAT = "msps-realbench-1"
VALIDATION_NOTE = "real captures are for validation only: never train or tune on them"
ZERO_NORMAL_NORM = 1e-6  # a ground-truth normal shorter than this is unknown: the pixel is left out
ERROR_MAP_MAX_DEG = 45.0
ERROR_CMAP = "viridis"
GT_NAMES = ("Normal_gt.mat", "Normal_gt.png")


@dataclass
class RealObject:
    """One real capture composed for the benchmark (arrays in the camera frame: x right, y up, z to camera)."""

    name: str
    root: Path
    image: np.ndarray  # (H, W, 3) float32, linear, 0 outside the mask
    mask: np.ndarray  # (H, W) bool, from mask.png
    normal_gt: np.ndarray  # (H, W, 3) float64
    light_dirs: np.ndarray  # (3, 3) the chosen lights' measured directions
    crosstalk: np.ndarray  # (3, 3)
    images: list[str]  # the chosen capture files
    light_indices: list[int]  # their 1-based rows in light_directions.txt
    deviation_deg: list[float]  # each chosen light's angle to its target
    gt_source: str
    skipped: list[str] = field(default_factory=list)

    @property
    def valid(self) -> np.ndarray:
        """Mask pixels with a known (non-zero) ground-truth normal: the pixels scored."""
        return self.mask & (np.linalg.norm(self.normal_gt, axis=-1) >= ZERO_NORMAL_NORM)

    @property
    def left_out(self) -> int:
        return int(self.mask.sum() - self.valid.sum())

    @property
    def rig(self) -> Rig:
        return Rig(self.light_dirs, self.crosstalk)


@dataclass
class RealBench:
    summary: dict  # what results.json holds
    normals: dict[str, dict[str, np.ndarray]]  # object -> method -> (H, W, 3)
    errors: dict[str, dict[str, np.ndarray]]  # object -> method -> (H, W) degrees, NaN where not scored


def object_name(folder: str | Path) -> str:
    """'ballPNG' -> 'ball' (DiLiGenT's folder names); other names as they are."""
    n = Path(folder).resolve().name
    return n[:-3] if n.endswith("PNG") and len(n) > 3 else n


def read_normal_gt(root: Path, shape: tuple[int, int]) -> tuple[np.ndarray, Path]:
    """Ground-truth normals (H, W, 3) of a capture folder: Normal_gt.mat, else Normal_gt.png, read by the
    rule `msps predict --normal-gt` uses (`io.normals.read_normal_map`); no normal: the zero vector."""
    from msps_render.io.normals import read_normal_map

    mat, png = root / GT_NAMES[0], root / GT_NAMES[1]
    src = mat if mat.is_file() else png if png.is_file() else None
    if src is None:
        raise InputError(mat, "missing, and no Normal_gt.png either: the benchmark needs ground-truth normals")
    return read_normal_map(src, shape)[0], src


def parse_skip(skips, names: list[str]) -> dict[str, list[str]]:
    """--skip NAME (every object) or OBJECT/NAME (one object) -> {object: [file names]}."""
    out: dict[str, list[str]] = {n: [] for n in names}
    for s in skips or ():
        s = str(s).strip()
        if "/" in s:
            obj, file = s.rsplit("/", 1)
            obj = object_name(obj) if obj not in out else obj
            if obj not in out:
                raise InputError("--skip", f"'{s}': no capture folder of object '{obj}' was given "
                                           f"(objects: {', '.join(names)})")
            targets = [obj]
        else:
            file, targets = s, list(names)
        if not file:
            raise InputError("--skip", f"'{s}': no file name")
        for t in targets:
            if file not in out[t]:
                out[t].append(file)
    return out


def skip_images(cap, names: list[str]):
    """The capture without the named images (and their lights); (capture, 0-based rows kept)."""
    have = [p.name for p in cap.images]
    for n in names:
        if n not in have:
            listed = "filenames.txt" if (cap.root / "filenames.txt").is_file() else "the folder"
            raise InputError(cap.root / n, f"--skip names no image of this capture ({listed} lists "
                                           f"{len(have)}: {have[0]} ... {have[-1]})")
    keep = np.array([i for i, h in enumerate(have) if h not in names], dtype=int)
    return dataclasses.replace(cap, images=[cap.images[i] for i in keep], light_dirs=cap.light_dirs[keep],
                               intensities=cap.intensities[keep]), keep


def load_real_object(folder: str | Path, slant_deg: float = 30.0, tilts_deg=(0.0, 120.0, 240.0),
                     crosstalk: np.ndarray | None = None, skip=(), srgb: bool = False,
                     name: str | None = None) -> RealObject:
    """Validate a capture folder and compose its benchmark image (one line naming the file on any problem)."""
    from msps_render.calibration import PAPER_CROSSTALK
    from msps_render.compose import compose_arrays, read_capture

    M = PAPER_CROSSTALK.copy() if crosstalk is None else np.asarray(crosstalk, np.float64)
    cap = read_capture(folder)
    if cap.mask_path is None:
        raise InputError(cap.root / "mask.png", "missing: the benchmark scores the pixels inside the mask")
    cap, keep = skip_images(cap, list(skip))
    for p in cap.images:  # every listed photo, not only the three chosen: a broken capture folder is refused
        if not p.is_file():
            where = "listed in filenames.txt" if (cap.root / "filenames.txt").is_file() else "image"
            raise InputError(p, f"image file not found ({where})")
    comp = compose_arrays(cap, slant_deg, tilts_deg, M, linear=False if srgb else None)  # PNG_RULE unless --srgb
    gt, src = read_normal_gt(cap.root, comp.mask.shape)
    return RealObject(name=name or object_name(cap.root), root=cap.root, image=comp.image.astype(np.float32),
                      mask=comp.mask, normal_gt=gt, light_dirs=comp.light_dirs, crosstalk=M,
                      images=[cap.images[i].name for i in comp.indices],
                      light_indices=[int(keep[i]) + 1 for i in comp.indices],
                      deviation_deg=[float(d) for d in comp.deviation_deg], gt_source=src.name,
                      skipped=list(skip))


def lambertian_method() -> Method:
    """Calibrated Lambertian PS: the chosen lights' measured directions and the crosstalk matrix."""
    p = lambertian_predictor()
    return Method(p.name, p)


def warnings(p: Predictor, o: RealObject) -> list[str]:
    """Caveats to print before scoring a predictor on an object (a network away from its trained lights)."""
    from msps_render.calibration import geometry_warnings

    if not p.network:
        return []
    return [f"{p.name} on {o.name}: {w}" for w in geometry_warnings(o.light_dirs, o.crosstalk, p.train_lights)]


def _stats(err: np.ndarray) -> dict:
    return {"mae_deg": float(err.mean()), "median_deg": float(np.median(err)), "n_pixels": int(err.size)}


def check_sizes(objects: list[RealObject], methods: list[Method]) -> None:
    """A network needs at least one 40x40 tile: refuse smaller composed images before any work."""
    if any(m.predictor.network for m in methods):
        for o in objects:
            if min(o.mask.shape) < 40:
                raise InputError(o.root, f"composed image is {o.mask.shape[1]}x{o.mask.shape[0]}; "
                                         "the network needs at least 40x40")


def evaluate_real(objects: list[RealObject], methods: list[Method], warn=None, bar=None) -> RealBench:
    """Every method on every object: per object MAE/median over the scored pixels, the mean over objects
    (and of the per-object ratio to Lambertian), and the pixel-pooled statistics.  Methods on one object
    share work (`Memo`: one colour fit, one prediction per distinct input)."""
    from msps_render.models.metrics import angular_error_deg

    warn = warn or (lambda msg: None)
    check_sizes(objects, methods)
    per: dict = {}
    normals: dict = {}
    errors: dict = {}
    pooled: dict[str, list[np.ndarray]] = {m.name: [] for m in methods}
    for o in objects:
        v = o.valid
        rows = {}
        normals[o.name], errors[o.name] = {}, {}
        memo, warned = Memo(), set()
        for m in methods:
            if id(m.predictor) not in warned:
                warned.add(id(m.predictor))
                for w in warnings(m.predictor, o):
                    warn(w)
            n = np.asarray(run(m, o.image, o.mask, o.rig, memo).normals, np.float64)
            e = np.full(o.mask.shape, np.nan)
            e[v] = angular_error_deg(n[v], o.normal_gt[v])
            normals[o.name][m.name], errors[o.name][m.name] = n, e
            rows[m.name] = _stats(e[v])
            pooled[m.name].append(e[v])
        if bar:
            bar.advance()
        if LAMBERTIAN in rows:
            for k, r in rows.items():
                r["ratio_to_lambertian"] = r["mae_deg"] / max(rows[LAMBERTIAN]["mae_deg"], 1e-12)
        per[o.name] = {"folder": str(o.root.resolve()), "images": o.images, "light_indices": o.light_indices,
                       "deviation_deg": o.deviation_deg, "light_dirs": np.asarray(o.light_dirs).tolist(),
                       "skipped": o.skipped, "ground_truth": o.gt_source, "size": [int(s) for s in o.mask.shape],
                       "n_mask": int(o.mask.sum()), "n_pixels": int(v.sum()), "left_out_zero_normal": o.left_out,
                       "methods": rows}
    mean, pool = {}, {}
    for m in methods:
        rs = [per[o.name]["methods"][m.name] for o in objects]
        mean[m.name] = {"mae_deg": float(np.mean([r["mae_deg"] for r in rs])),
                        "median_deg": float(np.mean([r["median_deg"] for r in rs]))}
        allerr = np.concatenate(pooled[m.name]) if pooled[m.name] else np.zeros(0)
        pool[m.name] = _stats(allerr) if allerr.size else {"n_pixels": 0}
    lam = mean.get(LAMBERTIAN, {}).get("mae_deg")
    for m in methods:  # one definition of "ratio" everywhere: a ratio of means (mean MAE / Lambertian's mean MAE)
        if lam and all("ratio_to_lambertian" in per[o.name]["methods"][m.name] for o in objects):
            mean[m.name]["ratio_to_lambertian"] = mean[m.name]["mae_deg"] / max(lam, 1e-12)
    summary = {"format": FORMAT, "note": VALIDATION_NOTE,
               "metric": "angular error (deg) over mask pixels with a non-zero ground-truth normal",
               "methods": {m.name: m.info for m in methods}, "objects": per,
               "mean": {**mean, "note": "mean over objects of each object's MAE and median; ratio to Lambertian: the "
                                       "ratio of means (this mean MAE / Lambertian's mean MAE)"},
               "pooled": {**pool, "note": "all scored pixels of all objects together"}}
    return RealBench(summary, normals, errors)


def error_rgb8(err: np.ndarray, vmax: float = ERROR_MAP_MAX_DEG) -> np.ndarray:
    """Angular error (H, W) -> uint8 RGB via the colormap over 0..vmax deg; NaN (not scored) white."""
    import matplotlib

    cmap = matplotlib.colormaps[ERROR_CMAP]
    e = np.asarray(err, np.float64)
    rgb = (cmap(np.clip(np.nan_to_num(e, nan=0.0) / vmax, 0.0, 1.0))[..., :3] * 255 + 0.5).astype(np.uint8)
    rgb[~np.isfinite(e)] = 255
    return rgb


def _table(s: dict, methods: list[str]) -> list[str]:
    others = [m for m in methods if m != LAMBERTIAN]
    head = ["object"] + [f"{m} MAE (median)" for m in methods]
    head += [f"{m} / Lambertian" for m in others if LAMBERTIAN in methods]
    head += ["pixels (left out)", "captures (deg off target)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, o in s["objects"].items():
        r = o["methods"]
        cells = [name] + [f"{r[m]['mae_deg']:.2f} ({r[m]['median_deg']:.2f})" for m in methods]
        cells += [f"{r[m]['ratio_to_lambertian']:.2f}" for m in others if LAMBERTIAN in methods]
        cells += [f"{o['n_pixels']} ({o['left_out_zero_normal']})",
                  ", ".join(f"{f} ({d:.1f})" for f, d in zip(o["images"], o["deviation_deg"]))]
        lines.append("| " + " | ".join(cells) + " |")
    mean, pool = s["mean"], s["pooled"]
    cells = ["**mean**"] + [f"**{mean[m]['mae_deg']:.2f}** ({mean[m]['median_deg']:.2f})" for m in methods]
    cells += [f"**{mean[m]['ratio_to_lambertian']:.2f}**" for m in others if LAMBERTIAN in methods]
    lines.append("| " + " | ".join(cells + ["", ""]) + " |")
    cells = ["pooled pixels"] + [f"{pool[m]['mae_deg']:.2f} ({pool[m]['median_deg']:.2f})" for m in methods]
    cells += [f"{pool[m]['mae_deg'] / pool[LAMBERTIAN]['mae_deg']:.2f}" for m in others if LAMBERTIAN in methods]
    lines.append("| " + " | ".join(cells + [str(pool[methods[0]]["n_pixels"]), ""]) + " |")
    return lines


def summary_table(bench: RealBench) -> list[str]:
    """The markdown table of results.md (also what the command prints)."""
    return _table(bench.summary, list(bench.summary["methods"]))


def write_report(bench: RealBench, objects: list[RealObject], out: Path, settings: dict | None = None) -> list[Path]:
    """results.json, results.md, <object>/{error,normal}_<method>.png and figure.png into the directory `out`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from msps_render.io.png16 import write_png
    from msps_render.preview import normal_to_rgb8, tonemap

    out = Path(out)
    s = {**bench.summary, "settings": settings or {}}
    methods = list(s["methods"])
    files = []
    (out / "results.json").write_text(json.dumps(s, indent=1) + "\n")
    st = settings or {}
    md = ["# Real-capture benchmark", "",
          f"{VALIDATION_NOTE[0].upper()}{VALIDATION_NOTE[1:]}.  Each object: the three captures nearest slant "
          f"{st.get('slant_deg', 30):g} deg, tilts {'/'.join(f'{t:g}' for t in st.get('tilts_deg', (0, 120, 240)))} "
          "deg, each divided by its light intensity and mixed through the crosstalk matrix (as `msps compose`). "
          "Angular error in degrees, MAE (median), over mask pixels with a non-zero ground-truth normal; "
          "'left out': mask pixels whose ground-truth normal is zero.  Mean: over objects (of the MAEs and "
          "medians); its ratio is the ratio of means (mean MAE / Lambertian's mean MAE); pooled: all scored "
          "pixels together.", ""]
    md += _table(s, methods)
    md += [""] + [f"- `{m}`: {', '.join(f'{k} {v}' for k, v in s['methods'][m].items())}" for m in methods] + [""]
    (out / "results.md").write_text("\n".join(md))
    files += [out / "results.json", out / "results.md"]
    grey = np.array([160, 160, 160], np.uint8)
    for o in objects:
        d = out / o.name
        d.mkdir()
        for m in methods:
            e = error_rgb8(bench.errors[o.name][m])
            e[o.mask & ~o.valid] = grey  # left out: inside the mask, unknown ground truth
            files.append(write_png(d / f"error_{m}.png", e, srgb=True))
            files.append(write_png(d / f"normal_{m}.png", normal_to_rgb8(bench.normals[o.name][m], o.mask)))
    # figure: rows = objects; input, ground truth, then per method its normal map and its error map
    ncol = 2 + 2 * len(methods)
    fig, axes = plt.subplots(len(objects), ncol, figsize=(1.9 * ncol + 0.9, 2.05 * len(objects) + 0.3),
                             squeeze=False)
    for r, o in enumerate(objects):
        row = axes[r]
        row[0].imshow(tonemap(o.image, o.mask))
        row[0].set_title(f"{o.name}: input", fontsize=8)
        row[1].imshow(normal_to_rgb8(o.normal_gt, o.mask))
        row[1].set_title("ground truth", fontsize=8)
        for j, m in enumerate(methods):
            mae = s["objects"][o.name]["methods"][m]["mae_deg"]
            row[2 + 2 * j].imshow(normal_to_rgb8(bench.normals[o.name][m], o.mask))
            row[2 + 2 * j].set_title(f"{m}: MAE {mae:.2f}°", fontsize=8)
            e = error_rgb8(bench.errors[o.name][m])
            e[o.mask & ~o.valid] = grey
            row[3 + 2 * j].imshow(e)
            row[3 + 2 * j].set_title(f"{m}: error", fontsize=8)
        for a in row:
            a.set_axis_off()
    sm = plt.cm.ScalarMappable(cmap=ERROR_CMAP, norm=matplotlib.colors.Normalize(0, ERROR_MAP_MAX_DEG))
    W = fig.get_figwidth()
    fig.tight_layout(rect=(0, 0, 1 - 0.9 / W, 0.97))  # room on the right for the colour bar and its label
    cax = fig.add_axes((1 - 0.8 / W, 0.15, 0.12 / W, 0.7))
    fig.colorbar(sm, cax=cax).set_label("angular error (deg)", fontsize=8)
    cax.tick_params(labelsize=7)
    fig.suptitle("real captures (validation only)", fontsize=9)
    fig.savefig(out / "figure.png", dpi=100)
    plt.close(fig)
    files.append(out / "figure.png")
    return files


def capture_names(folders) -> tuple[list[Path], list[str]]:
    """(folders, object names): at least one, names unique (one line naming the folder otherwise)."""
    folders = [Path(f) for f in folders]
    if not folders:
        raise InputError("CAPTURES", "give at least one capture folder")
    names = [object_name(f) for f in folders]
    for f, n in zip(folders, names):
        if names.count(n) > 1:
            raise InputError(f, f"object name '{n}' given twice (two folders with the same name)")
    return folders, names


def run_bench_real(folders, out: str | Path, checkpoints=(), columns: list[Steps] | None = None, *,
                   slant_deg: float = 30.0, tilts_deg=(0.0, 120.0, 240.0), crosstalk: np.ndarray | None = None,
                   skip=(), srgb: bool = False, warn=None, progress: bool = False) -> RealBench:
    """Validate OUT and every folder, load every checkpoint, evaluate every checkpoint and the baseline
    under every steps value in `columns` (default: `DEFAULT_PHOTOS`), then write OUT all-or-nothing."""
    from msps_render.calibration import PAPER_CROSSTALK
    from msps_render.io.staging import check_new_out, staged_dir
    from msps_render.progress import Bar

    out = Path(out)
    check_new_out(out)
    folders, names = capture_names(folders)
    M = PAPER_CROSSTALK.copy() if crosstalk is None else np.asarray(crosstalk, np.float64)
    skips = parse_skip(skip, names)
    columns = columns or [DEFAULT_PHOTOS]
    methods = make_methods(resolve_predictors(checkpoints, [NET, LAMBERTIAN]), columns)
    objects = [load_real_object(f, slant_deg, tilts_deg, M, skips[n], srgb, name=n) for f, n in zip(folders, names)]
    for c in columns:  # every step's needs, before any work (and any progress line)
        for o in objects:
            c.check(True, o.rig)
    check_sizes(objects, methods)
    with Bar(progress) as bar:
        bench = evaluate_real(objects, methods, warn, bar.task("objects", len(objects)))
    settings = {"slant_deg": float(slant_deg), "tilts_deg": [float(t) for t in tilts_deg],
                "crosstalk": M.tolist(), "srgb": bool(srgb), "skip": [str(s) for s in skip or ()],
                "steps": [str(c) for c in columns], **{n: any(n in c for c in columns) for n in STEPS}}
    with staged_dir(out) as stage:
        write_report(bench, objects, stage, settings)
    bench.summary["settings"] = settings
    return bench
