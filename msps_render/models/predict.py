"""`msps predict`: one image through one method (a checkpoint or the baseline, and its steps) to a
normal map, its picture, a panel and, with a ground truth, the error.

The tiled whole-image prediction itself is `models/tiles.py` (`predict_image`, re-exported here)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from msps_render.atomic import save_array
from msps_render.calibration import Rig, geometry_warnings, load_calibration_file, parse_calibration
from msps_render.errors import InputError
from msps_render.io.images import read_image, write_png
from msps_render.io.normals import read_normal_map as read_normal_gt
from msps_render.models.runner import (LAMBERTIAN, NET, Method, checkpoint_predictor, default_checkpoint,  # noqa: F401
                                       Memo, label, lambertian_predictor, run, trace)
from msps_render.models.steps import DEFAULT_PHOTOS, STEPS, Steps
from msps_render.models.tiles import predict_image  # noqa: F401 (re-exported: callers import it from here)
from msps_render.preview import normal_to_rgb8
from msps_render.progress import Bar


def load_calibration(path: str | Path | None, light_dirs: str | None, crosstalk: str | None):
    """Light directions (3x3, rows toward the lights) and crosstalk (3x3) from a calibration JSON
    (schema: `msps_render.calibration`) and/or the --light-dirs/--crosstalk flags (which win)."""
    L, M = load_calibration_file(path) if path else parse_calibration({})
    if light_dirs or crosstalk:
        d = {}
        for key, text in (("light_dirs", light_dirs), ("crosstalk", crosstalk)):
            if text:
                try:
                    d[key] = json.loads(text)
                except json.JSONDecodeError as e:
                    raise InputError(f"--{key.replace('_', '-')}", f"not valid JSON ({e})") from None
        L2, M2 = parse_calibration({"light_dirs": d.get("light_dirs", L.tolist()),
                                    "crosstalk": d.get("crosstalk", M.tolist())},
                                   "--light-dirs/--crosstalk")
        L, M = L2, M2
    return L, M


def read_inputs(image_path: str | Path, mask_path: str | Path | None,
                linear: bool | None = None, warn=None) -> tuple[np.ndarray, np.ndarray]:
    """PNG keeps 16 bits (Pillow would truncate them) and is decoded by the rule `compose` uses too
    (`io.png16.PNG_RULE`; `linear` True/False forces it, `warn` hears a guess)."""
    if Path(image_path).suffix.lower() == ".png":
        from msps_render.compose import read_photo

        img = read_photo(Path(image_path), linear, warn).astype(np.float32)
    else:
        img = read_image(image_path)
    if img.shape[-1] == 4:  # RGBA: the alpha channel carries no radiance
        img = np.ascontiguousarray(img[..., :3])
    if img.shape[-1] != 3:
        raise InputError(image_path, f"expected a 3-channel RGB image, got {img.shape[-1]} channel(s)")
    if mask_path:
        mk = read_image(mask_path)[..., 0] > 0
        if mk.shape != img.shape[:2]:
            raise InputError(mask_path, f"mask is {mk.shape[1]}x{mk.shape[0]}, image is {img.shape[1]}x{img.shape[0]}")
    else:
        mk = img.sum(-1) > 0
    if not mk.any():  # else every output is blank, written without a word
        raise InputError(mask_path or image_path, "no pixel to predict: the mask is empty" if mask_path else
                         "no pixel to predict: no pixel has positive radiance (the default mask); pass --mask")
    return img, mk


LARGE_PIXELS = 512 * 512  # from this size on `msps predict` shows progress (steps, network passes, tiles)
OUT_SUFFIXES = (".npy", ".png")  # `--out x.png` and `--out x` both mean the stem x; other dots stay
PANEL_COL_IN, PANEL_H_IN, PANEL_CBAR_IN, PANEL_DPI = 3.0, 3.4, 0.7, 100  # panel layout (inches, dpi)
ERROR_MAX_DEG = 45.0  # top of the error map's colour scale (larger errors saturate)


def out_paths(out: str | Path) -> dict[str, Path]:
    """OUT.npy, OUT.png, OUT-panel.png, OUT-metrics.json: OUT is a stem whose dots are kept
    (`pred-v0.1` -> `pred-v0.1.npy`; `Path.with_suffix` would write `pred-v0.npy`)."""
    s = str(out)
    if Path(s).suffix.lower() in OUT_SUFFIXES:
        s = s[:-len(Path(s).suffix)]
    return {"npy": Path(s + ".npy"), "png": Path(s + ".png"), "panel": Path(s + "-panel.png"),
            "metrics": Path(s + "-metrics.json")}


def write_panel(path: Path, image: np.ndarray, mask: np.ndarray, normal: np.ndarray, title: str,
                gt: np.ndarray | None = None, err: np.ndarray | None = None) -> Path:
    """Input (tonemapped), predicted normals, and with a ground truth: it and the angular-error map
    with its colour bar.  Fixed size: PANEL_COL_IN per column (+ PANEL_CBAR_IN), PANEL_H_IN high."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from msps_render.preview import tonemap

    tiles = [(tonemap(image, mask), "input (tonemapped)"), (normal_to_rgb8(normal, mask), "prediction")]
    if gt is not None:
        tiles.append((normal_to_rgb8(gt, np.linalg.norm(gt, axis=-1) > 0), "ground truth"))
    cols = len(tiles) + (err is not None)
    width = PANEL_COL_IN * cols + (PANEL_CBAR_IN if err is not None else 0.0)
    fig = plt.figure(figsize=(width, PANEL_H_IN), dpi=PANEL_DPI)
    ratios = [PANEL_COL_IN] * cols + ([PANEL_CBAR_IN * 0.25] if err is not None else [])
    gs = fig.add_gridspec(1, len(ratios), width_ratios=ratios, left=0.01, right=0.93 if err is not None else 0.99,
                          top=0.80, bottom=0.03, wspace=0.06)
    for i, (t, label) in enumerate(tiles):
        ax = fig.add_subplot(gs[0, i])
        ax.imshow(t, interpolation="nearest")
        ax.set_title(label, fontsize=9)
        ax.axis("off")
    if err is not None:
        ax = fig.add_subplot(gs[0, len(tiles)])
        bg = np.ones(mask.shape + (3,))
        bg[mask & ~np.isfinite(err)] = 0.6  # in the mask but no ground truth: grey, left out
        ax.imshow(bg, interpolation="nearest")
        cmap = matplotlib.colormaps["viridis"].with_extremes(bad=(0, 0, 0, 0))
        im = ax.imshow(np.ma.masked_invalid(err), cmap=cmap, vmin=0, vmax=ERROR_MAX_DEG, interpolation="nearest")
        ax.set_title("angular error" + (" (grey: no truth)" if (bg[..., 0] == 0.6).any() else ""), fontsize=9)
        ax.axis("off")
        cb = fig.colorbar(im, cax=fig.add_subplot(gs[0, -1]), extend="max")
        cb.set_label("deg", fontsize=8)
        cb.ax.tick_params(labelsize=7)
    fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=PANEL_DPI)
    plt.close(fig)
    return path


