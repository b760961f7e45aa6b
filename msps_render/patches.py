"""Frame -> patches: fixed-size windows kept where the object covers enough of them.

The paper trains on 40x40 patches; each patch keeps its mask (background
pixels must not count in the loss) and records where it came from so a patch
can always be traced back to its frame.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from msps_render.dataset.schema import Patches, all_finite

if TYPE_CHECKING:  # patchify takes a Frame; window_origins (used by predict) needs nothing of it
    from msps_render.frame import Frame


def window_origins(height: int, width: int, size: int, stride: int) -> np.ndarray:
    """Top-left corners of a regular grid of windows (the last row/column is flush with the edge)."""
    def axis(n: int) -> list[int]:
        if n < size:
            return []
        starts = list(range(0, n - size + 1, stride))
        if starts[-1] != n - size:
            starts.append(n - size)
        return starts

    ys, xs = axis(height), axis(width)
    return np.array([(y, x) for y in ys for x in xs], dtype=np.int32).reshape(-1, 2)


def patchify(frame: Frame, size: int = 40, stride: int = 20, min_coverage: float = 0.5,
             image_dtype: str = "float32", normal_dtype: str = "float32") -> Patches:
    """Cut windows whose mask coverage is >= `min_coverage` (fraction of pixels).

    `image_dtype` / `normal_dtype`: the patches' dtypes (the shard's storage dtypes).  The whole frame is
    cast once and then cut: the same values as casting every window (a cast is per value), at a
    fraction of the work, since a pixel lies in up to (size / stride)^2 windows.  Radiance beyond
    float16's range in a kept window is a ValueError that says what to do."""
    if not 0.0 <= min_coverage <= 1.0:
        raise ValueError(f"min_coverage must be in [0, 1], got {min_coverage}")
    H, W = frame.mask.shape
    origins = window_origins(H, W, size, stride)
    # coverage via a summed-area table: O(HW) regardless of the number of windows
    sat = np.pad(frame.mask.astype(np.int64).cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    y, x = origins[:, 0], origins[:, 1]
    cover = (sat[y + size, x + size] - sat[y, x + size] - sat[y + size, x] + sat[y, x]) / float(size * size)
    keep = origins[cover >= max(min_coverage, 1e-9)]
    shots = getattr(frame, "shots", None)  # mask-only stand-ins (plan estimates) carry no shots
    if shots is not None:  # any rig: (n, S, P, P, M), every image of the patch
        image = _radiance_windows(shots, keep, size, image_dtype, axis=1)
    else:
        image = _radiance_windows(frame.image, keep, size, image_dtype)
    points = getattr(frame, "points", None)
    points = cut_windows(points, keep, size).astype(np.float32, copy=False) if points is not None else None
    shadow = getattr(frame, "shadow", None)  # (L, H, W) -> (n, L, P, P)
    shadow = cut_windows(shadow, keep, size, axis=1).astype(np.uint8, copy=False) if shadow is not None else None
    return Patches(image=image, normal=cut_windows(_as(frame.normal, normal_dtype), keep, size),
                   mask=cut_windows(frame.mask.astype(np.uint8, copy=False), keep, size), yx=keep.astype(np.int32),
                   points=points, shadow=shadow)


def _as(a: np.ndarray, dtype: str) -> np.ndarray:
    """`a` as `dtype` by way of float32, as the patches were cut (float32) and then stored: no double
    rounding differs from that path whatever the frame's own dtype."""
    return a.astype(np.float32, copy=False).astype(dtype, copy=False)


def _radiance_windows(a: np.ndarray, keep: np.ndarray, size: int, dtype: str, axis: int = 0) -> np.ndarray:
    """`cut_windows` of `a` cast to `dtype` first; float16 overflow in a kept window is refused."""
    with np.errstate(over="ignore"):  # refused just below when a kept window holds it
        cast = _as(a, dtype)
    out = cut_windows(cast, keep, size, axis)
    if cast.dtype == np.float16 and not all_finite(cast) and not all_finite(out):
        raise ValueError("radiance exceeds float16 range; use image_dtype='float32'")
    return out


def cut_windows(a: np.ndarray, origins: np.ndarray, size: int, axis: int = 0) -> np.ndarray:
    """The size x size windows at `origins` (n, 2) of `a`, whose rows and columns are axes `axis` and
    `axis + 1`: shape (n, *a.shape[:axis], size, size, *a.shape[axis + 2:]).
    Why slices, not one fancy-indexed gather: a window is a block of contiguous rows, so n slice copies
    are ~3x faster than numpy's element-by-element advanced indexing (the same values)."""
    lead = (slice(None),) * axis
    if len(origins) == 0:
        return np.zeros((0, *a.shape[:axis], size, size, *a.shape[axis + 2:]), a.dtype)
    return np.stack([a[lead + (slice(y, y + size), slice(x, x + size))] for y, x in origins.tolist()])
