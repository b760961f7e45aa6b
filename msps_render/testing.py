"""Helpers for tests and benchmarks (not part of the pipeline): analytic references."""
from __future__ import annotations

import numpy as np


def analytic_sphere_normals(width: int, height: int, extent: float, radius: float):
    """Analytic normals/mask of an orthographic sphere at the pixel centres (for tests)."""
    xs = ((np.arange(width) + 0.5) / width * 2 - 1) * extent * (width / height if width > height else 1)
    ys = (1 - (np.arange(height) + 0.5) / height * 2) * extent
    X, Y = np.meshgrid(xs, ys)
    r2 = (X ** 2 + Y ** 2) / radius ** 2
    mask = r2 < 1
    Z = np.sqrt(np.clip(1 - r2, 0, None))
    n = np.stack([X / radius, Y / radius, Z], -1)
    n[~mask] = 0
    return n, mask


def corrupt_patch_chunk(shard, chunk: int) -> None:
    """Overwrite 16 bytes in the middle of compressed chunk `chunk` of a shard's patch images:
    the file still opens, and reading that chunk fails (what a bad disk block looks like)."""
    import h5py

    from msps_render.dataset import schema as K

    with h5py.File(shard, "r") as h:
        info = h[K.PATCH_IMAGE].id.get_chunk_info(chunk)
    with open(shard, "r+b") as f:
        f.seek(info.byte_offset + info.size // 2)
        f.write(bytes(16))
