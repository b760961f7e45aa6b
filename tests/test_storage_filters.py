"""Issue 21, loader: selectable HDF5 filters per corpus (lzf, gzip, zstd, blosc2-lz4, none)."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from cli_helpers import cli, one_line_error
from msps_render.dataset import open_shard, read_patches, schema as K
from msps_render.dataset.schema import FrameRecord, Patches, ShardContent
from msps_render.dataset.writer import write_shard

FILTERS = ("lzf", "gzip", "zstd", "blosc2-lz4", "none")
# the HDF5 filter ids each value must put on the patch arrays (h5py's names / registered plugin ids)
FILTER_IDS = {"lzf": 32000, "gzip": 1, "zstd": 32015, "blosc2-lz4": 32026}


def _content(n: int = 40, p: int = 8) -> ShardContent:
    rng = np.random.default_rng(0)
    # smooth-ish radiance (compressible like a render) plus noise in the low bits
    base = np.linspace(0.0, 2.0, p * p * 3, dtype=np.float32).reshape(p, p, 3)
    image = (base[None] * rng.uniform(0.5, 1.5, (n, 1, 1, 1)) + rng.normal(0, 0.01, (n, p, p, 3))).astype(np.float32)
    normal = rng.normal(size=(n, p, p, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    mask = (rng.uniform(size=(n, p, p)) > 0.2).astype(np.uint8)
    patches = Patches(image=image, normal=normal, mask=mask, yx=np.zeros((n, 2), np.int32))
    frames = [FrameRecord(light_dirs=np.eye(3, dtype=np.float32), crosstalk=np.eye(3, dtype=np.float32),
                        light_rgb=np.eye(3, dtype=np.float32), slant_deg=30.0, env_ratio=0.0,
                        env_rotation_deg=0.0, spp=4, frame_seed=1, scene_json="{}", object="blob",
                        materials="m", condition="c")]
    return ShardContent(patches=patches, frames=frames, frame_index=np.zeros(n, np.int32), attrs={})


def _old_create_array(group, name, data, compression, chunks=None):
    """The writer's filter code before issue 21 (lzf/gzip + shuffle + fletcher32): what old corpora hold."""
    kw = {"track_times": False}
    if compression != "none" and data.ndim >= 1 and data.size > 0:
        kw.update(compression="gzip" if compression == "gzip" else "lzf", shuffle=True, fletcher32=True,
                  chunks=chunks or True)
        if compression == "gzip":
            kw["compression_opts"] = 4
    elif data.size > 0 and data.ndim >= 1:
        kw.update(fletcher32=True, chunks=chunks or True)
    return group.create_dataset(name, data=data, **kw)


@pytest.mark.parametrize("compression", FILTERS)
def test_round_trip_per_filter(tmp_path, compression):
    """Every filter gives back the stored float16/uint8 arrays exactly, carries the expected HDF5 filter
    and the fletcher32 checksum, and compresses where it should."""
    c = _content()
    info = write_shard(tmp_path / "s.h5", c, compression=compression)
    with open_shard(tmp_path / "s.h5") as h:
        got = read_patches(h)
        filters = h[K.PATCH_IMAGE].id.get_create_plist().get_nfilters()
        ids = [h[K.PATCH_IMAGE].id.get_create_plist().get_filter(i)[0] for i in range(filters)]
        stored = h[K.PATCH_IMAGE].id.get_storage_size()
    assert np.array_equal(got["image"], c.patches.image.astype(np.float16))
    assert np.array_equal(got["normal"], c.patches.normal.astype(np.float16))
    assert np.array_equal(got["mask"], c.patches.mask)
    assert 3 in ids  # H5Z_FILTER_FLETCHER32 on every filter, "none" included
    raw = c.patches.image.astype(np.float16).nbytes
    if compression == "none":
        assert ids == [3] and stored >= raw
    else:
        assert FILTER_IDS[compression] in ids
        assert stored < 0.9 * raw, (compression, stored, raw)  # the smooth test radiance compresses
    assert info["n_patches"] == 40


