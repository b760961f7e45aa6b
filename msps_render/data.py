"""Training-side access to a dataset directory: `PatchDataset` (torch), `make_loader`, whole frames.

h5py handles are opened lazily in whichever process reads (DataLoader workers
fork/spawn after construction, and HDF5 handles must not cross processes).

Reading a shard is dominated by HDF5's filters (fletcher32 + lzf + unshuffle
cost ~80 us per 40x40 float16 patch, ~85% of the loader), so `make_loader`
decodes every shard once per epoch, whole, in exactly one process (a
DataLoader worker when `num_workers > 0`: a disjoint share each, so two
workers decode twice as fast), into a reusable buffer ("slot", shared memory
with workers: nothing is copied between processes and no fresh pages are
faulted in), and the main process cuts the `ShardBatchSampler` plan's batches
out of the decoded shards.  Batches, their order and their contents depend on
(seed, epoch) only, not on the number of workers.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterator, NamedTuple, Sequence

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Sampler

from msps_render.dataset import (SHARD_DIR, WholeFrame, iter_whole_frames, load_manifest, open_shard,
                                 read_calibration, read_frame_lambertian, read_patch_layout, read_patches,
                                 read_patches_into, read_shard_patches, shard_errors, verify_dataset)
from msps_render.dataset.manifest import at_fault
from msps_render.errors import InputError

_ALIGN = 64  # byte alignment of the arrays inside a slot


class ShardRef(NamedTuple):
    """One shard of a dataset as the loader sees it (a tuple, so `for path, n, _ in ds.shards` reads)."""

    path: Path
    n_patches: int
    condition: str


def _shard_list(root: Path, condition: str | None) -> list[ShardRef]:
    m = load_manifest(root)
    return [ShardRef(m.shard_path(e.name), e.n_patches, e.condition) for e in m.shards_of(condition)]


Layout = dict[str, tuple[tuple[int, ...], np.dtype]]  # {array: (stored shape, dtype)} of a shard


def _slot_layout(layout: Layout) -> dict[str, tuple[int, tuple[int, ...], np.dtype]]:
    """{name: (byte offset, shape, dtype)} of a decoded shard inside a slot: image and normal
    (N,C,P,P), mask (N,1,P,P), in the stored dtypes (a batch is then a plain row gather)."""
    out, off = {}, 0
    for name, (shape, dtype) in layout.items():
        shape = (shape[0], shape[3], shape[1], shape[2]) if len(shape) == 4 else (shape[0], 1) + tuple(shape[1:])
        out[name] = (off, shape, np.dtype(dtype))
        off += -(-int(np.prod(shape)) * np.dtype(dtype).itemsize // _ALIGN) * _ALIGN
    return out


def _slot_bytes(layout: Layout) -> int:
    off, shape, dtype = list(_slot_layout(layout).values())[-1]
    return off + int(np.prod(shape)) * dtype.itemsize


def _slot_views(buf: np.ndarray, layout: Layout) -> dict[str, np.ndarray]:
    """Typed views of a decoded shard in the uint8 buffer `buf`."""
    return {name: buf[off:off + int(np.prod(shape)) * dtype.itemsize].view(dtype).reshape(shape)
            for name, (off, shape, dtype) in _slot_layout(layout).items()}


def available_memory_bytes() -> int:
    """MemAvailable of this machine (Linux /proc/meminfo); 0 when unknown."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def should_cache(decoded_bytes: int, available_bytes: int, share: float = 0.4) -> bool:
    """Keep a corpus decoded in memory when it takes at most `share` of the available memory.

    Why: a shard is lzf-compressed HDF5, and decoding it (checksum, lzf, unshuffle) costs
    ~80 us of CPU per patch -- ~10k patches/s per core, less than a GPU trainer eats; decoded
    once and kept, batches come at ~50k patches/s (docs/benchmarks.md "Loader")."""
    return 0 < decoded_bytes <= share * available_bytes


