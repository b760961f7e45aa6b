"""msps_render.dataset on synthetic content: write -> read round trip, verification, the typed
manifest (typed sweep conditions, and the fallback for manifests written before them)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from msps_render.dataset import (FrameRecord, Patches, ShardContent, iter_whole_frames, load_manifest,
                                 read_digests, read_patch_rows, read_shard_calibration, verify_shard,
                                 write_manifest, write_shard)
from msps_render.dataset import schema as K
from msps_render.errors import InputError


def _content(n=5, p=8, frames=2, whole=True) -> ShardContent:
    rng = np.random.default_rng(0)
    nrm = rng.normal(size=(n, p, p, 3))
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    pat = Patches(image=rng.uniform(0, 2, (n, p, p, 3)).astype(np.float32), normal=nrm.astype(np.float32),
                  mask=np.ones((n, p, p), np.uint8), yx=rng.integers(0, 30, (n, 2)).astype(np.int32))
    recs = [FrameRecord(scene_json="{}", light_dirs=np.eye(3), crosstalk=np.eye(3) * 0.9 + 0.03,
                        light_rgb=np.eye(3), slant_deg=30.0, env_ratio=0.0, env_rotation_deg=0.0, spp=4,
                        frame_seed=j, object=f"obj{j}", materials="a;b", condition="slant_deg=30.0",
                        image=np.full((16, 16, 3), j, np.float32) if whole else None,
                        normal=np.tile(np.array([0, 0, 1], np.float32), (16, 16, 1)) if whole else None,
                        mask=np.ones((16, 16), bool) if whole else None) for j in range(frames)]
    return ShardContent(pat, np.arange(n, dtype=np.int32) % frames, recs, {"seed": 1})


def test_write_read_round_trip_and_verify(tmp_path):
    c = _content()
    info = write_shard(tmp_path / "s.h5", c, image_dtype="float32", normal_dtype="float32")
    pat, fi = read_patch_rows(tmp_path / "s.h5")
    assert np.array_equal(pat.image, c.patches.image) and np.array_equal(pat.yx, c.patches.yx)
    assert np.array_equal(fi, c.frame_index)
    cal = read_shard_calibration(tmp_path / "s.h5")
    assert cal["crosstalk"].shape == (2, 3, 3) and np.allclose(cal["light_dirs"][1], np.eye(3))
    frames = list(iter_whole_frames(tmp_path / "s.h5"))
    assert [f.object for f in frames] == ["obj0", "obj1"] and frames[1].image.max() == 1
    assert verify_shard(tmp_path / "s.h5", info["file_sha256"]) == []
    assert read_digests(tmp_path / "s.h5")[K.PATCH_IMAGE] == info["arrays"][K.PATCH_IMAGE]
    # same content, same bytes
    write_shard(tmp_path / "t.h5", c, image_dtype="float32", normal_dtype="float32")
    assert (tmp_path / "s.h5").read_bytes() == (tmp_path / "t.h5").read_bytes()


def test_shard_without_whole_frames_and_bad_file(tmp_path):
    write_shard(tmp_path / "s.h5", _content(whole=False))
    with pytest.raises(InputError, match="no whole frames"):
        list(iter_whole_frames(tmp_path / "s.h5"))
    (tmp_path / "bad.h5").write_bytes(b"not hdf5")
    with pytest.raises(InputError, match="bad.h5: unreadable shard"):
        read_patch_rows(tmp_path / "bad.h5")
    assert verify_shard(tmp_path / "missing.h5") == ["missing"]


def test_manifest_typed_conditions_new_and_old(tmp_path):
    new = {"complete": True, "conditions": ["ratio=0.0", "ratio=0.5"], "shards": {},
           "condition_values": {"ratio=0.0": {"key": "environment.ratio", "value": 0.0},
                                "ratio=0.5": {"key": "environment.ratio", "value": 0.5}}}
    write_manifest(tmp_path, new)
    m = load_manifest(tmp_path)
    assert [(c.name, c.key, c.value) for c in m.conditions] == [("ratio=0.0", "environment.ratio", 0.0),
                                                              ("ratio=0.5", "environment.ratio", 0.5)]
    old = {"complete": True, "conditions": ["slant_deg=20.0", "slant_deg=40.0"], "shards": {},
           "config": {"sweep": {"key": "lights.slant_deg", "values": [20.0, 40.0]}}}
    (tmp_path / "dataset.json").write_text(json.dumps(old))
    assert [c.value for c in load_manifest(tmp_path).conditions] == [20.0, 40.0]
    (tmp_path / "dataset.json").write_text(json.dumps({**old, "complete": False}))
    with pytest.raises(InputError, match="incomplete"):
        load_manifest(tmp_path)


def test_per_light_round_trip_and_overflow(tmp_path):
    """frames/per_light and frames/env_image: written in image_dtype, read only when asked, and a
    shard without them (every older shard) reads with None."""
    import dataclasses

    import h5py

    c = _content()
    rng = np.random.default_rng(1)
    recs = [dataclasses.replace(f, per_light=rng.uniform(0, 1, (3, 16, 16, 3)).astype(np.float32),
                                env_image=None if j == 0 else np.full((16, 16, 3), 0.25, np.float32))
            for j, f in enumerate(c.frames)]
    info = write_shard(tmp_path / "s.h5", dataclasses.replace(c, frames=recs))
    assert K.FRAME_PER_LIGHT in info["arrays"] and K.FRAME_ENV_IMAGE in info["arrays"]
    with h5py.File(tmp_path / "s.h5", "r") as h:
        assert h[K.FRAME_PER_LIGHT].dtype == np.float16 and h[K.FRAME_PER_LIGHT].shape == (2, 3, 16, 16, 3)
    assert verify_shard(tmp_path / "s.h5", info["file_sha256"]) == []
    frames = list(iter_whole_frames(tmp_path / "s.h5", per_light=True))
    for f, r in zip(frames, recs):
        assert np.array_equal(f.per_light, r.per_light.astype(np.float16).astype(np.float32))
    assert not frames[0].env_image.any() and (frames[1].env_image == 0.25).all()  # zeros: no environment
    assert all(f.per_light is None for f in iter_whole_frames(tmp_path / "s.h5"))
    write_shard(tmp_path / "old.h5", c)  # no per-light images
    assert all(f.per_light is None and f.env_image is None
               for f in iter_whole_frames(tmp_path / "old.h5", per_light=True))
    hot = [dataclasses.replace(r, per_light=r.per_light * 1e5) for r in recs]
    with pytest.raises(ValueError, match="float16"):
        write_shard(tmp_path / "hot.h5", dataclasses.replace(c, frames=hot))
    assert not (tmp_path / "hot.h5").exists()


def test_verify_names_non_finite_and_negative_float16_radiance(tmp_path):
    """`msps verify` reads float16 patches by their bits: a NaN in one patch, +inf in another and a negative
    value are each named; -0 is not negative."""
    import h5py

    write_shard(tmp_path / "s.h5", _content())  # float16 patches (the default)
    assert verify_shard(tmp_path / "s.h5") == []
    with h5py.File(tmp_path / "s.h5", "r+") as h:
        img = h[K.PATCH_IMAGE][()]
        img[0, 0, 0, 0], img[3, 1, 1, 2], img[2, 0, 0, 1] = -0.0, np.nan, np.inf
        h[K.PATCH_IMAGE][...] = img
    assert verify_shard(tmp_path / "s.h5") == ["2 patches with NaN/inf radiance"]
    with h5py.File(tmp_path / "s.h5", "r+") as h:
        img[3, 1, 1, 2] = img[2, 0, 0, 1] = 1.0
        img[4, 2, 2, 0] = -np.float16(6e-8)  # the smallest subnormal, below zero
        h[K.PATCH_IMAGE][...] = img
    assert verify_shard(tmp_path / "s.h5") == ["negative radiance"]
