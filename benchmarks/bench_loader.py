"""Loader throughput (issues 5, 12): patches/s into batched float32 tensors, per mode, in one run.

Usage: python benchmarks/bench_loader.py --data DIR [DIR ...] [--batch 64] [--epochs 1] [--workers 2]

Modes: the HDF5 decode alone (every shard's patch arrays once, no batches: the
floor of any loader that reads the shards each epoch); PatchDataset through
DataLoader's default collate (per-item dicts);
`make_loader` with 0 and `--workers` workers; the same on `PatchDataset(cache=True)`
(every shard decoded into memory first; its load time is printed); and the
floor of slicing the same arrays in memory (numpy fancy-index + float32).
Every mode reads the same batches (seed 0, epochs 0..E-1) after the shard files
have been read once (warm page cache); worker modes start their workers before
the clock.  Besides patches/s (wall clock: noisy on a shared machine) each mode
reports CPU microseconds per patch in the main process and in its workers
(needs psutil), which do not depend on what else runs on the machine.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from msps_render.data import PatchDataset, ShardBatchSampler, make_loader
from msps_render.dataset import open_shard, read_patch_layout, read_patches_into, shard_summary
from msps_render.dataset import schema as K


def cpu_seconds() -> tuple[float, float] | None:
    """(main, child processes) CPU seconds so far, or None without psutil."""
    try:
        import psutil
    except ImportError:
        return None
    me = psutil.Process()
    c = me.cpu_times()
    kids = 0.0
    for k in me.children(recursive=True):
        try:
            kids += sum(k.cpu_times()[:2])
        except psutil.NoSuchProcess:
            pass
    return c.user + c.system, kids


def measure(loader, epochs: int) -> tuple[float, float | None, float | None]:
    """(patches/s, main CPU us/patch, workers CPU us/patch) over `epochs` epochs."""
    n, c0, t = 0, cpu_seconds(), time.perf_counter()
    for e in range(epochs):
        set_epoch = getattr(loader, "set_epoch", None) or loader.batch_sampler.set_epoch
        set_epoch(e)
        for b in loader:
            n += b["image"].shape[0]
    wall, c1 = time.perf_counter() - t, cpu_seconds()
    if c0 is None:
        return n / wall, None, None
    return n / wall, (c1[0] - c0[0]) / n * 1e6, (c1[1] - c0[1]) / n * 1e6


def warm_workers(loader) -> None:
    """Start the workers (and leave an abandoned iteration behind, as a training loop may)."""
    for i, _ in enumerate(loader):
        if i == 3:
            break


def decode_rate(ds: PatchDataset, epochs: int) -> tuple[float, float | None, float | None]:
    """Every shard's image, normal and mask decoded into reused arrays, as `make_loader` does."""
    bufs: dict[str, np.ndarray] = {}
    n, c0, t = 0, cpu_seconds(), time.perf_counter()
    for _ in range(epochs):
        for path, count, _ in ds.shards:
            with open_shard(path, chunk_cache=False) as h:
                for name, (shape, dtype) in read_patch_layout(h).items():
                    if name not in bufs or len(bufs[name]) < shape[0] or bufs[name].shape[1:] != shape[1:]:
                        bufs[name] = np.empty(shape, dtype)
                read_patches_into(h, bufs)
            n += count
    wall, c1 = time.perf_counter() - t, cpu_seconds()
    if c0 is None:
        return n / wall, None, None
    return n / wall, (c1[0] - c0[0]) / n * 1e6, 0.0


def memory_rate(ds: PatchDataset, batch: int, epochs: int) -> tuple[float, float | None, float | None]:
    img = np.concatenate([c["image"] for c in ds._cache])
    nrm = np.concatenate([c["normal"] for c in ds._cache])
    msk = np.concatenate([c["mask"] for c in ds._cache])
    rng = np.random.default_rng(0)
    n, c0, t = 0, cpu_seconds(), time.perf_counter()
    for _ in range(epochs):
        perm = rng.permutation(len(img))
        for b in range(0, len(img), batch):
            i = np.sort(perm[b:b + batch])
            x = torch.from_numpy(img[i].transpose(0, 3, 1, 2).astype(np.float32))
            y = torch.from_numpy(nrm[i].transpose(0, 3, 1, 2).astype(np.float32))
            m = torch.from_numpy(msk[i][:, None].astype(np.float32))
            n += x.shape[0] + 0 * (y.shape[0] + m.shape[0])
    wall, c1 = time.perf_counter() - t, cpu_seconds()
    if c0 is None:
        return n / wall, None, None
    return n / wall, (c1[0] - c0[0]) / n * 1e6, 0.0


def describe(ds: PatchDataset) -> str:
    first = next((p for p, n, _ in ds.shards if n), None)
    if first is None:
        return "no patches"
    shape, dtype, comp = shard_summary(first)["datasets"][K.PATCH_IMAGE]
    return f"{shape[1]}x{shape[2]} patches, {dtype}, {comp}"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, nargs="+", help="dataset directories (read as one)")
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--epochs", type=int, default=1)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--skip-cache", action="store_true", help="leave out the cache=True modes and the floor")
    a = ap.parse_args()
    torch.set_num_threads(1)
    ds = PatchDataset(a.data)
    for p, _, _ in ds.shards:  # warm page cache: every mode reads the files from memory
        Path(p).read_bytes()
    print(f"corpus: {' + '.join(a.data)}: {len(ds):,} patches in {len(ds.shards)} shards "
          f"({describe(ds)}); batch {a.batch}, {a.epochs} epoch(s) per mode")
    rows = [("HDF5 decode only (each shard once, no batches)", decode_rate(ds, a.epochs))]
    dl = DataLoader(ds, batch_sampler=ShardBatchSampler(ds, a.batch, seed=0), num_workers=0)
    rows.append(("PatchDataset via default collate (per-item dicts), 0 workers", measure(dl, a.epochs)))
    for workers in (0, a.workers):
        dl = make_loader(ds, a.batch, num_workers=workers)
        warm_workers(dl)
        rows.append((f"make_loader(PatchDataset), {workers} workers", measure(dl, a.epochs)))
        del dl
    if not a.skip_cache:
        t = time.perf_counter()
        cached = PatchDataset(a.data, cache=True)
        load_s = time.perf_counter() - t
        for workers in (0, a.workers):
            dl = make_loader(cached, a.batch, num_workers=workers)
            warm_workers(dl)
            rows.append((f"make_loader(PatchDataset(cache=True)), {workers} workers", measure(dl, a.epochs)))
            del dl
        rows.append(("numpy arrays in memory (floor)", memory_rate(cached, a.batch, a.epochs)))
    print("| loader | patches/s | CPU us/patch main | CPU us/patch workers |")
    print("|---|---|---|---|")
    fmt = lambda v: "n/a" if v is None else f"{v:.1f}"  # noqa: E731
    for name, (r, main_us, work_us) in rows:
        print(f"| {name} | {r:,.0f} | {fmt(main_us)} | {fmt(work_us)} |")
    if not a.skip_cache:
        print(f"cache=True: decoding every shard into memory took {load_s:.1f} s "
              f"({len(ds) / load_s:,.0f} patches/s, main process)")


if __name__ == "__main__":
    main()
