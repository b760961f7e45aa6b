"""`ShardBatchSampler` / `make_loader` (issues 12, 13): batches of the requested size, across shard boundaries,
every patch once per epoch, the same batches with 0 or 2 workers, each shard decoded once by one process."""
from __future__ import annotations

import os
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("torch")


def fake_dataset(sizes):
    """What the sampler reads of a PatchDataset: its shard list and patch offsets."""
    return SimpleNamespace(shards=[None] * len(sizes), offsets=np.concatenate([[0], np.cumsum(sizes)]),
                           decoded_shards=8)


@pytest.mark.parametrize("shuffle", [True, False])
@pytest.mark.parametrize("sizes", [[7, 30, 1, 16, 0, 45, 3, 9, 22], [16, 16, 16], [5], [100, 3, 3, 3, 3, 3]])
def test_batches_have_the_requested_size_and_cover_every_patch_once(sizes, shuffle):
    from msps_render.data import ShardBatchSampler

    ds = fake_dataset(sizes)
    total = sum(sizes)
    for epoch in range(3):
        s = ShardBatchSampler(ds, 16, shuffle=shuffle, seed=4)
        s.set_epoch(epoch)
        batches = list(s)
        assert [len(b) for b in batches[:-1]] == [16] * (len(batches) - 1)
        assert 1 <= len(batches[-1]) <= 16
        flat = [i for b in batches for i in b]
        assert sorted(flat) == list(range(total))  # every patch exactly once
        assert len(s) == len(batches) == -(-total // 16)
        dl = ShardBatchSampler(ds, 16, shuffle=shuffle, seed=4, drop_last=True)
        dl.set_epoch(epoch)
        kept = list(dl)
        assert all(len(b) == 16 for b in kept) and len(kept) == total // 16  # drops < 16 patches, once
        assert len(set(i for b in kept for i in b)) == 16 * len(kept)
    if not shuffle:
        assert flat == list(range(total))  # unshuffled: dataset order


def test_batches_span_at_most_two_shards_when_shards_exceed_the_batch():
    from msps_render.data import ShardBatchSampler

    ds = fake_dataset([40, 33, 57, 21, 64, 18])
    shard_of = np.searchsorted(ds.offsets, np.arange(int(ds.offsets[-1])), side="right") - 1
    for epoch in range(5):
        s = ShardBatchSampler(ds, 16, seed=1)
        s.set_epoch(epoch)
        assert max(len(set(shard_of[b].tolist())) for b in s) <= 2


def test_same_seed_and_epoch_same_batches():
    from msps_render.data import ShardBatchSampler

    ds = fake_dataset([7, 30, 1, 16, 45])
    a, b = ShardBatchSampler(ds, 8, seed=3), ShardBatchSampler(ds, 8, seed=3)
    assert list(a) == list(b)
    b.set_epoch(1)
    assert list(a) != list(b)


# ---------------------------------------------------------------- make_loader on real (synthetic) shards
P = 8


def write_dataset(root, sizes, image_dtype="float16", seed=0, start=0):
    """A dataset directory of shards with `sizes` patches; patch i's image is filled with its
    dataset index (`start` + i, exact in float16 below 2048), so content can be traced."""
    from msps_render.dataset import FrameRecord, Patches, ShardContent, write_manifest, write_shard

    rng = np.random.default_rng(seed)
    (root / "shards").mkdir(parents=True)
    entries, i0 = {}, start
    for k, n in enumerate(sizes):
        frames = 3
        nrm = rng.normal(size=(n, P, P, 3))
        nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
        image = np.broadcast_to(np.arange(i0, i0 + n, dtype=np.float32)[:, None, None, None], (n, P, P, 3))
        pat = Patches(image=image + rng.uniform(0, 0.25, (n, P, P, 3)).astype(np.float32),
                      normal=nrm.astype(np.float32), mask=rng.integers(0, 2, (n, P, P)).astype(np.uint8),
                      yx=np.zeros((n, 2), np.int32))
        recs = [FrameRecord(scene_json="{}", light_dirs=np.eye(3) * (k + 1) + j, crosstalk=np.eye(3) * (j + 1),
                            light_rgb=np.eye(3), slant_deg=30.0, env_ratio=0.0, env_rotation_deg=0.0, spp=4,
                            frame_seed=j, object=f"o{j}", materials="m") for j in range(frames)]
        name = f"shard-{k:05d}.h5"
        info = write_shard(root / "shards" / name, ShardContent(pat, rng.integers(0, frames, n).astype(np.int32),
                                                                 recs), image_dtype=image_dtype)
        entries[name] = {"n_patches": n, "n_frames": frames, "condition": "", "file_sha256": info["file_sha256"]}
        i0 += n
    write_manifest(root, {"complete": True, "shards": entries})
    return root


SIZES = [7, 30, 1, 16, 0, 45, 3, 9, 22, 40]


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory):
    return write_dataset(tmp_path_factory.mktemp("loader") / "ds", SIZES)


def epoch_batches(loader, epoch):
    loader.set_epoch(epoch)
    return list(loader)


