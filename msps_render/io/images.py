"""Image formats: the registry `FORMATS` (suffix -> reader) and writers for EXR and PNG.

Reading: EXR/HDR are linear float (`hdr=True`: usable as environment maps),
PNG/JPG/TIFF are sRGB decoded to linear, NPY is taken as stored.  One entry in
`FORMATS` adds a format; the suffix lists in messages are derived from it.
Writes go through `atomic_write`, so an interrupted run never leaves a
half-written file under the final name.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from msps_render.atomic import atomic_write
from msps_render.errors import InputError


# File signatures, so a file with the wrong suffix gets "not an OpenEXR file (looks like PNG)" rather than
# the library's "Unable to open ... for read".
MAGIC = {"OpenEXR": (b"\x76\x2f\x31\x01",), "PNG": (b"\x89PNG\r\n\x1a\n",), "Radiance HDR": (b"#?",),
         "NPY": (b"\x93NUMPY",), "JPEG": (b"\xff\xd8\xff",), "TIFF": (b"II*\x00", b"MM\x00*"),
         "GIF": (b"GIF8",), "BMP": (b"BM",)}


def sniff(p: Path) -> str | None:
    """The format a file's first bytes say ('OpenEXR', 'PNG', ...), or None."""
    try:
        with open(p, "rb") as fh:
            head = fh.read(16)
    except OSError as e:
        raise InputError(p, f"cannot read ({e.strerror})") from None
    return next((name for name, sigs in MAGIC.items() if any(head.startswith(s) for s in sigs)), None)


def check_magic(p: Path, expected: str, what: str) -> None:
    """`InputError` '`what`: not a/an `expected` file (looks like X)' unless file `p` starts with the
    signature of format `expected` (a `MAGIC` key)."""
    if p.stat().st_size == 0:
        raise InputError(p, f"{what}: empty file")
    got = sniff(p)
    if got != expected:
        article = "an" if expected[0] in "AEIOU" else "a"
        raise InputError(p, f"{what}: not {article} {expected} file "
                            f"({f'looks like {got}' if got else 'unknown content'})")


def _read_exr(p: Path) -> np.ndarray:
    import OpenEXR

    check_magic(p, "OpenEXR", "cannot read EXR")
    try:
        with OpenEXR.File(str(p)) as f:
            ch = f.channels()
            if "RGB" in ch:
                img = np.asarray(ch["RGB"].pixels)
            elif "RGBA" in ch:
                img = np.asarray(ch["RGBA"].pixels)[..., :3]
            elif all(c in ch for c in "RGB"):
                img = np.stack([np.asarray(ch[c].pixels) for c in "RGB"], axis=-1)
            elif "Y" in ch:
                img = np.repeat(np.asarray(ch["Y"].pixels)[..., None], 3, axis=-1)
            else:
                raise InputError(p, f"EXR has no RGB channels (found: {', '.join(ch)})")
    except InputError:
        raise
    except Exception as e:
        raise InputError(p, f"cannot read EXR ({str(e)[:120]})") from None
    return img.astype(np.float32)


def _read_hdr(p: Path) -> np.ndarray:
    import mitsuba as mi  # Bitmap works without a variant; reads Radiance RGBE

    check_magic(p, "Radiance HDR", "cannot read HDR")
    try:
        img = np.array(mi.Bitmap(str(p)), dtype=np.float32)
    except Exception as e:
        raise InputError(p, f"cannot read HDR ({str(e)[:120]})") from None
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    return img[..., :3]


def _read_npy(p: Path) -> np.ndarray:
    check_magic(p, "NPY", "cannot read NPY")
    try:
        return np.load(p, allow_pickle=False).astype(np.float32)
    except Exception as e:
        raise InputError(p, f"cannot read NPY ({e})") from None


def _read_srgb(p: Path) -> np.ndarray:
    from PIL import Image

    try:
        a = np.asarray(Image.open(p))
    except Exception as e:
        raise InputError(p, f"cannot read image ({e})") from None
    scale = 65535.0 if a.dtype == np.uint16 else 255.0
    a = a.astype(np.float32) / scale
    return np.where(a <= 0.04045, a / 12.92, ((a + 0.055) / 1.055) ** 2.4).astype(np.float32)


@dataclass(frozen=True)
class ImageFormat:
    read: Callable[[Path], np.ndarray]  # path -> float32 linear (H, W[, C])
    hdr: bool = False  # linear HDR radiance (usable as an environment map)


# The registry: one entry adds a readable format (by lower-case suffix).
FORMATS: dict[str, ImageFormat] = {
    ".exr": ImageFormat(_read_exr, hdr=True),
    ".hdr": ImageFormat(_read_hdr, hdr=True),
    ".rgbe": ImageFormat(_read_hdr, hdr=True),
    ".pic": ImageFormat(_read_hdr, hdr=True),
    ".npy": ImageFormat(_read_npy),
    ".png": ImageFormat(_read_srgb),
    ".jpg": ImageFormat(_read_srgb),
    ".jpeg": ImageFormat(_read_srgb),
    ".tif": ImageFormat(_read_srgb),
    ".tiff": ImageFormat(_read_srgb),
}
HDR_SUFFIXES = (".exr", ".hdr")  # the ones named in messages (.rgbe/.pic are Radiance aliases)


def write_exr(path: str | Path, img: np.ndarray) -> Path:
    """Float32 RGB EXR (ZIP compression). `img` is (H, W, 3) or (H, W)."""
    import OpenEXR

    path = Path(path)
    a = np.asarray(img, dtype=np.float32)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_write(path, unique=True) as tmp, OpenEXR.File(header, {"RGB": np.ascontiguousarray(a[..., :3])}) as f:
        f.write(str(tmp))
    return path


def write_png(path: str | Path, img8: np.ndarray) -> Path:
    from PIL import Image

    path = Path(path)
    with atomic_write(path, unique=True) as tmp:
        Image.fromarray(np.asarray(img8, dtype=np.uint8)).save(tmp, format="PNG")
    return path


def read_image(path: str | Path) -> np.ndarray:
    """Read any format of `FORMATS` -> float32 (H, W, C), linear."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "image file not found")
    fmt = FORMATS.get(p.suffix.lower())
    if fmt is None:
        raise InputError(p, f"unsupported image format '{p.suffix}' (use {', '.join(FORMATS)})")
    img = fmt.read(p)
    if img.ndim == 2:
        img = img[..., None]
    if not np.isfinite(img).all():
        raise InputError(p, "image contains NaN/inf values")
    return img
