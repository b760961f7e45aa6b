"""Ground-truth normal maps, read by one rule for `msps predict --normal-gt` and `msps bench-real`.

Why one rule: the two readers disagreed -- a white PNG pixel (|n| = 1.73 once decoded) was a normal to
one of them and no normal to the other -- so the same truth scored differently in two commands.

.npy and .mat (variable `Normal_gt`, DiLiGenT's): signed normals.  PNG (8/16 bit) and other images:
(n+1)/2-encoded.  EXR/HDR: signed (as `msps` writes normal.exr) unless no value is negative, then
(n+1)/2-encoded.  Zero normals, non-finite ones and, once decoded, vectors far from unit length
(black or mid-grey or white backgrounds, which 8-bit codes cannot hold as zero) are invalid.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from msps_render.errors import InputError

MIN_LENGTH, MAX_LENGTH = 0.5, 1.5  # a decoded vector outside this is no normal


def _read_mat(p: Path) -> np.ndarray:
    import scipy.io

    try:
        d = scipy.io.loadmat(str(p))
    except Exception as e:  # scipy raises ValueError/TypeError/MatReadError on foreign files
        why = str(e).splitlines()[0][:100] if str(e) else type(e).__name__
        raise InputError(p, f"cannot read the .mat file ({why})") from None
    if "Normal_gt" not in d:
        keys = sorted(k for k in d if not k.startswith("__"))
        raise InputError(p, f"no variable 'Normal_gt' (has: {', '.join(keys) or 'none'})")
    return np.asarray(d["Normal_gt"], dtype=np.float64)


def read_normal_map(path: str | Path, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(unit normals (H, W, 3), 0 where invalid; valid (H, W)) of a ground-truth normal map of `shape`."""
    from msps_render.io.images import read_image

    p = Path(path)
    if not p.is_file():
        raise InputError(p, "ground-truth normal map not found")
    suffix = p.suffix.lower()
    if suffix == ".npy":
        n = np.load(p).astype(np.float64)
    elif suffix == ".mat":
        n = _read_mat(p)
    elif suffix == ".png":
        from msps_render.io.png16 import read_png

        a = read_png(p)
        n = a.astype(np.float64) / np.iinfo(a.dtype).max * 2.0 - 1.0 if a.ndim == 3 else a
    else:
        n = read_image(p).astype(np.float64)
        if suffix not in (".exr", ".hdr") or n[..., :3].min() >= 0:
            n = n * 2.0 - 1.0
    if n.ndim != 3 or n.shape[2] < 3:
        raise InputError(p, f"expected an (H, W, 3) normal map, got shape {list(n.shape)}")
    n = n[..., :3]
    if n.shape[:2] != tuple(shape):
        raise InputError(p, f"normal map is {n.shape[1]}x{n.shape[0]}, the image is {shape[1]}x{shape[0]}")
    n = np.where(np.isfinite(n).all(-1, keepdims=True), n, 0.0)
    length = np.linalg.norm(n, axis=-1)
    valid = (length > MIN_LENGTH) & (length < MAX_LENGTH)
    n = np.where(valid[..., None], n / np.maximum(length, 1e-12)[..., None], 0.0)
    return n, valid
