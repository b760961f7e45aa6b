"""A picture of `train.albedo_aug`: training patches as rendered (top) and with the colour field the
augmentation multiplies in (bottom), one column per patch.

    python benchmarks/albedo_aug_sheet.py --data data/train-grey-30 --out docs/img/albedo-aug.png

Each image is shown divided by its own 99th percentile (the network sees them normalised by their
mean), gamma 1/2.2.  The fields come from `models/augment.py` with the run's rule: seed (0, step, 1)."""
from __future__ import annotations

import argparse

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", action="append", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--n", type=int, default=10, help="patches (columns)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import torch

    from msps_render.data import PatchDataset
    from msps_render.models.augment import albedo_batch

    ds = PatchDataset(args.data)
    rng = np.random.default_rng(args.seed)
    idx = rng.choice(len(ds), size=args.n, replace=False)
    batch = {"image": torch.stack([ds[int(i)]["image"] for i in idx])}
    aug = albedo_batch(batch, np.ones(args.n, bool), np.random.default_rng((args.seed, 0, 1)))
    fig, ax = plt.subplots(2, args.n, figsize=(1.3 * args.n, 2.9))
    for r, imgs in enumerate((batch["image"], aug["image"])):
        for c in range(args.n):
            x = imgs[c].numpy().transpose(1, 2, 0)
            x = np.clip(x / max(float(np.quantile(x, 0.99)), 1e-6), 0, 1) ** (1 / 2.2)
            ax[r, c].imshow(x)
            ax[r, c].axis("off")
        ax[r, 0].set_title(("as rendered", "train.albedo_aug")[r], fontsize=8, loc="left")
    fig.tight_layout()
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
