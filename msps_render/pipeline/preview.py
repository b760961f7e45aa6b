"""Contact sheet of a dataset: labelled samples (image | normal map | mask) plus distribution plots.

Each sample is one cell: three `tile` x `tile` px tiles side by side (nearest-neighbour
upscaled, aspect kept) over a label band naming the shard and frame (and the patch origin
for patch samples), the shape kind and name, the materials and the sweep condition.
The sheet is drawn with Pillow (the histograms with matplotlib) and saved without
metadata, so the same dataset gives the same PNG bytes.

Rig datasets (format-2 shards, docs/rigs.md): a sample has S images of M channels, so its
cell shows up to three of its shots (first, middle, last; one multiplexed shot of more than
three channels: its first, middle and last channel) at one common exposure, each captioned,
then the normal map and the mask; the label band adds the rig (`Rig.describe` of the
nominal rig).  An RGB rig's channels are shown through their weights on R, G, B, a spectral
rig's through the colour of each channel's sensitivity (`spectral.display_weights`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from msps_render.atomic import atomic_write
from msps_render.dataset import SHARD_DIR, read_frame_table, read_manifest
from msps_render.dataset.samples import Sample, shard_samples
from msps_render.preview import normal_to_rgb8, srgb8, tonemap

PAD = 8  # around cells
GAP = 4  # between the tiles of a cell
HEADER = 30  # title band
LINE = 16  # label line height
LABEL_LINES = 4
LABEL_H = LABEL_LINES * LINE + 6
PLOTS_H = 240  # distribution plots band
FONT_SIZE = 13


@dataclass(frozen=True)
class Layout:
    """Where everything goes on the sheet (pixels)."""

    n: int
    tile: int
    cols: int
    tiles: int = 3  # tiles per cell: image (rig datasets: up to three shots), normal map, mask
    lines: int = LABEL_LINES  # label lines per cell

    @property
    def rows(self) -> int:
        return -(-self.n // self.cols) if self.n else 0

    @property
    def cell_w(self) -> int:
        return self.tiles * self.tile + (self.tiles - 1) * GAP

    @property
    def label_h(self) -> int:
        return self.lines * LINE + 6

    @property
    def cell_h(self) -> int:
        return self.tile + self.label_h

    @property
    def width(self) -> int:
        return PAD + self.cols * (self.cell_w + PAD)

    @property
    def height(self) -> int:
        return HEADER + self.rows * (self.cell_h + PAD) + PLOTS_H + PAD

    def cell(self, k: int) -> tuple[int, int]:
        """Top-left corner of cell k."""
        r, c = divmod(k, self.cols)
        return PAD + c * (self.cell_w + PAD), HEADER + r * (self.cell_h + PAD)

    def tile_box(self, k: int, j: int) -> tuple[int, int, int, int]:
        """(x0, y0, x1, y1) of tile j (0 image, 1 normal, 2 mask; rig datasets: the shots, then normal
        and mask) of cell k."""
        x, y = self.cell(k)
        x += j * (self.tile + GAP)
        return x, y, x + self.tile, y + self.tile

    def label_box(self, k: int) -> tuple[int, int, int, int]:
        x, y = self.cell(k)
        return x, y + self.tile, x + self.cell_w, y + self.cell_h


def layout(n_samples: int, tile: int = 160, cols: int = 2, tiles: int = 3, lines: int = LABEL_LINES) -> Layout:
    return Layout(n=n_samples, tile=tile, cols=max(1, min(cols, n_samples or 1)), tiles=tiles, lines=lines)


def _font(size: int = FONT_SIZE):
    try:
        return ImageFont.load_default(size=size)  # Pillow >= 10.1: scalable built-in font
    except TypeError:  # pragma: no cover - older Pillow: the fixed bitmap font
        return ImageFont.load_default()


def _fit(text: str, font, width: int) -> str:
    if font.getlength(text) <= width:
        return text
    while text and font.getlength(text + "...") > width:
        text = text[:-1]
    return text + "..."


def label_lines(s: Sample) -> list[str]:
    where = f"{s.shard} frame {s.frame}" + (f", patch at y={s.yx[0]} x={s.yx[1]}" if s.yx else " (whole frame)")
    shape = s.shape_kind if s.object in ("", s.shape_kind) else f"{s.shape_kind} {s.object}"
    return [where, f"shape: {shape}", f"materials: {', '.join(s.materials) or '-'}",
            f"condition: {s.condition or '- (no sweep)'}"]


def _tile(pic: np.ndarray, tile: int):
    """uint8 HxW(x3) -> PIL image fitted into tile x tile (nearest neighbour, aspect kept)."""
    im = Image.fromarray(pic)
    h, w = pic.shape[:2]
    s = tile / max(h, w)
    return im.resize((max(1, round(w * s)), max(1, round(h * s))), Image.NEAREST)


def _plots(width: int, slants, mats, cover, slant_title: str | None = None) -> np.ndarray:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dpi = 80
    fig = plt.figure(figsize=(width / dpi, PLOTS_H / dpi), dpi=dpi)
    axs = fig.subplots(1, 3)
    axs[0].hist(slants, bins=20, color="C0")
    axs[0].set_title(slant_title or "slant (deg) per frame", fontsize=9)
    u, c = np.unique(mats, return_counts=True) if mats else ([], [])
    axs[1].barh(list(u)[:15], list(c)[:15], color="C1")
    axs[1].set_title("materials", fontsize=9)
    axs[1].tick_params(axis="y", labelsize=6)
    axs[2].hist(cover, bins=20, range=(0, 1), color="C2")
    axs[2].set_title(f"patch mask coverage ({len(cover)} patches)", fontsize=9)
    fig.tight_layout()
    fig.canvas.draw()
    rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return rgb


def sample_quota(names: list[str], condition_of: dict[str, str], n: int) -> dict[str, int]:
    """{shard: samples to take}: `n` (at least one per condition) dealt to the shards with the
    conditions interleaved, so every condition is shown, the last one (e.g. the strongest
    environment light: plans are condition-major) as much as the first."""
    by_cond: dict[str, list[str]] = {}
    for name in names:
        by_cond.setdefault(condition_of.get(name, ""), []).append(name)
    order = [g[i] for i in range(max(map(len, by_cond.values()), default=0)) for g in by_cond.values() if i < len(g)]
    n = max(n, len(by_cond))
    S = max(1, len(order))
    return {name: n // S + (1 if i < n % S else 0) for i, name in enumerate(order)}


# ------------------------------------------------------------------ rig datasets (format 2)
@dataclass
class RigSample:
    """A sample of a rig shard: the labelled sample (its `image` the first view, for eyes only) and the
    views the cell shows, each (caption, H x W x 3 linear display radiance)."""

    sample: Sample
    views: list[tuple[str, np.ndarray]]
    rig: str  # `Rig.describe()` of the nominal rig


def pick(count: int, k: int = 3) -> list[int]:
    """Up to `k` indices of range(count): first, middle, last (each once)."""
    return sorted({0, count // 2, count - 1})[:k] if count > 0 else []


def display_weights_of(rig_json: str) -> np.ndarray:
    """(M, 3) weights that show a rig's M camera channels as linear RGB: an RGB rig's channel rows on
    R, G, B (unit sum: mono is grey), a spectral rig's channel colours (`spectral.display_weights`)."""
    from msps_render.rig import RigSpec, rig_sensitivities

    spec = RigSpec.model_validate_json(rig_json)
    if spec.is_spectral:
        from msps_render.spectral.spectra import display_weights

        return np.asarray(display_weights(rig_sensitivities(spec)), np.float64)
    w = np.asarray(spec.channels, np.float64)
    return w / np.maximum(w.sum(axis=1, keepdims=True), 1e-12)


