"""Training-side access to a dataset directory: `PatchDataset` (torch) and whole-frame iteration.

h5py handles are opened lazily in whichever process reads (DataLoader workers
fork/spawn after construction, and HDF5 handles must not cross processes).
`__getitems__` reads a whole batch from each shard with one sorted
fancy-index read per array, and `ShardBatchSampler` keeps each batch inside one
shard (two at a shard boundary), so random access costs one HDF5 read per batch
instead of per patch.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset, Sampler

from msps_render.dataset import (SHARD_DIR, WholeFrame, iter_whole_frames, load_manifest, open_shard,
                                 read_patches, read_shard_calibration, read_shard_patches, shard_errors,
                                 verify_dataset)
from msps_render.errors import InputError


def _shard_list(root: Path, condition: str | None) -> list[tuple[Path, int, str]]:
    m = load_manifest(root)
    return [(m.shard_path(e.name), e.n_patches, e.condition) for e in m.shards_of(condition)]


class PatchDataset(Dataset):
    """Patches of a dataset directory as dicts of tensors:

    image (3,P,P) float32 linear radiance, normal (3,P,P), mask (1,P,P) float32,
    light_dirs (3,3), crosstalk (3,3), plus shard/frame/index ids.
    """

    decoded_shards = 8  # LRU size of decoded shards per process (~12 MB each for 8x128^2 frames)

    def __init__(self, root: str | Path | Sequence[str | Path], condition: str | None = None,
                 cache: bool = False, verify: bool = False):
        """`root`: one dataset directory, or several read as one (e.g. a corpus plus a supplement)."""
        roots = [Path(root)] if isinstance(root, (str, os.PathLike)) else [Path(r) for r in root]
        if not roots:
            raise ValueError("PatchDataset needs at least one dataset directory")
        self.roots, self.root = roots, roots[0]
        self.shards = []
        for r in roots:
            if verify:
                bad = verify_dataset(r)
                if bad:
                    name, probs = sorted(bad.items())[0]
                    raise InputError(r / SHARD_DIR / name, f"fails verification: {'; '.join(probs)}")
            self.shards += _shard_list(r, condition)
        counts = np.array([n for _, n, _ in self.shards], dtype=np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(counts)])
        self._handles: dict[int, object] = {}
        self._decoded: dict[int, dict] = {}
        self._pid = None
        self._meta = [self._read_meta(p) for p, _, _ in self.shards]
        self._cache = [self._read_all(p) for p, _, _ in self.shards] if cache else None

    # -------------------------------------------------------------- internals
    @staticmethod
    def _read_meta(path: Path) -> dict:
        return read_shard_calibration(path)

    @staticmethod
    def _read_all(path: Path) -> dict:
        return read_shard_patches(path)

    def _h(self, s: int):
        if self._pid != os.getpid():  # new process (DataLoader worker): reopen everything
            self._handles, self._decoded, self._pid = {}, {}, os.getpid()
        if s not in self._handles:
            self._handles[s] = open_shard(self.shards[s][0])
        return self._handles[s]

    def locate(self, idx: int) -> tuple[int, int]:
        if idx < 0:
            idx += len(self)
        if not 0 <= idx < len(self):
            raise IndexError(idx)
        s = int(np.searchsorted(self.offsets, idx, side="right") - 1)
        return s, int(idx - self.offsets[s])

    def _arrays(self, s: int, local: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self._cache is not None:
            c = self._cache[s]
        else:
            c = self._decoded.get(s)
            if c is None:
                # Decode the whole shard once: h5py fancy indexing costs ~0.3 ms per index and
                # re-reading spans re-decompresses them; ShardBatchSampler visits a shard's batches
                # close together, so a small LRU of decoded shards serves them all.
                with shard_errors(self.shards[s][0]):
                    c = read_patches(self._h(s))
                self._decoded[s] = c
                while len(self._decoded) > self.decoded_shards:
                    self._decoded.pop(next(iter(self._decoded)))
            else:
                self._decoded[s] = self._decoded.pop(s)  # most recently used
        return c["image"][local], c["normal"][local], c["mask"][local]

    def _pack(self, s: int, local: np.ndarray) -> dict:
        img, nrm, msk = self._arrays(s, local)
        meta = self._meta[s]
        f = meta["frame_index"][local]
        return {
            "image": torch.from_numpy(np.ascontiguousarray(img.transpose(0, 3, 1, 2), dtype=np.float32)),
            "normal": torch.from_numpy(np.ascontiguousarray(nrm.transpose(0, 3, 1, 2), dtype=np.float32)),
            "mask": torch.from_numpy(msk[:, None].astype(np.float32)),
            "light_dirs": torch.from_numpy(meta["light_dirs"][f].astype(np.float32)),
            "crosstalk": torch.from_numpy(meta["crosstalk"][f].astype(np.float32)),
            "shard": torch.full((len(local),), s, dtype=torch.int64),
            "frame": torch.from_numpy(f.astype(np.int64)),
            "index": torch.from_numpy(local.astype(np.int64) + self.offsets[s]),
        }

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


class _BatchView(Dataset):
    """Lets a DataLoader fetch whole batches via `get_batch` (no per-item split + re-collate)."""

    def __init__(self, ds: PatchDataset):
        self.ds = ds

    def __len__(self) -> int:
        return len(self.ds)

    def __getitems__(self, indices: list[int]) -> list[dict]:
        return [self.ds.get_batch(indices)]

    def __getitem__(self, idx: int) -> dict:  # pragma: no cover - DataLoader uses __getitems__
        return self.ds[idx]


def _first(batch: list[dict]) -> dict:
    return batch[0]


def make_loader(ds: PatchDataset, batch_size: int, shuffle: bool = True, num_workers: int = 0, seed: int = 0,
                drop_last: bool = False) -> "torch.utils.data.DataLoader":
    """The fast way to iterate a PatchDataset: shard-aware batches fetched whole."""
    from torch.utils.data import DataLoader

    sampler = ShardBatchSampler(ds, batch_size, shuffle=shuffle, seed=seed, drop_last=drop_last)
    return DataLoader(_BatchView(ds), batch_sampler=sampler, collate_fn=_first, num_workers=num_workers,
                      persistent_workers=num_workers > 0)


class ShardBatchSampler(Sampler[list[int]]):
    """Batches of exactly `batch_size` patches, drawn a few shards at a time.

    Each epoch: shards in random order, taken in windows of `interleave`;
    within a window every shard's patches are shuffled, laid end to end and
    cut into batches, and the window's batches are shuffled together.  A
    window's remainder (fewer than `batch_size`) is carried into the next
    window, so every batch has the requested size — one at a shard boundary
    spans two shards — except the epoch's last, which `drop_last` drops.  Why
    windows: a batch needs one or two decoded shards, and a window (plus the
    carried shard) fits the dataset's LRU of decoded shards, so every shard is
    decompressed once per epoch while consecutive batches still come from
    different objects.
    """

    def __init__(self, dataset: PatchDataset, batch_size: int, shuffle: bool = True, seed: int = 0,
                 drop_last: bool = False, interleave: int = 4):
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.ds, self.bs, self.shuffle, self.seed, self.drop_last = dataset, batch_size, shuffle, seed, drop_last
        cap = max(1, getattr(dataset, "decoded_shards", interleave + 1) - 1)  # room for the carried shard
        self.interleave = max(1, min(interleave, cap))
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def _batches(self) -> list[list[int]]:
        rng = np.random.default_rng([self.seed, self.epoch])
        n = len(self.ds.shards)
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
            window = [flat[b * self.bs:(b + 1) * self.bs].tolist() for b in range(full)]
            carry = flat[full * self.bs:]
            if self.shuffle:
                window = [window[i] for i in rng.permutation(len(window))]
            batches.extend(window)
        if len(carry) and not self.drop_last:
            batches.append(carry.tolist())
        return batches

    def __iter__(self) -> Iterator[list[int]]:
        yield from self._batches()

    def __len__(self) -> int:
        return len(self._batches())


def iter_frames(root: str | Path, condition: str | None = None) -> Iterator[WholeFrame]:
    """Whole frames of a dataset stored with `store_frames = true`."""
    for path, _, _ in _shard_list(Path(root), condition):
        yield from iter_whole_frames(path)