def test_lzf_shards_written_before_still_read_and_are_unchanged(tmp_path, monkeypatch):
    """A shard written by the pre-issue-21 filter code reads back through today's reader, and today's
    lzf / gzip / none shards are byte-identical to it (existing corpora and their digests stay valid)."""
    from msps_render.dataset import writer

    c = _content()
    for comp in ("lzf", "gzip", "none"):
        new = tmp_path / f"new-{comp}.h5"
        write_shard(new, c, compression=comp)
        with monkeypatch.context() as m:
            m.setattr(writer, "create_array", _old_create_array)
            old = tmp_path / f"old-{comp}.h5"
            write_shard(old, c, compression=comp)
        assert new.read_bytes() == old.read_bytes(), comp
        with open_shard(old) as h:
            assert np.array_equal(read_patches(h)["image"], c.patches.image.astype(np.float16))


def test_reader_registers_the_plugin_filters_itself(tmp_path):
    """A fresh process that never imports hdf5plugin itself opens zstd and Blosc2 shards through
    `open_shard` (the reader imports it)."""
    for comp in ("zstd", "blosc2-lz4"):
        write_shard(tmp_path / f"{comp}.h5", _content(), compression=comp)
    code = ("import sys; from msps_render.dataset import open_shard, read_patches\n"
            "assert 'hdf5plugin' not in sys.modules\n"
            f"for c in ('zstd', 'blosc2-lz4'):\n"
            f"    with open_shard(r'{tmp_path}/' + c + '.h5') as h:\n"
            "        print(c, float(read_patches(h)['image'].astype('float64').sum()))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-1500:]
    sums = [float(line.split()[1]) for line in r.stdout.splitlines()]
    assert len(sums) == 2 and sums[0] == sums[1] > 0


def test_unknown_filter_is_one_line_and_exit_1(tmp_path):
    r = cli("config", "show", "train", "--set", "dataset.storage.compression=snappy")
    line = one_line_error(r)
    assert "dataset.storage.compression" in line and "'zstd'" in line and "'blosc2-lz4'" in line
    out = tmp_path / "out"
    r = cli("render", "train", "--out", out, "--set", "dataset.storage.compression=snappy",
            "--set", "dataset.n_shards=1")
    assert "dataset.storage.compression" in one_line_error(r)
    assert not out.exists()  # nothing half-written
    with pytest.raises(ValueError, match="compression must be one of"):
        write_shard(tmp_path / "x.h5", _content(), compression="snappy")
    assert not (tmp_path / "x.h5").exists()


@pytest.mark.slow
def test_corpus_with_plugin_filters_streams_through_the_loader(tmp_path):
    """Tiny rendered corpora stored with each plugin filter: `msps verify` passes and `make_loader` with
    two workers yields every patch, equal batch for batch to the same corpus stored with lzf."""
    from cli_helpers import render_tiny

    from msps_render.data import PatchDataset, make_loader
    from msps_render.dataset import verify_dataset

    base = ('[dataset]\nname = "t"\nseed = 3\nn_shards = 2\nframes_per_shard = 1\n'
            '[dataset.patches]\nsize = 16\nstride = 8\nmin_coverage = 0.3\n'
            '[dataset.storage]\ncompression = "{c}"\n[scene.shape]\nsource = "primitive"\n'
            'primitives = ["torus", "capsule"]\n'
            '[scene.camera]\nwidth = 32\nheight = 32\n[scene.integrator]\nspp = 4\nmax_depth = 2\n')
    batches = {}
    for name in ("lzf", "zstd", "blosc2-lz4"):
        render_tiny(base.format(c=name), tmp_path, name)
        assert verify_dataset(tmp_path / name) == {}
        ds = PatchDataset(tmp_path / name)
        batches[name] = [b["image"] for b in make_loader(ds, 16, num_workers=2, seed=0)]
        assert sum(len(b) for b in batches[name]) == len(ds) > 0
    for name in ("zstd", "blosc2-lz4"):
        assert len(batches[name]) == len(batches["lzf"])
        for a, b in zip(batches["lzf"], batches[name]):
            assert torch_equal(a, b)


def torch_equal(a, b) -> bool:
    return bool((a == b).all())