def rig_views(shots: np.ndarray, rig, weights: np.ndarray, names) -> list[tuple[str, np.ndarray]]:
    """The views of one sample's shots (S, H, W, M): shots first/middle/last in colour, captioned with
    their lights; one shot of more than three channels: its first/middle/last channel, grey."""
    shots = np.asarray(shots, np.float32)
    S, M = shots.shape[0], shots.shape[-1]
    shot_list = rig.shot_list
    if S == 1 and M > 3:
        return [(f"channel {names[m] if m < len(names) else m}", np.repeat(shots[0, ..., m:m + 1], 3, axis=-1))
                for m in pick(M)]
    out = []
    for s in pick(S):
        lights = shot_list[s] if s < len(shot_list) else ()
        which = (f"light {lights[0]}" if len(lights) == 1 else f"{len(lights)} lights") if lights else ""
        out.append((f"shot {s}" + (f": {which}" if which and S > 1 else ""),
                    (shots[s].astype(np.float64) @ weights).astype(np.float32)))
    return out


def rig_shard_samples(path: str | Path, n: int, rng: np.random.Generator) -> tuple[list[RigSample], list[float]]:
    """Up to `n` samples of a format-2 shard (its first whole frames if stored, else `n` random patches
    in shard order) and the mask coverage of every patch of the shard (as `shard_samples`)."""
    from msps_render.dataset import schema as K
    from msps_render.dataset.reader import read_rigs
    from msps_render.dataset.samples import labelled, pick_samples

    name = Path(path).name

    def make(h, labels):
        rjs = h[K.FRAME_RIG_JSON].asstr()[()]
        _, nominal = read_rigs(h)
        cache: dict[str, np.ndarray] = {}

        def sample(shots, normal, mask, f, yx) -> RigSample:
            import json

            rj = str(rjs[f])
            if rj not in cache:
                cache[rj] = display_weights_of(rj)
            names = json.loads(rj).get("channel_names", ())
            views = rig_views(shots, nominal[f], cache[rj], names)
            smp = labelled(labels, views[0][1], normal, np.asarray(mask, bool), name, f, yx)
            return RigSample(smp, views, nominal[f].describe())
        return sample

    return pick_samples(path, n, rng, make, whole_key=K.FRAME_SHOTS)


