"""Figures of docs/rigs.md: for each rig preset, its light layout and one rendered frame (docs/img/rig-*.png).

    .venv/bin/python scripts/rig_figures.py                       # every rig preset, into docs/img/
    .venv/bin/python scripts/rig_figures.py near-field --size 64  # one preset, smaller frames

Each figure is one row: the light layout seen from the camera (left), then a frame of the preset rendered
small into a temporary directory -- its first, middle and last shot (a multiplexed shot of more than three
channels: the shot in display colours and its first, middle and last channel), all at one exposure --
and the ground-truth normal map.

Layout panel, camera frame (x right, y up, the camera looking down -z at the object):
- directional lights: the unit direction toward each light projected on the image plane, (x, y) =
  sin(slant) (cos tilt, sin tilt), inside the unit circle (the horizon, slant 90 deg); dotted rings at
  slant 30 and 60 deg.  Presets that draw new directions every frame (`sampling = "random"`) show three
  frames' draws, one marker each (circles: the rendered frame's).  The lights of the shots shown are
  numbered.
- point lights: each LED's position (x, y) in scene units, with the object's bounding circle (radius 1;
  every object fits in the unit sphere) and the LED plane's distance in the title.
Markers are coloured by the light's colour (white lights grey; spectral LEDs the colour of their peak).

The render uses the preset unchanged except for size: one shard of one frame (a swept preset: one per
condition), `--size` pixels square, `--spp` samples, whole frames stored.  diligent-rig needs
$MSPS_TEST_DATA (the DiLiGenT light file and the test meshes); without it that preset is skipped.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PRESETS = ("demo-rig", "classic-train", "diligent-rig", "near-field", "narrowband")


def overrides(size: int, spp: int) -> list[str]:
    return ["dataset.n_shards=1", "dataset.frames_per_shard=1", f"scene.camera.width={size}",
            f"scene.camera.height={size}", f"scene.integrator.spp={spp}", "dataset.storage.store_frames=true",
            "dataset.patches.size=16", "dataset.patches.stride=16", "dataset.patches.min_coverage=0.1"]


def render_frame(name: str, size: int, spp: int, tmp: Path):
    """The first whole frame (`RigFrame`) and the rig_json of `name` rendered small into `tmp`."""
    from msps_render.dataset import load_manifest
    from msps_render.dataset.reader import iter_rig_frames
    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.run import render_dataset

    cfg = load_config(name, overrides(size, spp))
    out = tmp / name
    render_dataset(cfg, out, workers=1, progress=False)
    m = load_manifest(out)
    first = m.shard_path(m.shards_of()[0].name)
    return next(iter_rig_frames(first)), cfg


def layouts(cfg, fr, frames: int = 3):
    """[(directions (N, 3), positions (N, 3) or None, colours (N, 3) in [0, 1])]: the rendered frame's
    true lights, then (presets that draw new directions every frame) `frames - 1` more draws of the rig."""
    from msps_render.scene.rig_layouts import sample_rig

    rc = cfg.scene.rig
    pos = np.asarray(fr.rig.positions) if fr.rig.has_point_lights else None
    out = [(np.asarray(fr.rig.light_dirs), pos, light_colours(rc, fr.light_rgb))]
    if rc.layout == "hemisphere" and rc.sampling == "random":
        for f in range(1, frames):
            lights, _ = sample_rig(rc, np.random.default_rng(f))
            D = np.array([l.direction for l in lights])
            P = np.array([[c * l.distance for c in l.direction] for l in lights]) if lights[0].kind == "point" else None
            out.append((D, P, light_colours(rc, np.array([l.rgb for l in lights]))))
    return out


def light_colours(rc, light_rgb) -> np.ndarray:
    """(N, 3) marker colours: RGB lights' hue (white as grey), spectral LEDs the colour of their peak."""
    if rc.led_peaks_nm is not None:
        from msps_render.spectral.spectra import display_weights, filter_sensitivities

        return np.clip(display_weights(filter_sensitivities([(p, rc.led_fwhm_nm) for p in rc.led_peaks_nm])) * 2.2,
                       0, 1)
    rgb = np.array(light_rgb, np.float64)
    rgb = rgb / np.maximum(rgb.max(axis=1, keepdims=True), 1e-12)
    grey = np.ptp(rgb, axis=1) < 1e-6
    rgb[grey] = 0.45
    return rgb


