"""Contact sheet of a dataset: labelled samples (image | normal map | mask) plus distribution plots.

Each sample is one cell: three `tile` x `tile` px tiles side by side (nearest-neighbour
upscaled, aspect kept) over a label band naming the shard and frame (and the patch origin
for patch samples), the shape kind and name, the materials and the sweep condition.
The sheet is drawn with Pillow (the histograms with matplotlib) and saved without
metadata, so the same dataset gives the same PNG bytes.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from msps_render.atomic import atomic_write
from msps_render.dataset import SHARD_DIR, read_frame_table, read_manifest
from msps_render.dataset.samples import Sample, shard_samples
from msps_render.preview import normal_to_rgb8, tonemap

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

    @property
    def rows(self) -> int:
        return -(-self.n // self.cols) if self.n else 0

    @property
    def cell_w(self) -> int:
        return 3 * self.tile + 2 * GAP

    @property
    def cell_h(self) -> int:
        return self.tile + LABEL_H

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
        """(x0, y0, x1, y1) of tile j (0 image, 1 normal, 2 mask) of cell k."""
        x, y = self.cell(k)
        x += j * (self.tile + GAP)
        return x, y, x + self.tile, y + self.tile

    def label_box(self, k: int) -> tuple[int, int, int, int]:
        x, y = self.cell(k)
        return x, y + self.tile, x + self.cell_w, y + self.cell_h


def layout(n_samples: int, tile: int = 160, cols: int = 2) -> Layout:
    return Layout(n=n_samples, tile=tile, cols=max(1, min(cols, n_samples or 1)))


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


def _plots(width: int, slants, mats, cover) -> np.ndarray:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dpi = 80
    fig = plt.figure(figsize=(width / dpi, PLOTS_H / dpi), dpi=dpi)
    axs = fig.subplots(1, 3)
    axs[0].hist(slants, bins=20, color="C0")
    axs[0].set_title("slant (deg) per frame", fontsize=9)
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


def preview_dataset(root: str | Path, out: str | Path, n: int = 8, seed: int = 0, tile: int = 160,
                    cols: int = 2, labels: bool = True) -> Path:
    """Write the contact sheet of dataset `root` to `out` (PNG); returns `out`."""
    root, out = Path(root), Path(out)
    m = read_manifest(root)
    names = sorted(m["shards"]) if m else sorted(p.name for p in (root / SHARD_DIR).glob("shard-*.h5"))
    rng = np.random.default_rng(seed)
    samples: list[Sample] = []
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
        got, cov = shard_samples(path, want, rng)
        carry = want - len(got)
        samples.extend(got)
        cover.extend(cov)
    samples = samples[:n]

    L = layout(len(samples), tile, cols)
    sheet = Image.new("RGB", (L.width, L.height), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    font = _font()
    for k, s in enumerate(samples):
        pics = (tonemap(s.image, s.mask), normal_to_rgb8(s.normal, s.mask), s.mask.astype(np.uint8) * 255)
        for j, pic in enumerate(pics):
            x0, y0, x1, y1 = L.tile_box(k, j)
            draw.rectangle((x0, y0, x1 - 1, y1 - 1), fill=(0, 0, 0))
            im = _tile(pic, tile)
            sheet.paste(im.convert("RGB"), (x0 + (tile - im.width) // 2, y0 + (tile - im.height) // 2))
        if labels:
            x0, y0, _, _ = L.label_box(k)
            for i, text in enumerate(label_lines(s)):
                draw.text((x0 + 2, y0 + 3 + i * LINE), _fit(text, font, L.cell_w - 4), fill=(0, 0, 0), font=font)
    if labels:
        title = (f"{root.name}: {len(names)} shards, {len(objects)} frames, {len(cover)} patches"
                 + (f", conditions: {', '.join(sorted(set(conds)))}" if any(conds) else "")
                 + "  |  each sample: image, normal map, mask")
        draw.text((PAD, 8), _fit(title, font, L.width - 2 * PAD), fill=(0, 0, 0), font=font)
    plots = _plots(L.width, slants, mats, cover)
    sheet.paste(Image.fromarray(plots).resize((L.width, PLOTS_H)), (0, L.height - PLOTS_H - PAD))
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(out) as tmp:
        sheet.save(tmp, format="PNG")  # no text chunks, no timestamps: same data, same bytes
    return out