def _is_rig_shard(path: Path) -> bool:
    from msps_render.dataset.reader import is_rig_shard, open_shard, shard_errors

    with shard_errors(path), open_shard(path) as h:
        return is_rig_shard(h)


def _caption(draw, box, text: str, font) -> None:
    """`text` in white on a black band at the top of a tile."""
    x0, y0, x1, _ = box
    draw.rectangle((x0, y0, x1 - 1, y0 + LINE + 1), fill=(0, 0, 0))
    draw.text((x0 + 3, y0 + 2), _fit(text, font, x1 - x0 - 6), fill=(255, 255, 255), font=font)


def preview_dataset(root: str | Path, out: str | Path, n: int = 8, seed: int = 0, tile: int = 160,
                    cols: int = 2, labels: bool = True) -> Path:
    """Write the contact sheet of dataset `root` to `out` (PNG); returns `out`."""
    root, out = Path(root), Path(out)
    m = read_manifest(root)
    names = sorted(m["shards"]) if m else sorted(p.name for p in (root / SHARD_DIR).glob("shard-*.h5"))
    rng = np.random.default_rng(seed)
    samples: list[Sample | RigSample] = []
    slants, mats, cover, objects, conds = [], [], [], [], []
    quota = sample_quota(names, {k: e.get("condition", "") for k, e in (m or {}).get("shards", {}).items()}, n)
    n = sum(quota.values())
    carry = 0  # samples a shard could not give (fewer frames than its share) go to the next one
    for name in names:
        path = root / SHARD_DIR / name
        table = read_frame_table(path)
        slants.extend(table["slant_deg"])
        mats.extend(s for ms in table["materials"] for s in ms.split(";") if s)
        objects.extend(table["object"])
        conds.extend(table["condition"])
        want = min(quota[name] + carry, n - len(samples))
        got, cov = (rig_shard_samples if _is_rig_shard(path) else shard_samples)(path, want, rng)
        carry = want - len(got)
        samples.extend(got)
        cover.extend(cov)
    samples = samples[:n]
    rig = any(isinstance(s, RigSample) for s in samples)
    n_views = max((len(s.views) for s in samples if isinstance(s, RigSample)), default=1)

    L = layout(len(samples), tile, cols, tiles=n_views + 2, lines=LABEL_LINES + (1 if rig else 0))
    sheet = Image.new("RGB", (L.width, L.height), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    font = _font()
    for k, s in enumerate(samples):
        base = s.sample if isinstance(s, RigSample) else s
        if isinstance(s, RigSample):  # the shots at one exposure: a dim shot is dim
            white = np.concatenate([v[base.mask] if base.mask.any() else v.reshape(-1, 3) for _, v in s.views])
            w = max(float(np.percentile(white, 99.0)) if white.size else 1.0, 1e-8)
            views = [(c, srgb8(v / w)) for c, v in s.views]
            views += [("", None)] * (n_views - len(views))
        else:
            views = [("", tonemap(base.image, base.mask))]
        pics = [*views, ("normal", normal_to_rgb8(base.normal, base.mask)),
                ("mask", base.mask.astype(np.uint8) * 255)]
        for j, (caption, pic) in enumerate(pics):
            box = L.tile_box(k, j)
            x0, y0, x1, y1 = box
            draw.rectangle((x0, y0, x1 - 1, y1 - 1), fill=(0, 0, 0) if pic is not None else (255, 255, 255))
            if pic is None:
                continue
            im = _tile(pic, tile)
            sheet.paste(im.convert("RGB"), (x0 + (tile - im.width) // 2, y0 + (tile - im.height) // 2))
            if labels and rig and caption:
                _caption(draw, box, caption, font)
        if labels:
            x0, y0, _, _ = L.label_box(k)
            lines = label_lines(base) + ([f"rig: {s.rig}"] if isinstance(s, RigSample) else [])
            for i, text in enumerate(lines):
                draw.text((x0 + 2, y0 + 3 + i * LINE), _fit(text, font, L.cell_w - 4), fill=(0, 0, 0), font=font)
    if labels:
        channels = rig and all(s.views[0][0].startswith("channel") for s in samples if isinstance(s, RigSample))
        what = ("the channels (first, middle, last) of its one shot, normal map, mask" if channels else
                "shots (first, middle, last), normal map, mask" if rig else "image, normal map, mask")
        title = (f"{root.name}: {len(names)} shards, {len(objects)} frames, {len(cover)} patches"
                 + (f", conditions: {', '.join(sorted(set(conds)))}" if any(conds) else "")
                 + f"  |  each sample: {what}")
        draw.text((PAD, 8), _fit(title, font, L.width - 2 * PAD), fill=(0, 0, 0), font=font)
    plots = _plots(L.width, slants, mats, cover, "mean light slant (deg) per frame" if rig else None)
    sheet.paste(Image.fromarray(plots).resize((L.width, PLOTS_H)), (0, L.height - PLOTS_H - PAD))
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(out) as tmp:
        sheet.save(tmp, format="PNG")  # no text chunks, no timestamps: same data, same bytes
    return out
