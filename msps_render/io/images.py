"""Writing and reading images: linear float EXR (OpenEXR) and 8-bit PNG (Pillow).

Writes go to a temporary name in the same directory and are renamed into
place, so an interrupted run never leaves a half-written file under the final
name.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from msps_render.errors import InputError


def _atomic_target(path: Path) -> Path:
    return path.with_name(f".{path.name}.tmp-{os.getpid()}")


def write_exr(path: str | Path, img: np.ndarray) -> Path:
    """Float32 RGB EXR (ZIP compression). `img` is (H, W, 3) or (H, W)."""
    import OpenEXR

    path = Path(path)
    a = np.asarray(img, dtype=np.float32)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    tmp = _atomic_target(path)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"RGB": np.ascontiguousarray(a[..., :3])}) as f:
        f.write(str(tmp))
    os.replace(tmp, path)
    return path


def write_png(path: str | Path, img8: np.ndarray) -> Path:
    from PIL import Image

    path = Path(path)
    tmp = _atomic_target(path)
    Image.fromarray(np.asarray(img8, dtype=np.uint8)).save(tmp, format="PNG")
    os.replace(tmp, path)
    return path


def read_image(path: str | Path) -> np.ndarray:
    """Read EXR/HDR (linear float), PNG/JPG (sRGB decoded to linear), or NPY -> float32 (H, W, C)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "image file not found")
    suf = p.suffix.lower()
    if suf in (".exr", ".hdr"):
        from msps_render.scene.envmap import _read_exr, _read_hdr

        img = _read_exr(p) if suf == ".exr" else _read_hdr(p)
    elif suf == ".npy":
        try:
            img = np.load(p, allow_pickle=False).astype(np.float32)
        except Exception as e:
            raise InputError(p, f"cannot read NPY ({e})") from None
    elif suf in (".png", ".jpg", ".jpeg", ".tif", ".tiff"):
        from PIL import Image

        try:
            a = np.asarray(Image.open(p))
        except Exception as e:
            raise InputError(p, f"cannot read image ({e})") from None
        scale = 65535.0 if a.dtype == np.uint16 else 255.0
        a = a.astype(np.float32) / scale
        img = np.where(a <= 0.04045, a / 12.92, ((a + 0.055) / 1.055) ** 2.4).astype(np.float32)
    else:
        raise InputError(p, f"unsupported image format '{p.suffix}' (use .exr, .hdr, .png, .npy)")
    if img.ndim == 2:
        img = img[..., None]
    if not np.isfinite(img).all():
        raise InputError(p, "image contains NaN/inf values")
    return img
