"""Contact sheet of a dataset (tone-mapped images, normal maps, masks) plus distribution plots."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from msps_render.atomic import atomic_write
from msps_render.dataset import SHARD_DIR, open_shard, read_frame_table, read_manifest
from msps_render.dataset.reader import n_whole_frames, read_whole_frame
from msps_render.dataset.schema import PATCH_IMAGE, PATCH_MASK, PATCH_NORMAL
from msps_render.preview import normal_to_rgb8, tonemap


def _samples(path: Path, n: int, per_shard: int, rng: np.random.Generator) -> tuple[list, list[float]]:
    """Up to `n` (image, normal, mask) of a shard (whole frames if stored, else random patches)
    and the mask coverage of every patch."""
    with open_shard(path) as h:
        msk = h[PATCH_MASK][()]
        N = len(msk)
        cover = msk.reshape(N, -1).mean(1).tolist()
        if n <= 0:
            return [], cover
        if n_whole_frames(h):
            return [read_whole_frame(h, i) for i in range(min(n_whole_frames(h), n))], cover
        out = []
        if N:
            for i in sorted(rng.choice(N, size=min(N, per_shard), replace=False)):
                out.append((h[PATCH_IMAGE][i].astype(np.float32), h[PATCH_NORMAL][i].astype(np.float32),
                            msk[i].astype(bool)))
        return out, cover


def preview_dataset(root: str | Path, out: str | Path, n: int = 8, seed: int = 0) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    root, out = Path(root), Path(out)
    m = read_manifest(root)
    names = sorted(m["shards"]) if m else sorted(p.name for p in (root / SHARD_DIR).glob("shard-*.h5"))
    rng = np.random.default_rng(seed)
    samples, slants, mats, cover, objects, conds = [], [], [], [], [], []
    for name in names:
        path = root / SHARD_DIR / name
        table = read_frame_table(path)
        slants.extend(table["slant_deg"])
        mats.extend(s for ms in table["materials"] for s in ms.split(";"))
        objects.extend(table["object"])
        conds.extend(table["condition"])
        got, cov = _samples(path, n - len(samples), max(1, n // max(1, len(names))), rng)
        samples.extend(got)
        cover.extend(cov)
    samples = samples[:n]
    fig = plt.figure(figsize=(2.0 * max(len(samples), 4), 9.5))
    gs = fig.add_gridspec(4, max(len(samples), 4), height_ratios=[1, 1, 1, 1.4])
    for j, (img, nrm, msk) in enumerate(samples):
        for r, (pic, title) in enumerate(((tonemap(img, msk), "image"), (normal_to_rgb8(nrm, msk), "normal"),
                                          (msk.astype(np.uint8) * 255, "mask"))):
            ax = fig.add_subplot(gs[r, j])
            ax.imshow(pic, cmap="gray" if r == 2 else None, vmin=0, vmax=255, interpolation="nearest")
            ax.set_xticks([]), ax.set_yticks([])
            if j == 0:
                ax.set_ylabel(title)
    k = max(len(samples), 4)
    w = k // 3
    ax = fig.add_subplot(gs[3, 0:w])
    ax.hist(slants, bins=20, color="C0")
    ax.set_title("slant (deg) per frame")
    ax = fig.add_subplot(gs[3, w:2 * w])
    u, c = np.unique(mats, return_counts=True) if mats else ([], [])
    ax.barh(list(u)[:15], list(c)[:15], color="C1")
    ax.set_title("materials")
    ax.tick_params(axis="y", labelsize=6)
    ax = fig.add_subplot(gs[3, 2 * w:])
    ax.hist(cover, bins=20, range=(0, 1), color="C2")
    ax.set_title(f"patch mask coverage ({len(cover)} patches)")
    fig.suptitle(f"{root.name}: {len(names)} shards, {len(objects)} frames, {len(cover)} patches"
                 + (f", conditions: {', '.join(sorted(set(conds)))}" if any(conds) else ""))
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(out) as tmp:
        fig.savefig(tmp, dpi=80, format="png")
    plt.close(fig)
    return out
