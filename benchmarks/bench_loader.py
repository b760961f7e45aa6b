"""PatchDataset throughput (issue 5): patches/s into batched tensors.

Usage: .venv/bin/python benchmarks/bench_loader.py --data DIR [--batch 64] [--epochs 2]

Compares, in one run: PatchDataset + ShardBatchSampler with 0 and 2 DataLoader
workers, the in-memory cache mode, and the floor of slicing the same arrays
from memory (numpy fancy-index + torch.from_numpy), all yielding the same
batch dict layout.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from torch.utils.data import DataLoader

from msps_render.data import PatchDataset, ShardBatchSampler, make_loader


def rate(loader, epochs: int) -> float:
    n, t = 0, time.perf_counter()
    for e in range(epochs):
        if hasattr(loader.batch_sampler, "set_epoch"):
            loader.batch_sampler.set_epoch(e)
        for b in loader:
            n += b["image"].shape[0]
    return n / (time.perf_counter() - t)


def memory_rate(ds: PatchDataset, batch: int, epochs: int) -> float:
    img = np.concatenate([c["image"] for c in ds._cache])
    nrm = np.concatenate([c["normal"] for c in ds._cache])
    msk = np.concatenate([c["mask"] for c in ds._cache])
    rng = np.random.default_rng(0)
    n, t = 0, time.perf_counter()
    for _ in range(epochs):
        perm = rng.permutation(len(img))
        for b in range(0, len(img), batch):
            i = np.sort(perm[b:b + batch])
            x = torch.from_numpy(img[i].transpose(0, 3, 1, 2).astype(np.float32))
            y = torch.from_numpy(nrm[i].transpose(0, 3, 1, 2).astype(np.float32))
            m = torch.from_numpy(msk[i][:, None].astype(np.float32))
            n += x.shape[0] + 0 * (y.shape[0] + m.shape[0])
    return n / (time.perf_counter() - t)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", required=True)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--epochs", type=int, default=2)
    a = ap.parse_args()
    torch.set_num_threads(1)
    ds = PatchDataset(a.data)
    rows = []
    dl = DataLoader(ds, batch_sampler=ShardBatchSampler(ds, a.batch, seed=0), num_workers=0)
    rows.append(("PatchDataset via default collate (per-item dicts), 0 workers", rate(dl, a.epochs)))
    for workers in (0, 2):
        dl = make_loader(ds, a.batch, num_workers=workers)
        rate(dl, 1)  # warm-up (worker start, page cache)
        rows.append((f"make_loader(PatchDataset), {workers} workers", rate(dl, a.epochs)))
    cached = PatchDataset(a.data, cache=True)
    rows.append(("make_loader(PatchDataset(cache=True)), 0 workers", rate(make_loader(cached, a.batch), a.epochs)))
    rows.append(("numpy arrays in memory (floor)", memory_rate(cached, a.batch, a.epochs)))
    print(f"{len(ds)} patches, batch {a.batch}, {a.epochs} epochs")
    print("| loader | patches/s |")
    print("|---|---|")
    for name, r in rows:
        print(f"| {name} | {r:,.0f} |")


if __name__ == "__main__":
    main()
