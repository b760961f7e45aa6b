"""Write a shard atomically and byte-deterministically.  Format: docs/shard-format.md.

A shard is written under a temporary name in the same directory and renamed
into place only after its `complete` attribute is set and the file is closed
and fsynced, so a crash (or a full disk) never leaves a partial shard under a
final name.  Writing is byte-deterministic: no timestamps (`track_times=False`),
fixed dataset order and fixed chunking, so the same content gives the same file.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from msps_render.atomic import atomic_write
from msps_render.dataset import schema as K
from msps_render.dataset.digest import array_digest, file_digest
from msps_render.dataset.schema import RowBlocks, ShardContent, all_finite


def filter_kwargs(compression: str) -> dict:
    """h5py `create_dataset` arguments of a `dataset.storage.compression` value (chunked arrays).

    Every filter is followed by fletcher32 (the per-chunk checksum `msps verify` relies on).
    lzf (h5py's own) and gzip level 4 use HDF5's byte shuffle; zstd (level 3) too; blosc2-lz4
    (level 5) shuffles bytes inside Blosc2 (SIMD, cheaper than HDF5's).  zstd and blosc2-lz4 are
    HDF5 plugin filters from `hdf5plugin`, which every reader imports (`open_shard`).
    """
    if compression == "none":
        return {"fletcher32": True}
    if compression in ("lzf", "gzip"):
        kw = {"compression": compression, "shuffle": True, "fletcher32": True}
        if compression == "gzip":
            kw["compression_opts"] = 4
        return kw
    import hdf5plugin

    if compression == "zstd":
        return {**hdf5plugin.Zstd(clevel=3), "shuffle": True, "fletcher32": True}
    if compression == "blosc2-lz4":
        return {**hdf5plugin.Blosc2(cname="lz4", clevel=5, filters=hdf5plugin.Blosc2.SHUFFLE), "fletcher32": True}
    raise ValueError(f"compression must be one of {K.COMPRESSIONS}, got {compression!r}")


def create_array(group, name: str, data, compression: str, chunks=None):
    """One numeric dataset with the shard's filters (`filter_kwargs`); empty and scalar arrays unfiltered.
    A `RowBlocks` (a shard's patch images) is written a chunk's rows at a time: the same bytes as one
    write of the whole array (tested), without ever holding it whole."""
    kw = {"track_times": False}
    if data.size > 0 and data.ndim >= 1:
        kw.update(filter_kwargs(compression), chunks=chunks or True)
    if not isinstance(data, RowBlocks):
        return group.create_dataset(name, data=data, **kw)
    if data.size == 0:
        return group.create_dataset(name, data=np.asarray(data), **kw)
    # No chunk cache: each chunk goes to the file as it is written, in order, as a one-shot write puts them
    ds = group.create_dataset(name, shape=data.shape, dtype=data.dtype, rdcc_nbytes=0, **kw)
    step = ds.chunks[0]
    for start in range(0, len(data), step):
        ds[start:start + step] = data[start:start + step]
    return ds


def shard_arrays(content: ShardContent, image_dtype: str = "float16", normal_dtype: str = "float16"
                 ) -> tuple[dict[str, np.ndarray], dict[str, list[str]]]:
    """(numeric arrays, string arrays) of a shard, by HDF5 key, in the order they are written."""
    p = content.patches
    img = p.image.astype(image_dtype, copy=False)  # patches arrive in the storage dtypes (`patchify`)
    blocks = getattr(img, "blocks", [img])
    if image_dtype == "float16" and len(p) and not all(all_finite(b) for b in blocks):
        raise ValueError("radiance exceeds float16 range; use image_dtype='float32'")
    arrays = {
        K.PATCH_IMAGE: img,
        K.PATCH_NORMAL: p.normal.astype(normal_dtype, copy=False),
        K.PATCH_MASK: p.mask.astype(np.uint8, copy=False),
        K.PATCH_FRAME_INDEX: content.frame_index.astype(np.int32),
        K.PATCH_YX: p.yx.astype(np.int32),
    }
    fr = content.frames
    if is_rig_content(content):
        return _rig_arrays(content, arrays, image_dtype)
    arrays.update(_frame_rows(fr, {
        K.FRAME_LIGHT_DIRS: np.array([f.light_dirs for f in fr], np.float32).reshape(-1, 3, 3),
        K.FRAME_CROSSTALK: np.array([f.crosstalk for f in fr], np.float32).reshape(-1, 3, 3),
        K.FRAME_LIGHT_RGB: np.array([f.light_rgb for f in fr], np.float32).reshape(-1, 3, 3)}))
    if fr and fr[0].image is not None:
        arrays.update(_whole_frames(fr))
        if all(f.albedo is not None for f in fr):
            arrays[K.FRAME_ALBEDO] = np.stack([f.albedo for f in fr]).astype(np.float16)
            arrays[K.FRAME_BLEND] = np.stack([f.blend for f in fr]).astype(np.float16)
        if all(f.per_light is not None for f in fr):
            arrays[K.FRAME_PER_LIGHT] = _radiance(np.stack([f.per_light for f in fr]), image_dtype, "per-light")
            if any(f.env_image is not None for f in fr):  # zeros for the frames without an environment
                arrays[K.FRAME_ENV_IMAGE] = _radiance(np.stack(
                    [f.env_image if f.env_image is not None else np.zeros_like(f.image) for f in fr]),
                    image_dtype, "environment")
    strings = {K.FRAME_SCENE_JSON: [f.scene_json for f in fr], K.FRAME_OBJECT: [f.object for f in fr],
               K.FRAME_MATERIALS: [f.materials for f in fr], K.FRAME_CONDITION: [f.condition for f in fr]}
    return arrays, strings


def _frame_rows(fr: list, lights: dict) -> dict:
    """Per-frame arrays, in the order they are written: the lights (each format's shapes), then the scalars."""
    return {**lights,
            K.FRAME_SLANT_DEG: np.array([f.slant_deg for f in fr], np.float32),
            K.FRAME_ENV_RATIO: np.array([f.env_ratio for f in fr], np.float32),
            K.FRAME_ENV_ROTATION_DEG: np.array([f.env_rotation_deg for f in fr], np.float32),
            K.FRAME_SPP: np.array([f.spp for f in fr], np.int32),
            K.FRAME_SEED: np.array([f.frame_seed for f in fr], np.int64)}


def _whole_frames(fr: list) -> dict:
    return {K.FRAME_IMAGE: np.stack([f.image for f in fr]).astype(np.float32),
            K.FRAME_NORMAL: np.stack([f.normal for f in fr]).astype(np.float32),
            K.FRAME_MASK: np.stack([f.mask for f in fr]).astype(np.uint8)}


def is_rig_content(content: ShardContent) -> bool:
    """Format 2 (any rig) when the frames carry a RigSpec; format 1 (three-light, unchanged) otherwise."""
    return any(f.rig_json is not None for f in content.frames)


def _rig_arrays(content: ShardContent, arrays: dict, image_dtype: str):
    """Format 2: the rig's lights per frame (N lights, M channels), whole frames' shots (docs/shard-format.md)."""
    fr, p = content.frames, content.patches
    if p.points is not None:
        arrays[K.PATCH_POINTS] = p.points.astype(np.float32)
    if p.shadow is not None:
        arrays[K.PATCH_SHADOW] = p.shadow.astype(np.uint8)
    n = {len(f.light_dirs) for f in fr}
    m = {np.asarray(f.crosstalk).shape[0] for f in fr}
    if len(n) > 1 or len(m) > 1:
        raise ValueError(f"frames of one shard must share the rig's size, got lights {sorted(n)}, channels {sorted(m)}")
    arrays.update(_frame_rows(fr, {
        K.FRAME_LIGHT_DIRS: np.array([f.light_dirs for f in fr], np.float32),
        K.FRAME_CROSSTALK: np.array([f.crosstalk for f in fr], np.float32),
        K.FRAME_LIGHT_RGB: np.array([f.light_rgb for f in fr], np.float32),
        K.FRAME_LIGHT_POS: np.array([f.light_pos for f in fr], np.float32),
        K.FRAME_NOMINAL_DIRS: np.array([f.nominal_dirs for f in fr], np.float32),
        K.FRAME_NOMINAL_CROSSTALK: np.array([f.nominal_crosstalk for f in fr], np.float32)}))
    if fr and fr[0].image is not None:
        arrays.update(_whole_frames(fr))
        arrays[K.FRAME_SHOTS] = _radiance(np.stack([f.shots for f in fr]), image_dtype, "shot")
        if all(f.points is not None for f in fr):
            arrays[K.FRAME_POINTS] = np.stack([f.points for f in fr]).astype(np.float32)
        if all(f.shadow is not None for f in fr):
            arrays[K.FRAME_SHADOW] = np.stack([f.shadow for f in fr]).astype(np.uint8)
    strings = {K.FRAME_SCENE_JSON: [f.scene_json for f in fr], K.FRAME_RIG_JSON: [f.rig_json for f in fr],
               K.FRAME_OBJECT: [f.object for f in fr], K.FRAME_MATERIALS: [f.materials for f in fr],
               K.FRAME_CONDITION: [f.condition for f in fr]}
    return arrays, strings


def _radiance(a: np.ndarray, dtype: str, what: str) -> np.ndarray:
    with np.errstate(over="ignore"):  # overflow is refused just below, with a line that says what to do
        out = a.astype(dtype)
    if dtype == "float16" and not all_finite(out):
        raise ValueError(f"{what} radiance exceeds float16 range; use image_dtype='float32'")
    return out


def write_shard(path: str | Path, content: ShardContent, compression: str = "lzf",
                image_dtype: str = "float16", normal_dtype: str = "float16") -> dict:
    """Write `content` to `path` atomically; returns {'file_sha256', 'arrays': {name: sha256}, ...}."""
    import h5py

    if compression not in K.COMPRESSIONS:
        raise ValueError(f"compression must be one of {K.COMPRESSIONS}, got {compression!r}")
    path = Path(path)
    p, fr = content.patches, content.frames
    P = p.normal.shape[1] if len(p) else 0  # (n, P, P, 3): format 2's image has a shot axis first
    arrays, strings = shard_arrays(content, image_dtype, normal_dtype)
    # The `core` driver builds the file in memory and writes it out once, at close: HDF5 writing chunk
    # by chunk to a full disk crashed the process (segmentation fault at its next flush); here a full
    # disk fails that one write, cleanly (`WriteFailed` naming the shard).  Same bytes as the default
    # driver (tested); memory: one compressed shard.
    with atomic_write(path) as tmp:
        with h5py.File(tmp, "w", driver="core", backing_store=True, track_order=True) as h:
            for k, v in sorted(content.attrs.items()):
                h.attrs[k] = v
            rig = is_rig_content(content)
            h.attrs[K.ATTR_FORMAT_VERSION] = K.RIG_FORMAT_VERSION if rig else K.FORMAT_VERSION
            if rig:
                h.attrs[K.ATTR_N_SHOTS] = int(arrays[K.PATCH_IMAGE].shape[1]) if len(p) else 0
                h.attrs[K.ATTR_N_CHANNELS] = int(np.asarray(fr[0].crosstalk).shape[0]) if fr else 0
            h.attrs[K.ATTR_N_PATCHES] = len(p)
            h.attrs[K.ATTR_N_FRAMES] = len(fr)
            h.attrs[K.ATTR_COMPLETE] = False
            for key, a in arrays.items():
                g, n = K.split_key(key)
                grp = h.require_group(g)
                chunks = None
                if g == K.PATCHES and a.ndim >= 1 and len(a):
                    chunks = (min(K.PATCH_CHUNK, len(a)),) + a.shape[1:]
                elif g == K.FRAMES and a.ndim >= 3 and len(a):
                    chunks = (1,) + a.shape[1:]
                create_array(grp, n, a, compression, chunks)
            sdt = h5py.string_dtype("utf-8")
            for key, vals in strings.items():
                g, n = K.split_key(key)
                h.require_group(g).create_dataset(n, data=np.array(vals, dtype=object), dtype=sdt,
                                                  track_times=False)
            h.attrs[K.ATTR_PATCH_SIZE] = P
            h.attrs[K.ATTR_COMPLETE] = True  # last: a shard without it is partial
    return {"file_sha256": file_digest(path), "n_patches": int(len(p)), "n_frames": len(fr),
            "arrays": {k: array_digest(v) for k, v in arrays.items()}}
