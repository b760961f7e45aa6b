"""Loader throughput (issues 5, 12): patches/s into batched float32 tensors, per mode, in one run.

Usage: python benchmarks/bench_loader.py --data DIR [DIR ...] [--batch 64] [--epochs 1] [--workers 2]
       python benchmarks/bench_loader.py --compare DIR [DIR ...] [--rounds 5] [--epochs 1] [--workers 2]

`--repack SRC --to FILTER --out DST` copies a rendered corpus with every numeric
array re-encoded with another filter (same values, chunks, attributes, manifest;
checked array by array), so filters are compared on identical content without
rendering the corpus again.  Its manifest's file digests then describe SRC's files,
so `msps verify` is not meant for DST.

`--compare` (issue 21, storage filters): the same corpus stored with different
`dataset.storage.compression` filters, one directory each (the first is the
reference, e.g. lzf); per corpus the disk size and, over `--rounds` rounds that
visit the corpora in turn (so a change in machine load hits all of them alike),
the streaming rate of the HDF5 decode alone and of `make_loader` with 0 and
`--workers` workers; prints medians, their ratio to the first corpus, and CPU
microseconds per patch.

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
    ap.add_argument("--data", nargs="+", help="dataset directories (read as one)")
    ap.add_argument("--compare", nargs="+", help="one corpus per storage filter, compared (see above)")
    ap.add_argument("--rounds", type=int, default=5, help="--compare: rounds (medians)")
    ap.add_argument("--repack", metavar="SRC", help="copy corpus SRC re-encoded with --to into --out")
    ap.add_argument("--to", help="--repack: the filter (a dataset.storage.compression value)")
    ap.add_argument("--out", help="--repack: the new corpus directory")
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--epochs", type=int, default=1)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--skip-cache", action="store_true", help="leave out the cache=True modes and the floor")
    a = ap.parse_args()
    torch.set_num_threads(1)
    if a.repack:
        return repack(a.repack, a.to, a.out)
    if a.compare:
        return compare_main(a)
    if not a.data:
        ap.error("--data or --compare is required")
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


def _filters(ds: PatchDataset) -> str:
    """The HDF5 filter pipeline of the first shard's patch images, e.g. 'shuffle+lzf+fletcher32'."""
    first = next((p for p, n, _ in ds.shards if n), None)
    with open_shard(first) as h:
        pl = h[K.PATCH_IMAGE].id.get_create_plist()
        names = [pl.get_filter(i)[3].decode(errors="replace").split()[0].lower() for i in range(pl.get_nfilters())]
    return "+".join(names) or "no filter"


def _corpus_bytes(ds: PatchDataset) -> int:
    return sum(Path(p).stat().st_size for p, _, _ in ds.shards)


def repack(src: str, filt: str, dst: str) -> None:
    """`src` with every chunked numeric array re-encoded with `filt` (see the module docstring)."""
    import shutil

    import h5py

    from msps_render.dataset.writer import filter_kwargs

    src_p, dst_p = Path(src), Path(dst)
    if dst_p.exists():
        raise SystemExit(f"bench_loader: {dst} exists")
    shutil.copytree(src_p, dst_p, ignore=shutil.ignore_patterns("*.h5"))
    kw = filter_kwargs(filt)
    for f in sorted((src_p / "shards").glob("*.h5")):
        with open_shard(f) as a, h5py.File(dst_p / "shards" / f.name, "w", track_order=True) as b:
            for k, v in a.attrs.items():
                b.attrs[k] = v

            def copy(name, obj):
                if isinstance(obj, h5py.Group):
                    b.require_group(name)
                    return
                data = obj[()]
                if obj.chunks is not None and obj.dtype.kind in "fiub":
                    b.create_dataset(name, data=data, chunks=obj.chunks, track_times=False, **kw)
                    assert np.array_equal(b[name][()], data), (f, name)
                else:
                    a.copy(obj, b, name=name)

            a.visititems(copy)
    print(f"repacked {src} -> {dst} ({filt})")


def compare_main(a) -> None:
    """Storage filters side by side: disk and streaming rate per corpus, medians over rounds."""
    import statistics

    corpora = []
    for d in a.compare:
        ds = PatchDataset(d)
        for p, _, _ in ds.shards:  # warm page cache: every round reads the files from memory
            Path(p).read_bytes()
        corpora.append((d, ds))
    n0 = len(corpora[0][1])
    for d, ds in corpora:
        if len(ds) != n0:
            raise SystemExit(f"bench_loader: {d} has {len(ds)} patches, {corpora[0][0]} has {n0}: not the same corpus")
    modes = ["decode", "loader0", f"loader{a.workers}"]
    res = {d: {m: [] for m in modes} for d, _ in corpora}
    cpu = {d: {m: [] for m in modes} for d, _ in corpora}
    loaders = {d: make_loader(ds, a.batch, num_workers=a.workers) for d, ds in corpora}
    for dl in loaders.values():
        warm_workers(dl)
    for r in range(a.rounds):
        for d, ds in corpora:
            for m in modes:
                if m == "decode":
                    rate, main_us, work_us = decode_rate(ds, a.epochs)
                elif m == "loader0":
                    rate, main_us, work_us = measure(make_loader(ds, a.batch, num_workers=0), a.epochs)
                else:
                    rate, main_us, work_us = measure(loaders[d], a.epochs)
                res[d][m].append(rate)
                cpu[d][m].append((main_us or 0.0) + (work_us or 0.0))
        print(f"round {r + 1}: " + "; ".join(f"{Path(d).name} " + " ".join(f"{res[d][m][-1]:,.0f}" for m in modes)
                                             for d, _ in corpora), flush=True)
    med = {d: {m: statistics.median(v) for m, v in res[d].items()} for d in res}
    ref = a.compare[0]
    print(f"corpus: {n0:,} patches in {len(corpora[0][1].shards)} shards ({describe(corpora[0][1])}); batch "
          f"{a.batch}, {a.epochs} epoch(s) per measurement, medians of {a.rounds} rounds")
    print(f"| filter | disk (MB) | bytes/patch | HDF5 decode only (patches/s) | make_loader, 0 workers | "
          f"make_loader, {a.workers} workers | ratio to {Path(ref).name} (decode / 0 / {a.workers} workers) | "
          f"CPU us/patch (decode / 0 / {a.workers} workers, main + workers) |")
    print("|---|---|---|---|---|---|---|---|")
    for d, ds in corpora:
        size = _corpus_bytes(ds)
        filt = _filters(ds)
        ratio = " / ".join(f"{med[d][m] / med[ref][m]:.2f}" for m in modes)
        us = " / ".join(f"{statistics.median(cpu[d][m]):.0f}" for m in modes)
        print(f"| {Path(d).name} ({filt}) | {size / 1e6:.1f} | {size / len(ds):,.0f} | {med[d]['decode']:,.0f} | "
              f"{med[d]['loader0']:,.0f} | {med[d][modes[2]]:,.0f} | {ratio} | {us} |")


if __name__ == "__main__":
    main()