def load_rig(calibration: str | Path | None = None, light_dirs: str | None = None,
             crosstalk: str | None = None) -> Rig:
    """The image's rig from --calibration / --light-dirs / --crosstalk; none given: the paper's, assumed."""
    L, M = load_calibration(calibration, light_dirs, crosstalk)  # validated either way
    return Rig(L, M, assumed=not (calibration or light_dirs or crosstalk))


def predict_method(kind: str = NET, checkpoint: str | Path | None = None, steps: Steps = DEFAULT_PHOTOS) -> Method:
    """`msps predict`'s one method: the checkpoint (default: the shipped one) or the baseline, and its steps."""
    if kind not in (NET, LAMBERTIAN):
        raise InputError("--method", f"unknown method '{kind}' (net or lambertian)")
    p = lambertian_predictor() if kind == LAMBERTIAN else checkpoint_predictor(checkpoint or default_checkpoint())
    return Method(p.name, p, steps.for_predictor(p.network) or steps)  # or: refused by its check, one line


def predict_main(image: str | Path, out: str | Path, method: Method | None = None, rig: Rig | None = None, *,
                 mask: str | Path | None = None, linear: bool | None = None, normal_gt: str | Path | None = None,
                 panel: bool = True, warn=None, progress: bool = False) -> list[Path]:
    """Write OUT.npy (H, W, 3 normals), OUT.png (visualisation) and OUT-panel.png (input, prediction;
    with `normal_gt` also the ground truth and the error map, and OUT-metrics.json with the MAE).

    `method` default: the shipped network with the default steps; `rig` default: the paper's, assumed.
    `warn(message)` (default: a 'warning: ...' line on stderr) hears when the paper's lights are assumed
    for lack of a calibration, and when the given lights differ from the geometry the network was
    trained for.  Every check runs before anything is written."""
    warn = warn or _warn_stderr
    method = method or predict_method()
    rig = rig or load_rig()
    p = method.predictor
    method.steps.check(p.network, rig)
    img, mk = read_inputs(image, mask, linear, warn)
    gt = read_normal_gt(normal_gt, img.shape[:2]) if normal_gt else None  # before any work: fail early
    if p.network and min(img.shape[:2]) < 40:
        raise InputError(image, f"image is {img.shape[1]}x{img.shape[0]}; the network needs at least 40x40")
    if rig.assumed and (not p.network or getattr(p.model, "needs_rig", False) or
                        any(STEPS[n].needs_rig for n in method.steps.names)):
        warn(f"no --calibration: assuming the paper's lights (slant 30 deg, tilts 0/120/240 deg, crosstalk "
             f"0.92/0.04) for {' and '.join(['the baseline' if not p.network else 'the network'] + list(method.steps.names))}")
    elif p.network and not rig.assumed:
        for w in geometry_warnings(rig.light_dirs, rig.crosstalk, p.train_lights):
            warn(w)
    with Bar(progress and mk.size >= LARGE_PIXELS) as bar:  # per step and network pass: large images take minutes
        state = run(method, img, mk, rig, Memo(bar.task(f"{Path(image).name}: {method.name}", None)))
    n = state.normals
    paths = out_paths(out)
    paths["npy"].parent.mkdir(parents=True, exist_ok=True)
    save_array(paths["npy"], n.astype(np.float32))
    files = [paths["npy"], write_png(paths["png"], normal_to_rgb8(n, mk))]
    title = f"{Path(image).name}: {label(method, state)}"
    err = None
    if gt is not None:
        from msps_render.models.metrics import angular_error_deg, error_stats

        g, valid = gt
        scored = mk & valid
        err = np.full(mk.shape, np.nan)
        err[scored] = angular_error_deg(n[scored], g[scored])
        stats = error_stats(err[scored])
        steps = trace(state)
        metrics = {"image": str(image), "normal_gt": str(normal_gt), "method": p.kind,
                   "checkpoint": p.info.get("checkpoint"), **stats, "steps": str(method.steps),
                   **{k: steps.get(k) for k in STEPS}, "n_mask_pixels": int(mk.sum()),
                   "n_left_out": int((mk & ~valid).sum())}
        paths["metrics"].write_text(json.dumps(metrics, indent=1))
        title += (f" — MAE {stats['mae_deg']:.2f}° over {stats['n_pixels']:,} px" if stats["n_pixels"]
                  else " — no pixel with both a mask and a ground-truth normal")
    if panel:
        files.append(write_panel(paths["panel"], img, mk, n, title, gt[0] if gt is not None else None, err))
    if gt is not None:
        files.append(paths["metrics"])
    return files


def _warn_stderr(msg: str) -> None:
    import sys

    print(f"warning: {msg}", file=sys.stderr)