class PatchDataset(Dataset):
    """Patches of a dataset directory as dicts of tensors:

    image (3,P,P) float32 linear radiance, normal (3,P,P), mask (1,P,P) float32,
    light_dirs (3,3), crosstalk (3,3), lambertian () bool (the frame's image is linear in its
    albedo: `dataset.reader.scene_is_lambertian`), plus shard/frame/index ids.
    """

    decoded_shards = 8  # LRU size of decoded shards per process for per-item access (~15 MB each)

    def __init__(self, root: str | Path | Sequence[str | Path], condition: str | None = None,
                 cache: bool = False, verify: bool = False):
        """`root`: one dataset directory, or several read as one (e.g. a corpus plus a supplement)."""
        roots = [Path(root)] if isinstance(root, (str, os.PathLike)) else [Path(r) for r in root]
        if not roots:
            raise ValueError("PatchDataset needs at least one dataset directory")
        self.roots, self.root = roots, roots[0]
        self.shards: list[ShardRef] = []
        for r in roots:
            if verify:
                bad = verify_dataset(r)
                if bad:
                    name, probs = sorted(bad.items())[0]
                    raise InputError(at_fault(r, name), f"fails verification: {'; '.join(probs)}")
            self.shards += _shard_list(r, condition)
        counts = np.array([n for _, n, _ in self.shards], dtype=np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(counts)])
        self._handles: dict[int, object] = {}
        self._decoded: dict[int, dict] = {}
        self._scratch: dict[str, np.ndarray] = {}
        self._pid = None
        # per shard: its frames' light_dirs, crosstalk, lambertian, and per patch frame_index, yx; its layout
        self.meta = [self._read_meta(p) for p, _, _ in self.shards]
        self._cache = None
        if cache:
            self.keep_decoded()

    def keep_decoded(self) -> None:
        """Decode every shard once and keep it in memory (what `cache=True` does at construction)."""
        if self._cache is None:
            self._cache = [self._read_all(p) for p, _, _ in self.shards]

    @property
    def is_cached(self) -> bool:
        """Is every shard kept decoded in memory (`cache=True` / `keep_decoded`)?"""
        return self._cache is not None

    def cached_views(self, s: int) -> dict[str, np.ndarray]:
        """Shard `s` from the cache as channels-first views (the layout `read_shard_into` writes)."""
        c = self._cache[s]
        return {"image": c["image"].transpose(0, 3, 1, 2), "normal": c["normal"].transpose(0, 3, 1, 2),
                "mask": c["mask"][:, None]}

    def decoded_bytes(self) -> int:
        """Bytes the decoded patches take in memory (what `cache=True` holds), from the layouts alone."""
        return int(sum(int(np.prod(shape)) * np.dtype(dtype).itemsize
                       for m in self.meta for shape, dtype in m["layout"].values()))

    # -------------------------------------------------------------- internals
    @staticmethod
    def _read_meta(path: Path) -> dict:
        with shard_errors(path), open_shard(path) as h:
            return {**read_calibration(h), "lambertian": read_frame_lambertian(h),
                    "layout": read_patch_layout(h)}

    @staticmethod
    def _read_all(path: Path) -> dict:
        return read_shard_patches(path)

    def _h(self, s: int):
        if self._pid != os.getpid():  # new process (DataLoader worker): reopen everything
            self._handles, self._decoded, self._scratch, self._pid = {}, {}, {}, os.getpid()
        if s not in self._handles:
            self._handles[s] = open_shard(self.shards[s].path, chunk_cache=False)  # whole-array reads only
        return self._handles[s]

    def locate(self, idx: int) -> tuple[int, int]:
        if idx < 0:
            idx += len(self)
        if not 0 <= idx < len(self):
            raise IndexError(idx)
        s = int(np.searchsorted(self.offsets, idx, side="right") - 1)
        return s, int(idx - self.offsets[s])

    def _shard_arrays(self, s: int) -> dict[str, np.ndarray]:
        """Every patch of shard `s` as stored (float16 NHWC): from the cache, else the LRU, else decoded."""
        if self._cache is not None:
            return self._cache[s]
        c = self._decoded.get(s)
        if c is None:
            # Decode the whole shard once: h5py fancy indexing costs ~0.3 ms per index and
            # re-reading spans re-decompresses them; a small LRU of decoded shards serves the
            # per-item / get_batch paths and repeated validation passes over the same shards.
            with shard_errors(self.shards[s].path):
                c = read_patches(self._h(s))
            self._decoded[s] = c
            while len(self._decoded) > self.decoded_shards:
                self._decoded.pop(next(iter(self._decoded)))
        else:
            self._decoded[s] = self._decoded.pop(s)  # most recently used
        return c

    def _pack(self, s: int, local: np.ndarray) -> dict:
        """The batch dict of rows `local` of shard `s` (the one batch builder, `_assemble`)."""
        c = self._shard_arrays(s)
        views = {"image": c["image"].transpose(0, 3, 1, 2), "normal": c["normal"].transpose(0, 3, 1, 2),
                 "mask": c["mask"][:, None]}
        idx = np.asarray(local, dtype=np.int64) + self.offsets[s]
        return _assemble(idx, [(s, 0, len(idx))], {s: views}, self.meta, self.offsets)

    def shard_bytes(self, s: int) -> int:
        """Bytes of shard `s` decoded (what `read_shard_into` needs)."""
        return _slot_bytes(self.meta[s]["layout"])

    def read_shard_into(self, s: int, buf: np.ndarray) -> dict[str, np.ndarray]:
        """Decode every patch of shard `s` into the uint8 buffer `buf`; returns typed views of it:
        image, normal (N,3,P,P) and mask (N,1,P,P) in the stored dtypes.

        How `make_loader` reads a shard, once per epoch: HDF5 decodes into per-process scratch
        buffers that are reused (fresh ones cost a page fault per 4 KiB), and the transpose to
        channels-first is the one copy into `buf`.
        """
        layout = self.meta[s]["layout"]
        views = _slot_views(buf, layout)
        if self._cache is not None:
            src = self._cache[s]
        else:
            with shard_errors(self.shards[s].path):
                h = self._h(s)  # first: a new process starts with fresh handles and scratch
                for name, (shape, dtype) in layout.items():
                    have = self._scratch.get(name)
                    if have is None or have.dtype != dtype or have.shape[1:] != shape[1:] or len(have) < shape[0]:
                        self._scratch[name] = np.empty(shape, dtype)
                read_patches_into(h, self._scratch)
            src = {name: a[:layout[name][0][0]] for name, a in self._scratch.items()}
        np.copyto(views["image"], src["image"].transpose(0, 3, 1, 2))
        np.copyto(views["normal"], src["normal"].transpose(0, 3, 1, 2))
        np.copyto(views["mask"][:, 0], src["mask"])
        return views

    # ---------------------------------------------------------------- Dataset
    def __len__(self) -> int:
        return int(self.offsets[-1])

    def __getitem__(self, idx: int) -> dict:
        s, j = self.locate(int(idx))
        return {k: v[0] for k, v in self._pack(s, np.array([j])).items()}

    def get_batch(self, indices) -> dict:
        """A batched dict for `indices` (any order, any shards): one read per shard per array."""
        idx = np.asarray(indices, dtype=np.int64)
        shard = np.searchsorted(self.offsets, idx, side="right") - 1
        parts, where = [], []
        for s in np.unique(shard):
            pos = np.nonzero(shard == s)[0]
            parts.append(self._pack(int(s), idx[pos] - self.offsets[s]))
            where.append(pos)
        if len(parts) == 1:
            return parts[0]
        order = np.argsort(np.concatenate(where))
        return {k: torch.cat([p[k] for p in parts])[order] for k in parts[0]}

    def __getitems__(self, indices: list[int]) -> list[dict]:
        """Batched fetch (used by DataLoader's auto-batching): one read per shard per array."""
        idx = np.asarray(indices, dtype=np.int64)
        shard = np.searchsorted(self.offsets, idx, side="right") - 1
        out: list[dict | None] = [None] * len(idx)
        for s in np.unique(shard):
            pos = np.nonzero(shard == s)[0]
            packed = self._pack(int(s), idx[pos] - self.offsets[s])
            for r, p in enumerate(pos):
                out[p] = {k: v[r] for k, v in packed.items()}
        return out  # type: ignore[return-value]

    def close(self) -> None:
        for h in self._handles.values():
            h.close()
        self._handles = {}


