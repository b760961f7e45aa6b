"""A render worker's memory at many lights (issue 42, ≤ 600 MiB at N = 96): what changed must not change
bytes.  The per-light images come from the tensor `mi.render` returns (not a second develop of the film),
a shard's patch images are written block by block (never concatenated), and what a worker keeps between
frames shrinks as N grows (`render/memory.py` `frame_budget`).  The peak itself is a benchmark
(`benchmarks/bench_rig.py --parts 3`, docs/benchmarks.md "Any rig"), not a timed test."""
from __future__ import annotations

import numpy as np
import pytest

from msps_render.dataset.reader import open_shard, read_digests
from msps_render.dataset.schema import FrameRecord, Patches, RowBlocks, ShardContent
from msps_render.dataset.writer import write_shard
from msps_render.render.memory import KERNEL_BUDGET, MemoryBudget, frame_budget


def test_emitter_images_from_the_render_tensor_equal_the_film_bitmap(rgb_variant):
    """The same float32 values as reading the developed film's bitmap by channel name (what msps did
    before), for 5 lights and the environment channels."""
    import mitsuba as mi

    from msps_render.pipeline.config import load_config
    from msps_render.render.multilight import read_emitter_images
    from msps_render.render.scene_dict import build_scene_dict, emitter_ids
    from msps_render.scene.sample import sample_scene

    cfg = load_config("classic-train", ["scene.rig.n_lights=5", "scene.camera.width=24", "scene.camera.height=24",
                                        "scene.integrator.spp=4", "dataset.patches.size=16",
                                        "dataset.patches.stride=8"])
    spec = sample_scene(cfg.scene, np.random.default_rng(3), seed=3, frame_index=0)
    scene = mi.load_dict(build_scene_dict(spec, mi))
    sensor = scene.sensors()[0]
    ids = emitter_ids(spec)
    got = read_emitter_images(mi.render(scene, sensor=sensor, spp=4, seed=1), scene.integrator().aov_names(), ids)
    bmp = sensor.film().bitmap()
    names = [f.name for f in bmp.struct_()]
    data = np.array(bmp, dtype=np.float32)
    want = np.stack([data[..., [names.index(f"{e}.{c}") for c in "RGB"]] for e in ids])
    assert got.shape == (len(ids), 24, 24, 3) and len(ids) == 5 and got.max() > 0
    assert np.array_equal(got, want)
    with pytest.raises(RuntimeError, match="fewer than"):
        read_emitter_images(np.zeros((2, 2, 4), np.float32), scene.integrator().aov_names(), ids)


def test_row_blocks_slice_and_concatenate_like_the_array():
    rng = np.random.default_rng(0)
    parts = [rng.random((n, 2, 3)).astype(np.float32) for n in (5, 0, 7, 1)]
    rb, whole = RowBlocks(parts), np.concatenate(parts)
    assert rb.shape == whole.shape and len(rb) == 13 and rb.dtype == np.float32 and rb.size == whole.size
    for a, b in [(0, 13), (3, 9), (5, 12), (12, 40), (7, 7)]:
        assert np.array_equal(rb[a:b], whole[a:b])
    assert np.array_equal(np.asarray(rb), whole)
    assert np.array_equal(np.asarray(rb.astype(np.float16)), whole.astype(np.float16))


def _content(image, n: int, P: int = 8) -> ShardContent:
    rng = np.random.default_rng(1)
    rig = image.ndim == 5
    fr = [FrameRecord(scene_json="{}", light_dirs=np.eye(3), crosstalk=np.eye(3), light_rgb=np.eye(3),
                      slant_deg=30.0, env_ratio=0.0, env_rotation_deg=0.0, spp=8, frame_seed=1, object="x",
                      materials="m", rig_json='{"n": 3}' if rig else None,
                      light_pos=np.full((3, 3), np.nan) if rig else None,
                      nominal_dirs=np.eye(3) if rig else None, nominal_crosstalk=np.eye(3) if rig else None)]
    return ShardContent(Patches(image, rng.random((n, P, P, 3)).astype(np.float32),
                                (rng.random((n, P, P)) > 0.5).astype(np.uint8),
                                rng.integers(0, 99, (n, 2)).astype(np.int32)), np.zeros(n, np.int32), fr, {"a": 1})


@pytest.mark.parametrize("compression", ["zstd", "lzf", "none"])
@pytest.mark.parametrize("shape", [(37, 8, 8, 3), (21, 64, 16, 16, 3)], ids=["three-light", "rig"])
def test_a_shard_from_row_blocks_is_byte_identical_to_one_from_the_whole_array(tmp_path, compression, shape):
    """Chunk by chunk (16 patches a chunk; the rig's chunks are 1.5 MiB, more than HDF5's 1 MiB chunk
    cache) gives the same file and checksums as one write of the concatenated array: the corpora
    written before keep their bytes (and three-light presets those of v0.6)."""
    n = shape[0]
    dtype = np.float16 if len(shape) == 5 else np.float32  # rig patches arrive in the storage dtype
    whole = np.random.default_rng(2).random(shape).astype(dtype)
    cuts = [0, 3, 11, 20, n]
    blocks = RowBlocks([whole[a:b] for a, b in zip(cuts, cuts[1:])])
    a = write_shard(tmp_path / "a.h5", _content(whole, n, shape[-2]), compression)
    b = write_shard(tmp_path / "b.h5", _content(blocks, n, shape[-2]), compression)
    assert a == b
    assert (tmp_path / "a.h5").read_bytes() == (tmp_path / "b.h5").read_bytes()
    with open_shard(tmp_path / "b.h5") as h:
        assert np.array_equal(h["patches/image"][()], whole.astype(np.float16))
    assert read_digests(tmp_path / "b.h5")["patches/image"] == a["arrays"]["patches/image"]


def test_frame_budget_keeps_three_lights_and_shrinks_with_n():
    assert frame_budget(3) == MemoryBudget() == MemoryBudget(KERNEL_BUDGET, None, None, None)
    b8, b96 = frame_budget(8), frame_budget(96)
    assert b96.kernels == 4 and b8.kernels == KERNEL_BUDGET * 3 // 8
    assert (b96.tables, b96.scenes) == (2, 2) and b96.mesh_bytes <= 4 << 20


def test_scene_pool_and_canonical_mesh_cache_trim_to_the_budget():
    from msps_render.render.pool import ScenePool
    from msps_render.scene import shapes
    from msps_render.scene.spec import ShapeSpec

    pool = ScenePool(max_scenes=16)
    pool._scenes.update({k: object() for k in range(5)})
    pool.trim(2)
    assert list(pool._scenes) == [3, 4]  # the most recently used
    pool.trim(None)
    assert len(pool) == 2
    saved = dict(shapes._CANONICAL)
    try:
        shapes._CANONICAL.clear()
        for k in range(4):
            shapes.canonical_mesh(ShapeSpec(kind="blobby", sh_coeffs=(0.1 * k, 0.2, 0.0), subdivisions=3))
        per = sum(a.nbytes for a in next(iter(shapes._CANONICAL.values()))[:2])
        keys = list(shapes._CANONICAL)
        shapes.trim_canonical_cache(2 * per)
        assert list(shapes._CANONICAL) == keys[2:]
        shapes.trim_canonical_cache(0)
        assert not shapes._CANONICAL
    finally:
        shapes._CANONICAL.clear()
        shapes._CANONICAL.update(saved)