def test_make_loader_batches_equal_the_plan_for_0_and_2_workers(dataset_dir):
    """Every patch once per epoch, exact batch sizes, the sampler's order, the per-item
    contents, shapes and dtypes; and the same batches whatever the number of workers."""
    import torch

    from msps_render.data import PatchDataset, make_loader

    ds = PatchDataset(dataset_dir)
    total = sum(SIZES)
    for drop_last in (False, True):
        runs = {w: make_loader(ds, 16, seed=5, num_workers=w, drop_last=drop_last) for w in (0, 2)}
        for epoch in range(2):
            got = {w: epoch_batches(dl, epoch) for w, dl in runs.items()}
            plan = runs[0].batch_sampler.plan()
            assert [b["index"].tolist() for b in got[0]] == [p.tolist() for p in plan]
            sizes = [len(b["index"]) for b in got[0]]
            if drop_last:
                assert sizes == [16] * (total // 16)
            else:
                assert sizes[:-1] == [16] * (len(sizes) - 1) and sizes[-1] == total - 16 * (len(sizes) - 1)
                assert sorted(torch.cat([b["index"] for b in got[0]]).tolist()) == list(range(total))
            assert len(got[0]) == len(got[2]) == len(runs[0])
            for a, b in zip(got[0], got[2]):
                assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
            for b in got[0]:
                ref = ds.get_batch(b["index"].numpy())  # the per-shard fancy-index path
                assert b.keys() == ref.keys()
                for k in b:
                    assert b[k].dtype == ref[k].dtype and torch.equal(b[k], ref[k]), k
                n = len(b["index"])
                assert b["image"].shape == b["normal"].shape == (n, 3, P, P) and b["mask"].shape == (n, 1, P, P)
                assert b["image"].dtype == b["mask"].dtype == torch.float32 and b["light_dirs"].shape == (n, 3, 3)
                assert torch.equal(b["image"][:, 0, 0, 0].floor().long(), b["index"])  # traced content


def test_make_loader_is_deterministic_from_the_seed(dataset_dir):
    from msps_render.data import PatchDataset, make_loader

    ds = PatchDataset(dataset_dir)
    order = lambda dl, e: [b["index"].tolist() for b in epoch_batches(dl, e)]  # noqa: E731
    a, b, c = make_loader(ds, 8, seed=3), make_loader(ds, 8, seed=3), make_loader(ds, 8, seed=4)
    assert order(a, 0) == order(b, 0) and order(a, 1) == order(b, 1)
    assert order(a, 0) != order(a, 1) and order(a, 0) != order(c, 0)
    flat = [i for batch in order(make_loader(ds, 8, shuffle=False), 0) for i in batch]
    assert flat == list(range(sum(SIZES)))  # unshuffled: dataset order


class LoggingDataset:
    """Wraps `read_shard_into` to log (pid, shard) of each decode to a file (workers are processes)."""

    @staticmethod
    def make(root, log):
        from msps_render.data import PatchDataset

        class Logged(PatchDataset):
            def read_shard_into(self, s, buf):
                with open(log, "a") as f:
                    f.write(f"{os.getpid()} {s}\n")
                return super().read_shard_into(s, buf)

        return Logged(root)


def decodes(log):
    rows = [line.split() for line in log.read_text().splitlines()] if log.exists() else []
    log.unlink(missing_ok=True)
    return [(int(p), int(s)) for p, s in rows]


def test_workers_decode_disjoint_shards_each_once_per_epoch(dataset_dir, tmp_path):
    log = tmp_path / "decodes.txt"
    ds = LoggingDataset.make(dataset_dir, log)
    from msps_render.data import make_loader

    dl = make_loader(ds, 16, seed=1, num_workers=2)
    non_empty = [s for s, n in enumerate(SIZES) if n]
    for epoch in range(2):
        n = sum(len(b["index"]) for b in epoch_batches(dl, epoch))
        assert n == sum(SIZES)
        got = decodes(log)
        assert sorted(s for _, s in got) == non_empty  # every shard decoded exactly once
        pids = {p for p, _ in got}
        assert len(pids) == 2 and os.getpid() not in pids  # both workers did their share
    inline = make_loader(ds, 16, seed=1)
    list(inline)
    got = decodes(log)
    assert sorted(s for _, s in got) == non_empty and {p for p, _ in got} == {os.getpid()}


def test_an_abandoned_epoch_frees_its_slots_and_cannot_be_resumed(dataset_dir):
    import torch

    from msps_render.data import PatchDataset, make_loader

    ds = PatchDataset(dataset_dir)
    for workers in (0, 2):
        dl = make_loader(ds, 8, seed=2, num_workers=workers)
        for epoch in range(3):  # break early twice: slots and workers are reused each time
            dl.set_epoch(epoch)
            it = iter(dl)
            next(it), next(it)
        full = epoch_batches(dl, 3)
        assert sorted(torch.cat([b["index"] for b in full]).tolist()) == list(range(sum(SIZES)))
        assert len(dl._slots.bufs) <= 8  # a window of shards + carried + prefetched, not one per shard
        with pytest.raises(RuntimeError, match="superseded"):
            next(it)


def test_cache_and_mixed_dtype_roots_give_the_same_batches(dataset_dir, tmp_path):
    """cache=True reads from memory; a float32-stored supplement read with a float16 corpus."""
    import torch

    from msps_render.data import PatchDataset, make_loader

    extra = write_dataset(tmp_path / "f32", [12, 50], image_dtype="float32", seed=1, start=sum(SIZES))
    plain, cached = PatchDataset([dataset_dir, extra]), PatchDataset([dataset_dir, extra], cache=True)
    for workers in (0, 2):
        a = list(make_loader(plain, 16, seed=7, num_workers=workers))
        b = list(make_loader(cached, 16, seed=7, num_workers=workers))
        assert len(a) == len(b) == -(-len(plain) // 16)
        for x, y in zip(a, b):
            assert all(torch.equal(x[k], y[k]) for k in x)
            assert torch.equal(x["image"], plain.get_batch(x["index"].numpy())["image"])
            assert torch.equal(x["image"][:, 0, 0, 0].floor().long(), x["index"])


def test_whole_corpus_window_gives_iid_batches(dataset_dir, tmp_path):
    """`window=None` (`train.shuffle_window = 0`): one shuffle over every shard, so a batch mixes
    shards (two corpora read as one are interleaved from the first batch on), every patch once,
    the same batches read from the cache or decoded, and windows of 4 keep batches within ~1-2
    shards (what made multi-corpus training swing between corpora)."""
    import torch

    from msps_render.data import PatchDataset, make_loader

    extra = write_dataset(tmp_path / "b", [40, 40, 40], seed=2, start=sum(SIZES))
    plain, cached = PatchDataset([dataset_dir, extra]), PatchDataset([dataset_dir, extra], cache=True)
    n_a = len(PatchDataset(dataset_dir))
    a = list(make_loader(plain, 16, seed=3, window=None))
    b = list(make_loader(cached, 16, seed=3, window=None))
    assert len(a) == len(b) == -(-len(plain) // 16)
    for x, y in zip(a, b):
        assert all(torch.equal(x[k], y[k]) for k in x)
    idx = torch.cat([x["index"] for x in a])
    assert sorted(idx.tolist()) == list(range(len(plain)))
    shards_per_batch = [len(set(x["shard"].tolist())) for x in a[:-1]]
    both_corpora = [bool((x["index"] < n_a).any() and (x["index"] >= n_a).any()) for x in a[:-1]]
    windowed = [len(set(x["shard"].tolist())) for x in list(make_loader(plain, 16, seed=3))[:-1]]
    assert np.mean(shards_per_batch) > 2 * np.mean(windowed), (shards_per_batch, windowed)
    assert np.mean(both_corpora) > 0.5


@pytest.mark.parametrize("workers", [0, 2])
def test_a_corrupted_shard_is_one_line_naming_it(dataset_dir, tmp_path, workers):
    import shutil

    from msps_render.data import PatchDataset, make_loader
    from msps_render.errors import InputError
    from msps_render.testing import corrupt_patch_chunk

    out = tmp_path / "ds"
    shutil.copytree(dataset_dir, out)
    shard = out / "shards" / "shard-00005.h5"
    corrupt_patch_chunk(shard, 1)
    with pytest.raises(InputError, match=r"shard-00005\.h5: unreadable shard") as e:
        list(make_loader(PatchDataset(out), 16, num_workers=workers))
    assert "\n" not in str(e.value)


def test_decoded_bytes_and_the_auto_cache_rule(dataset_dir):
    """`decoded_bytes` is what `cache=True` really holds; `train.cache = "auto"` keeps a corpus
    decoded only when it takes at most 40 % of the available memory."""
    from msps_render.data import PatchDataset, available_memory_bytes, should_cache

    ds = PatchDataset(dataset_dir, cache=True)
    held = sum(a.nbytes for shard in ds._cache for k, a in shard.items() if k in ("image", "normal", "mask"))
    assert ds.decoded_bytes() == held > 0
    assert should_cache(400, 1000) and not should_cache(401, 1000) and not should_cache(1, 0)
    assert available_memory_bytes() > 0  # Linux: /proc/meminfo


@pytest.mark.parametrize("shape", [(0, 40, 40, 3), (1, 200, 200, 3), (64, 40, 40, 3), (7, 3), (5,)])
def test_batch_cast_in_pieces_equals_one_cast(shape):
    """`data._float32` casts in pieces of at most CAST_GRAIN elements (one thread each, docs/benchmarks.md
    "Loader under load"): the same float32 values as one cast, for rows smaller and larger than a piece."""
    from msps_render.data import _float32

    rows = np.random.default_rng(0).normal(size=shape).astype(np.float16)
    out = np.full(shape, np.nan, np.float32)
    _float32(rows, out)
    assert np.array_equal(out, rows.astype(np.float32))