CAST_GRAIN = 32768  # elements per cast: torch's parallel grain (at::internal::GRAIN_SIZE), so each runs on one thread


def _float32(rows: np.ndarray, out: np.ndarray) -> None:
    """`out[...] = rows` through torch's vectorised cast (numpy's float16 -> float32 is several
    times slower), in pieces of at most `CAST_GRAIN` elements.  Why pieces: a larger copy runs on
    torch's intra-op threads, which wait for each other, so with another job on the machine a
    batch's cast took 8x the CPU and the loader ran at half speed (docs/benchmarks.md "Loader
    under load"); one thread per piece is as fast on a quiet machine."""
    src, dst = torch.from_numpy(rows), torch.from_numpy(out)
    per_row = max(1, int(np.prod(rows.shape[1:], dtype=np.int64)))
    step = max(1, CAST_GRAIN // per_row)
    for a in range(0, len(rows), step):
        dst[a:a + step].copy_(src[a:a + step])


def _assemble(idx: np.ndarray, runs: list[tuple[int, int, int]], live: dict[int, dict[str, np.ndarray]],
              meta: list[dict], offsets: np.ndarray) -> dict[str, torch.Tensor]:
    """The batch dict (layout of `PatchDataset.get_batch`) of dataset indices `idx`, whose stretches
    `runs` = [(shard, start, stop)] are rows of the decoded shards in `live`."""
    n, first = len(idx), live[runs[0][0]]
    out = {k: np.empty((n,) + first[k].shape[1:], np.float32) for k in ("image", "normal", "mask")}
    out.update(light_dirs=np.empty((n, 3, 3), np.float32), crosstalk=np.empty((n, 3, 3), np.float32),
               lambertian=np.empty(n, bool), shard=np.empty(n, np.int64), frame=np.empty(n, np.int64),
               yx=np.empty((n, 2), np.int64), index=idx.copy())
    for s, a, z in runs:
        d, m, local = live[s], meta[s], idx[a:z] - offsets[s]
        for k in ("image", "normal", "mask"):
            _float32(d[k][local], out[k][a:z])
        f = m["frame_index"][local]
        out["frame"][a:z], out["shard"][a:z] = f, s
        out["light_dirs"][a:z], out["crosstalk"][a:z] = m["light_dirs"][f], m["crosstalk"][f]
        out["lambertian"][a:z] = m["lambertian"][f]
        out["yx"][a:z] = m["yx"][local]
    return {k: torch.from_numpy(v) for k, v in out.items()}


class _Slots:
    """Decode buffers reused across shards and epochs (main-process bookkeeping).

    Shared-memory tensors when workers decode (sent along with the shard index: torch passes
    the handle once per worker and caches the mapping), plain arrays otherwise.  A slot is
    taken when its shard is dispatched and given back after the shard's last batch, so at
    most (shards a batch window needs + shards in flight) exist.
    """

    def __init__(self, nbytes: int, shared: bool):
        self.nbytes, self.shared = nbytes, shared
        self.bufs: list[torch.Tensor] = []
        self.free: list[int] = []

    def take(self) -> int:
        if self.free:
            return self.free.pop()
        t = torch.empty(self.nbytes, dtype=torch.uint8)
        self.bufs.append(t.share_memory_() if self.shared else t)
        return len(self.bufs) - 1

    def give(self, k: int) -> None:
        self.free.append(k)

    def reset(self) -> None:
        self.free = list(range(len(self.bufs)))[::-1]


class _ShardView(Dataset):
    """(shard, slot tensor) -> shard decoded into the slot, in a DataLoader worker.  An `InputError`
    is returned, so the loader re-raises it as is (one line naming the shard) instead of
    DataLoader's multi-line wrapper."""

    def __init__(self, ds: PatchDataset):
        self.ds = ds

    def __len__(self) -> int:
        return len(self.ds.shards)

    def __getitem__(self, item: tuple[int, torch.Tensor]) -> int | InputError:
        s, buf = item
        try:
            self.ds.read_shard_into(s, buf.numpy())
        except InputError as e:
            return e
        return s


class _Dispatch(Sampler[tuple[int, torch.Tensor]]):
    """The shards of an epoch in first-use order, each with a free slot; iterated by the decoding
    DataLoader in the main process as it dispatches (so a slot is taken only when needed)."""

    def __init__(self, slots: _Slots) -> None:
        self.slots = slots
        self.order: list[int] = []
        self.taken: list[int] = []

    def __iter__(self) -> Iterator[tuple[int, torch.Tensor]]:
        # Runs after DataLoader has drained the previous epoch's tasks: every slot is free again.
        self.slots.reset()
        self.taken = []
        for s in list(self.order):
            k = self.slots.take()
            self.taken.append(k)
            yield s, self.slots.bufs[k]

    def __len__(self) -> int:
        return len(self.order)


class ShardLoader:
    """Iterates the batches of a `ShardBatchSampler`, cut from whole decoded shards.

    Each epoch the plan's shards are decoded in the order the batches first need them, each
    by exactly one process: inline with `num_workers=0`, otherwise by persistent DataLoader
    workers, which decode into shared-memory slots and return only the shard index.  The
    main process keeps only the shards later batches still need and gathers each batch with
    one row copy + float32 cast per array.  Batches, their order and contents depend on
    (seed, epoch) only, never on the number of workers.  One iteration at a time: starting a
    new one ends the previous (its iterator raises if resumed).
    """

    def __init__(self, dataset: PatchDataset, batch_sampler: "ShardBatchSampler", num_workers: int = 0,
                 prefetch_shards: int = 2):
        self.dataset, self.batch_sampler, self.num_workers = dataset, batch_sampler, num_workers
        nbytes = max([dataset.shard_bytes(s) for s in range(len(dataset.shards))], default=0)
        self._slots = _Slots(nbytes, shared=num_workers > 0)
        self._dispatch = _Dispatch(self._slots)
        self._decoder = None
        self._run = 0
        if num_workers > 0:
            self._decoder = DataLoader(_ShardView(dataset), sampler=self._dispatch, batch_size=None,
                                       num_workers=num_workers, prefetch_factor=prefetch_shards,
                                       persistent_workers=True)

    def set_epoch(self, epoch: int) -> None:
        self.batch_sampler.set_epoch(epoch)

    def __len__(self) -> int:
        return len(self.batch_sampler)

    def _decoded(self, order: list[int]) -> Iterator[tuple[int, int]]:
        """(shard, slot) of each shard of `order`, decoded, in order."""
        if self._decoder is None:
            self._slots.reset()
            for s in order:
                k = self._slots.take()
                self.dataset.read_shard_into(s, self._slots.bufs[k].numpy())
                yield s, k
            return
        self._dispatch.order = order
        for i, got in enumerate(self._decoder):
            if isinstance(got, InputError):
                raise got
            yield got, self._dispatch.taken[i]

    def __iter__(self) -> Iterator[dict[str, torch.Tensor]]:
        self._run += 1
        run, ds = self._run, self.dataset
        offsets = ds.offsets
        batches = self.batch_sampler.plan()
        runs = []  # per batch: [(shard, start, stop)], maximal stretches of one shard
        order: list[int] = []
        last_use: dict[int, int] = {}
        for b, idx in enumerate(batches):
            shard = np.searchsorted(offsets, idx, side="right") - 1
            cut = np.concatenate([[0], np.flatnonzero(np.diff(shard)) + 1, [len(idx)]])
            runs.append([(int(shard[a]), int(a), int(z)) for a, z in zip(cut[:-1], cut[1:])])
            for s, _, _ in runs[-1]:
                if s not in last_use:
                    order.append(s)
                last_use[s] = b
        if ds.is_cached:  # the decoded corpus is in memory: batches gather straight from it, no slots
            for b, idx in enumerate(batches):
                if run != self._run:
                    raise RuntimeError("this ShardLoader iteration was superseded by a newer one")
                yield _assemble(idx, runs[b], {s: ds.cached_views(s) for s, _, _ in runs[b]}, ds.meta, offsets)
            return
        stream = self._decoded(order)
        live: dict[int, dict[str, np.ndarray]] = {}
        slot_of: dict[int, int] = {}
        for b, idx in enumerate(batches):
            if run != self._run:  # its slots and the workers now serve the newer iteration
                raise RuntimeError("this ShardLoader iteration was superseded by a newer one")
            for s, _, _ in runs[b]:
                while s not in live:
                    got, k = next(stream)
                    live[got] = _slot_views(self._slots.bufs[k].numpy(), ds.meta[got]["layout"])
                    slot_of[got] = k
            yield _assemble(idx, runs[b], live, ds.meta, offsets)
            for s, _, _ in runs[b]:
                if last_use[s] == b and s in live:
                    del live[s]
                    self._slots.give(slot_of.pop(s))


def make_loader(ds: PatchDataset, batch_size: int, shuffle: bool = True, num_workers: int = 0, seed: int = 0,
                drop_last: bool = False, window: int | None = 4) -> ShardLoader:
    """The fast way to iterate a PatchDataset: `ShardBatchSampler` batches cut from whole decoded shards.
    `window`: shards shuffled together (None: the whole corpus, i.i.d. batches)."""
    sampler = ShardBatchSampler(ds, batch_size, shuffle=shuffle, seed=seed, drop_last=drop_last,
                                interleave=window)
    return ShardLoader(ds, sampler, num_workers=num_workers)


class ShardBatchSampler(Sampler[list[int]]):
    """Batches of exactly `batch_size` patches, drawn a few shards at a time (or, with
    `interleave=None`, i.i.d. from the whole corpus: meant for a corpus kept decoded in memory).

    Each epoch: shards in random order, taken in windows of `interleave`;
    within a window every shard's patches are shuffled, laid end to end and
    cut into batches, and the window's batches are shuffled together.  A
    window's remainder (fewer than `batch_size`) is carried into the next
    window, so every batch has the requested size — one at a shard boundary
    spans two shards — except the epoch's last, which `drop_last` drops.  Why
    windows: a batch needs one or two decoded shards, and only a window (plus
    the carried shard) is held decoded at a time — by `ShardLoader`, or in the
    dataset's LRU when a plain DataLoader uses this sampler — so every shard is
    decompressed once per epoch while consecutive batches still come from
    different objects.  `plan()` is a pure function of (seed, epoch).
    """

    def __init__(self, dataset: PatchDataset, batch_size: int, shuffle: bool = True, seed: int = 0,
                 drop_last: bool = False, interleave: int | None = 4):
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.ds, self.bs, self.shuffle, self.seed, self.drop_last = dataset, batch_size, shuffle, seed, drop_last
        n = len(dataset.shards)
        self.whole_corpus = interleave is None
        if interleave is None:  # the whole corpus in one window: i.i.d. batches
            self.interleave = max(1, n)
        else:
            cap = max(1, getattr(dataset, "decoded_shards", interleave + 1) - 1)  # room for the carried shard
            self.interleave = max(1, min(interleave, cap))
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def plan(self) -> list[np.ndarray]:
        """This epoch's batches as arrays of dataset indices (a pure function of seed and epoch)."""
        rng = np.random.default_rng([self.seed, self.epoch])
        n = len(self.ds.shards)
        if self.shuffle and self.whole_corpus:  # i.i.d.: any patch next to any other
            flat = rng.permutation(int(self.ds.offsets[-1])).astype(np.int64)
            batches = [flat[a:a + self.bs] for a in range(0, len(flat), self.bs)]
            if batches and self.drop_last and len(batches[-1]) < self.bs:
                batches.pop()
            return batches
        order = rng.permutation(n) if self.shuffle else np.arange(n)
        batches, carry = [], np.zeros(0, np.int64)
        for w in range(0, n, self.interleave):
            parts = [carry]
            for s in order[w:w + self.interleave]:
                idx = np.arange(int(self.ds.offsets[s]), int(self.ds.offsets[s + 1]), dtype=np.int64)
                if self.shuffle:
                    rng.shuffle(idx)
                parts.append(idx)
            flat = np.concatenate(parts)
            full = len(flat) // self.bs
            window = [flat[b * self.bs:(b + 1) * self.bs] for b in range(full)]
            carry = flat[full * self.bs:]
            if self.shuffle:
                window = [window[i] for i in rng.permutation(len(window))]
            batches.extend(window)
        if len(carry) and not self.drop_last:
            batches.append(carry)
        return batches

    def __iter__(self) -> Iterator[list[int]]:
        yield from (b.tolist() for b in self.plan())

    def __len__(self) -> int:
        n = int(self.ds.offsets[-1])
        return n // self.bs if self.drop_last else -(-n // self.bs)


def iter_frames(root: str | Path, condition: str | None = None) -> Iterator[WholeFrame]:
    """Whole frames of a dataset stored with `store_frames = true`."""
    for path, _, _ in _shard_list(Path(root), condition):
        yield from iter_whole_frames(path)