def draw_layout(ax, draws, shown=()) -> None:
    """The layout panel; the lights of the shots shown (`shown`, light indices) numbered."""
    markers = ("o", "^", "s")
    t = np.linspace(0, 2 * np.pi, 200)
    near = draws[0][1] is not None
    if near:
        P = draws[0][1]
        ax.plot(np.cos(t), np.sin(t), "k-", lw=1)
        ax.fill(np.cos(t), np.sin(t), color="0.9")
        for k, (_, P, c) in enumerate(draws):
            ax.scatter(P[:, 0], P[:, 1], s=18, c=c, marker=markers[k], edgecolors="k", linewidths=0.4)
        r = max(1.2, float(np.abs(P[:, :2]).max()) * 1.25)
        ax.set_xlim(-r, r)
        ax.set_ylim(-r, r)
        z = float(np.median(P[:, 2]))
        ax.set_title(f"{len(P)} point lights at z ~ {z:.3g}\n(x, y in scene units; grey: object)", fontsize=8)
        ax.set_xlabel("x", fontsize=7)
        ax.set_ylabel("y", fontsize=7)
        xy = P[:, :2]
    else:
        ax.plot(np.cos(t), np.sin(t), "k-", lw=1)
        for s in (30, 60):
            r = np.sin(np.radians(s))
            ax.plot(r * np.cos(t), r * np.sin(t), "k:", lw=0.6)
            ax.text(r * np.cos(0.8), r * np.sin(0.8), f"{s}\N{DEGREE SIGN}", fontsize=6, color="0.3")
        for k, (D, _, c) in enumerate(draws):
            ax.scatter(D[:, 0], D[:, 1], s=16, c=c, marker=markers[k], edgecolors="k", linewidths=0.4)
        ax.set_xlim(-1.08, 1.08)
        ax.set_ylim(-1.08, 1.08)
        what = f"{len(draws[0][0])} directional lights"
        if len(draws) > 1:
            what += f"\n(new draw every frame: {len(draws)} shown)"
        ax.set_title(what, fontsize=8)
        xy = draws[0][0][:, :2]
    for k in shown:
        ax.annotate(str(k), xy[k], xytext=(3, 3), textcoords="offset points", fontsize=7, color="C3",
                    weight="bold")
    ax.set_aspect("equal")
    ax.tick_params(labelsize=6)
    ax.axhline(0, color="0.8", lw=0.5, zorder=0)
    ax.axvline(0, color="0.8", lw=0.5, zorder=0)


def frame_views(fr) -> list[tuple[str, np.ndarray]]:
    """Captioned display images (linear RGB) of a frame's shots: `msps preview`'s views, plus the shot in
    display colours when its channels are shown one by one."""
    import json

    from msps_render.pipeline.preview import display_weights_of, rig_views

    w = display_weights_of(fr.rig_json)
    names = json.loads(fr.rig_json).get("channel_names", ())
    views = rig_views(fr.shots, fr.nominal, w, names)
    if fr.shots.shape[0] == 1 and fr.shots.shape[-1] > 3:
        views.insert(0, ("the one shot (display colours)", (fr.shots[0].astype(np.float64) @ w).astype(np.float32)))
    return views


def figure(name: str, fr, cfg, out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from msps_render.pipeline.preview import pick
    from msps_render.preview import normal_to_rgb8, srgb8

    views = frame_views(fr)
    n = 1 + len(views) + 1
    fig, axs = plt.subplots(1, n, figsize=(1.8 * n, 2.25), dpi=100,
                            gridspec_kw={"width_ratios": [1.25] + [1] * (n - 1)})
    shots = fr.rig.shot_list
    shown = sorted({shots[s][0] for s in pick(len(shots)) if len(shots[s]) == 1})
    draw_layout(axs[0], layouts(cfg, fr), shown)
    mask = fr.mask
    white = np.concatenate([v[mask] for _, v in views]) if mask.any() else np.ones(1)
    w = max(float(np.percentile(white, 98.0)), 1e-8)  # one exposure: a dim shot stays dim
    for ax, (cap, v) in zip(axs[1:], views):
        ax.imshow(srgb8(v / w), interpolation="nearest")
        ax.set_title(cap, fontsize=7)
    axs[-1].imshow(normal_to_rgb8(fr.normal, mask), interpolation="nearest")
    axs[-1].set_title("ground-truth normals", fontsize=7)
    for ax in axs[1:]:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(f"{name}: {fr.nominal.describe()}", fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 0.97), w_pad=0.4)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100, metadata={"Software": None})
    plt.close(fig)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("presets", nargs="*", default=list(PRESETS), help=f"rig presets (default: {' '.join(PRESETS)})")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "img", help="folder of rig-<preset>.png")
    ap.add_argument("--size", type=int, default=96, help="frame width and height (px)")
    ap.add_argument("--spp", type=int, default=8, help="samples per pixel")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="rig-figures-") as tmp:
        for name in a.presets:
            if name == "diligent-rig" and not os.environ.get("MSPS_TEST_DATA"):
                print(f"{name}: skipped (set MSPS_TEST_DATA to the folder holding diligent/ and meshes/)",
                      file=sys.stderr)
                continue
            fr, cfg = render_frame(name, a.size, a.spp, Path(tmp))
            p = figure(name, fr, cfg, a.out / f"rig-{name}.png")
            print(f"wrote {p} ({p.stat().st_size // 1024} KiB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
