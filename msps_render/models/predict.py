"""Whole-image prediction: overlapping tiles through the network, blended; or the baseline.

The network sees 40x40 patches in training, so a whole image is cut into
overlapping tiles (stride 20 by default), each tile's normals are weighted by a
smooth window that favours tile centres (where the receptive field is
complete), summed, and renormalised.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from msps_render.atomic import save_array
from msps_render.calibration import geometry_warnings, load_calibration_file, parse_calibration
from msps_render.errors import InputError
from msps_render.io.images import read_image, write_png
from msps_render.models.baseline import lambertian_ps
from msps_render.patches import window_origins
from msps_render.preview import normal_to_rgb8
from msps_render.resources import data_dir


def _window(size: int) -> np.ndarray:
    w = np.hanning(size + 2)[1:-1]
    return np.outer(w, w).astype(np.float32) + 1e-3


def predict_image(model, image: np.ndarray, mask: np.ndarray, tile: int = 40, stride: int = 20,
                  batch: int = 64, rig: np.ndarray | None = None) -> np.ndarray:
    """Normals (H, W, 3) of an image (H, W, 3) with a dual-cue model; 0 outside the mask.
    `rig` = crosstalk @ light_dirs (3, 3): needed by a network with the Lambertian cue."""
    import torch

    rig_t = None if rig is None else torch.as_tensor(np.asarray(rig), dtype=torch.float32)
    H, W = mask.shape
    if H < tile or W < tile:
        raise ValueError(f"image {H}x{W} is smaller than the {tile}x{tile} tile")
    origins = window_origins(H, W, tile, stride)
    m = mask.astype(bool)
    keep = [(y, x) for y, x in origins if m[y:y + tile, x:x + tile].any()]
    acc = np.zeros((H, W, 3), np.float32)
    wsum = np.zeros((H, W), np.float32)
    win = _window(tile)
    model.eval()
    with torch.no_grad():
        for i in range(0, len(keep), batch):
            yx = keep[i:i + batch]
            x = np.stack([image[y:y + tile, x_:x_ + tile] for y, x_ in yx]).transpose(0, 3, 1, 2)
            mk = np.stack([m[y:y + tile, x_:x_ + tile] for y, x_ in yx])[:, None]
            pred, _ = model(torch.from_numpy(np.ascontiguousarray(x, np.float32)),
                            torch.from_numpy(mk.astype(np.float32)), rig_t)
            pred = pred.numpy().transpose(0, 2, 3, 1)
            for (y, x_), p in zip(yx, pred):
                acc[y:y + tile, x_:x_ + tile] += p * win[..., None]
                wsum[y:y + tile, x_:x_ + tile] += win
    n = acc / np.maximum(np.linalg.norm(acc, axis=-1, keepdims=True), 1e-12)
    n[~m] = 0.0
    return n


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
    return img, mk


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


def read_normal_gt(path: str | Path, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(unit normals (H, W, 3), valid (H, W)) of a ground-truth normal map.

    .npy: signed normals.  PNG (8/16 bit) and other images: (n+1)/2-encoded.  EXR/HDR: signed (as
    `msps` writes normal.exr) unless no value is negative, then (n+1)/2-encoded.  Zero normals (and,
    once decoded, vectors far from unit length: black or mid-grey backgrounds) are invalid."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "ground-truth normal map not found")
    suffix = p.suffix.lower()
    if suffix == ".npy":
        n = np.load(p).astype(np.float64)
    elif suffix == ".png":
        from msps_render.io.png16 import read_png

        a = read_png(p)
        n = a.astype(np.float64) / np.iinfo(a.dtype).max * 2.0 - 1.0 if a.ndim == 3 else a
    else:
        n = read_image(p).astype(np.float64)
        if suffix not in (".exr", ".hdr") or n[..., :3].min() >= 0:
            n = n * 2.0 - 1.0
    if n.ndim != 3 or n.shape[2] < 3:
        raise InputError(p, f"expected an (H, W, 3) normal map, got shape {list(n.shape)}")
    n = n[..., :3]
    if n.shape[:2] != tuple(shape):
        raise InputError(p, f"normal map is {n.shape[1]}x{n.shape[0]}, the image is {shape[1]}x{shape[0]}")
    n = np.where(np.isfinite(n).all(-1, keepdims=True), n, 0.0)
    length = np.linalg.norm(n, axis=-1)
    valid = (length > 0.5) & (length < 1.5)
    n = np.where(valid[..., None], n / np.maximum(length, 1e-12)[..., None], 0.0)
    return n, valid


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


def predict_main(image: str | Path, out: str | Path, checkpoint: str | Path | None = None,
                 method: str = "net", mask: str | Path | None = None, calibration: str | Path | None = None,
                 light_dirs: str | None = None, crosstalk: str | None = None, warn=None,
                 linear: bool | None = None, normal_gt: str | Path | None = None, panel: bool = True,
                 selfcal: bool = False, refine: bool = False, mirror: bool = False,
                 segments: bool = False, netcal: bool = False) -> list[Path]:
    """Write OUT.npy (H, W, 3 normals), OUT.png (visualisation) and OUT-panel.png (input, prediction;
    with `normal_gt` also the ground truth and the error map, and OUT-metrics.json with the MAE).

    `warn(message)` (default: a 'warning: ...' line on stderr) hears when the Lambertian path assumes
    the paper's lights for lack of a calibration, and when the given lights differ from the geometry
    the network was trained for (the network takes no light input)."""
    warn = warn or _warn_stderr
    if refine and method == "lambertian":
        raise InputError("--refine", "refines a network's normals; the Lambertian baseline has nothing to refine")
    if netcal and method == "lambertian":
        raise InputError("--netcal", "reads the colour off a network's normals; the Lambertian baseline "
                                     "explains every colour as a tilt (use --selfcal)")
    if netcal and segments:
        raise InputError("--netcal", "and --segments are two ways to divide out the albedo colour; give one")
    if mirror and method == "lambertian":
        raise InputError("--mirror", "averages a network's two predictions; the Lambertian baseline is already "
                                     "mirror-symmetric")
    img, mk = read_inputs(image, mask, linear, warn)
    gt = read_normal_gt(normal_gt, img.shape[:2]) if normal_gt else None  # before any work: fail early
    calibrated = bool(calibration or light_dirs or crosstalk)
    L, M = load_calibration(calibration, light_dirs, crosstalk)  # validated on both paths
    if mirror:
        from msps_render.models.symmetry import mirror_ensemble, require_mirror

        sym = require_mirror(L, M)  # before any work
    fit = sfit = nfit = None
    if selfcal or segments or netcal:
        from msps_render.models.selfcal import apply_colour_fit, fit_albedo_colour

        if not calibrated:
            flag = "--segments" if segments else "--netcal" if netcal else "--selfcal"
            warn(f"{flag} without --calibration: fitting the colour under the paper's lights")
        fit = fit_albedo_colour(img, mk, L, M)
        img_in = apply_colour_fit(img, fit)
        if segments:  # after the object-level fit: only objects it leaves alone are cut into colour regions
            from msps_render.models.segments import fit_segments

            sfit = fit_segments(img, mk, L, M, whole=fit)
            if sfit.applied:
                img_in = (img_in * sfit.scale).astype(img_in.dtype)
    else:
        img_in = img
    if method == "lambertian":
        if not calibrated:
            warn("no --calibration: assuming the paper's lights (slant 30 deg, tilts 0/120/240 deg, "
                 "crosstalk 0.92/0.04)")
        n = lambertian_ps(img_in, L, M, mk)
        label = "lambertian"
    else:
        from msps_render.models.checkpoint import load_checkpoint

        ck = checkpoint or default_checkpoint()
        model, _, ckd = load_checkpoint(ck)
        if calibrated:
            for w in geometry_warnings(L, M, ckd.get("train_lights")):
                warn(w)
        elif getattr(model, "needs_rig", False):
            warn("no --calibration: this network takes the lights; assuming the paper's (slant 30 deg, "
                 "tilts 0/120/240 deg, crosstalk 0.92/0.04)")
        if min(img.shape[:2]) < 40:
            raise InputError(image, f"image is {img.shape[1]}x{img.shape[0]}; the network needs at least 40x40")
        if mirror:
            net = lambda x: mirror_ensemble(lambda y, m: predict_image(model, y, m, rig=M @ L), x, mk, sym)  # noqa: E731
        else:
            net = lambda x: predict_image(model, x, mk, rig=M @ L)  # noqa: E731
        if netcal:
            from msps_render.models.netcal import calibrate

            n, img_in, nfit = calibrate(net, img_in, mk, M @ L)
        else:
            n = net(img_in)
        label = f"net ({Path(ck).name})" + (" +mirror" if mirror else "")
        if refine:
            from msps_render.models.refine import refine_normals

            n, rstats = refine_normals(img_in, mk, n, L, M)
            label += f" +refine ({rstats.n_three + rstats.n_two:,} px)" if rstats.n_three + rstats.n_two \
                else " +refine (not one albedo: kept)"
    if fit is not None:
        label += " +selfcal " + ("x" + "/".join(f"{v:.2f}" for v in fit.scale) if fit.applied else "(grey kept)")
    if nfit is not None:
        label += " +netcal " + ("x" + "/".join(f"{v:.2f}" for v in nfit.scale) if nfit.applied else "(kept)")
    if sfit is not None:
        label += (f" +segments ({len(sfit.accepted)} regions)" if sfit.applied else " +segments (not applied)")
    paths = out_paths(out)
    paths["npy"].parent.mkdir(parents=True, exist_ok=True)
    save_array(paths["npy"], n.astype(np.float32))
    files = [paths["npy"], write_png(paths["png"], normal_to_rgb8(n, mk))]
    title = f"{Path(image).name}: {label}"
    err = None
    if gt is not None:
        from msps_render.models.metrics import angular_error_deg, error_stats

        g, valid = gt
        scored = mk & valid
        err = np.full(mk.shape, np.nan)
        err[scored] = angular_error_deg(n[scored], g[scored])
        stats = error_stats(err[scored])
        metrics = {"image": str(image), "normal_gt": str(normal_gt), "method": method,
                   "checkpoint": None if method == "lambertian" else str(ck), **stats,
                   "selfcal": None if fit is None else {"applied": fit.applied, "scale": fit.scale.tolist(),
                                                        "grey_rms": fit.grey_rms, "colour_rms": fit.colour_rms,
                                                        "share": fit.share, "grey_share": fit.grey_share},
                   "segments": None if sfit is None else {"applied": sfit.applied, "regions": len(sfit.accepted),
                                                          "object_share": sfit.object_share,
                                                          "reason": sfit.reason},
                   "netcal": None if nfit is None else {"applied": nfit.applied, "scale": nfit.scale.tolist(),
                                                        "agree": nfit.agree, "n_pixels": nfit.n_pixels},
                   "refine": None if not refine else {"n_three": rstats.n_three, "n_two": rstats.n_two,
                                                      "rho": rstats.albedo.rho, "uniform": rstats.albedo.uniform},
                   "n_mask_pixels": int(mk.sum()), "n_left_out": int((mk & ~valid).sum())}
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


def default_checkpoint() -> Path:
    """The small checkpoint shipped in models/ (trained by docs/reproducing.md)."""
    p = data_dir("models") / "dualcue-cpu.pt"
    if not p.is_file():
        raise InputError(p, "no shipped checkpoint; pass --checkpoint")
    return p
