"""Bytes a shard spends on each of its arrays (for disk estimates: `msps config show`)."""
from __future__ import annotations

from pathlib import Path

from msps_render.dataset import schema as K
from msps_render.dataset.reader import open_shard, shard_errors


def storage_bytes(path: str | Path) -> dict[str, int]:
    """{'patches': bytes, 'frames': bytes, 'other': bytes, 'file': bytes} of a shard on disk.

    `patches`/`frames` are the stored (compressed) sizes of the `patches/*` and `frames/*`
    arrays (variable-length strings counted by their UTF-8 length); `other` is the rest
    of the file (HDF5 metadata, attributes, heap overhead).
    """
    import h5py

    path = Path(path)
    out = {K.PATCHES: 0, K.FRAMES: 0}
    with shard_errors(path), open_shard(path) as h:
        for group in (K.PATCHES, K.FRAMES):
            if group in h:
                for obj in h[group].values():
                    if isinstance(obj, h5py.Dataset):
                        out[group] += int(obj.id.get_storage_size())
        for key in K.STRING_ARRAYS:  # variable-length strings live in the global heap, not the dataset
            if key in h:
                out[K.split_key(key)[0]] += sum(len(s) for s in h[key].asstr()[()])
    size = path.stat().st_size
    return {"patches": out[K.PATCHES], "frames": out[K.FRAMES],
            "other": max(0, size - out[K.PATCHES] - out[K.FRAMES]), "file": size}


def raw_patch_bytes(size: int, image_dtype: str, normal_dtype: str, shots: int = 1, channels: int = 3,
                    points: bool = False, shadow_lights: int = 0) -> int:
    """Uncompressed bytes of one patch row: image (shots x channels) + normal + mask (+ surface points
    of near-light rigs, + one shadow code per light with `store_shadows`) + frame index + yx."""
    item = {"float16": 2, "float32": 4}
    return size * size * (shots * channels * item[image_dtype] + 3 * item[normal_dtype] + 1
                          + (12 if points else 0) + shadow_lights) + 4 + 2 * 4
