"""`ShardBatchSampler` / `make_loader` (issue 13): batches of the requested size, across shard boundaries."""
from __future__ import annotations

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
