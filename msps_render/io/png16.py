"""8/16-bit PNG for export and captures: a small exact writer, and a reader that keeps 16 bits.

Pillow truncates 16-bit RGB PNGs to 8 bits on read and cannot write them, so
the writer here encodes PNG itself (zlib, filter 0; lossless, deterministic)
and the reader uses Mitsuba's `Bitmap` (libpng), which returns the stored
integers.  Values are written as stored, with a gAMA 1.0 chunk that says so
(the PNG way of marking linear data).  `read_png_linear` is the one rule by which
`msps predict`, `msps compose` and `msps bench-real` turn a PNG into linear values (`PNG_RULE`).
"""
from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from msps_render.atomic import writing
from msps_render.errors import InputError

_SIG = b"\x89PNG\r\n\x1a\n"
LINEAR_GAMMA = 100000  # gAMA chunk value of file gamma 1.0 (the PNG spec stores gamma x 100000)
PNG_RULE = ("PNG values are decoded as the file says: a gAMA 1.0 chunk (msps's own PNGs) means linear, an sRGB/"
            "iCCP chunk or another gamma means sRGB; an untagged photo of a capture folder with "
            "light_intensities.txt (DiLiGenT layout: radiometric, so linear) is linear at any bit depth; any other "
            "untagged 16-bit PNG is taken as linear (raw captures), an untagged 8-bit one as sRGB, each with a "
            "warning")
PNG_OVERRIDES = "; --linear / --srgb override"  # the commands that have both flags (predict, compose)


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def encode_png(a: np.ndarray, srgb: bool = False) -> bytes:
    """PNG bytes of a uint8 or uint16 array (H, W), (H, W, 1) or (H, W, 3), tagged linear (gAMA 1.0),
    or with `srgb` (pictures for people: previews, error maps) tagged sRGB."""
    a = np.asarray(a)
    if a.dtype not in (np.uint8, np.uint16):
        raise TypeError(f"PNG needs uint8 or uint16, got {a.dtype}")
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim == 2:
        colour = 0
    elif a.ndim == 3 and a.shape[2] == 3:
        colour = 2
    else:
        raise ValueError(f"PNG needs (H, W) or (H, W, 3), got {a.shape}")
    H, W = a.shape[:2]
    depth = 16 if a.dtype == np.uint16 else 8
    rows = np.ascontiguousarray(a.astype(">u2") if depth == 16 else a).reshape(H, -1).view(np.uint8)
    raw = np.concatenate([np.zeros((H, 1), np.uint8), rows], axis=1).tobytes()  # filter byte 0 per row
    ihdr = struct.pack(">IIBBBBB", W, H, depth, colour, 0, 0, 0)
    if srgb:  # the sRGB chunk, with the gAMA the PNG spec asks to accompany it
        tag = _chunk(b"sRGB", b"\x00") + _chunk(b"gAMA", struct.pack(">I", 45455))
    else:  # stored values are linear: no gamma applied
        tag = _chunk(b"gAMA", struct.pack(">I", LINEAR_GAMMA))
    return (_SIG + _chunk(b"IHDR", ihdr) + tag + _chunk(b"IDAT", zlib.compress(raw, 6))
            + _chunk(b"IEND", b""))


def write_png(path: str | Path, a: np.ndarray, srgb: bool = False) -> Path:
    p = Path(path)
    with writing(p):  # a full disk: one line naming this file (no fsync: exports write thousands)
        p.write_bytes(encode_png(a, srgb))
    return p


def read_png(path: str | Path) -> np.ndarray:
    """The stored integers of a PNG (uint8 or uint16), (H, W) or (H, W, C), alpha kept."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "image file not found")
    from msps_render.io.images import check_magic

    check_magic(p, "PNG", "cannot read PNG")
    try:
        import mitsuba as mi

        a = np.array(mi.Bitmap(str(p)))
    except InputError:
        raise
    except Exception as e:
        raise InputError(p, f"cannot read PNG ({str(e).splitlines()[0][:120] if str(e) else type(e).__name__})") from None
    return a[..., 0] if a.ndim == 3 and a.shape[2] == 1 else a


def to_unorm(x: np.ndarray, dtype=np.uint16) -> np.ndarray:
    """Values in [0, 1] -> nearest integer code (clipped)."""
    top = np.iinfo(dtype).max
    return np.round(np.clip(np.asarray(x, np.float64), 0.0, 1.0) * top).astype(dtype)


def from_unorm(a: np.ndarray) -> np.ndarray:
    return np.asarray(a, np.float64) / np.iinfo(a.dtype).max


def encode_normal(n: np.ndarray, mask: np.ndarray, dtype=np.uint16) -> np.ndarray:
    """(n + 1) / 2 as integers; outside the mask n = 0 (mid grey), the convention PS-FCN decodes."""
    n = np.where(np.asarray(mask, bool)[..., None], n, 0.0)
    return to_unorm((n + 1.0) * 0.5, dtype)


def decode_normal(a: np.ndarray) -> np.ndarray:
    return from_unorm(a) * 2.0 - 1.0


def png_colour_tags(path: str | Path) -> dict:
    """{'bit_depth', 'gamma' (float or None), 'srgb' (sRGB or iCCP chunk present)} from the chunks before
    the image data (a few bytes read; `read_png` has checked the file is a PNG)."""
    tags = {"bit_depth": None, "gamma": None, "srgb": False}
    with open(path, "rb") as fh:
        fh.read(len(_SIG))
        while True:
            head = fh.read(8)
            if len(head) < 8:
                break
            n, kind = struct.unpack(">I", head[:4])[0], head[4:]
            if kind in (b"IDAT", b"IEND"):
                break
            data = fh.read(n)
            fh.read(4)  # CRC
            if kind == b"IHDR" and len(data) >= 9:
                tags["bit_depth"] = data[8]
            elif kind == b"gAMA" and len(data) == 4:
                tags["gamma"] = struct.unpack(">I", data)[0] / 100000.0
            elif kind in (b"sRGB", b"iCCP"):
                tags["srgb"] = True
    return tags


def png_is_linear(path: str | Path, bit_depth: int, linear: bool | None = None,
                  radiometric: bool = False) -> tuple[bool, str | None]:
    """(values are linear, warning or None when guessed): the rule of `PNG_RULE`.

    Why tags first: msps writes gAMA 1.0 into its PNGs, so its own 16-bit exports read back
    linear without a flag; untagged files fall back on what they are.  `radiometric`: a photo of a
    capture that gives its lights' intensities (DiLiGenT layout), whose values are divided by them, so
    they are linear whatever the bit depth (DiLiGenT's 8-bit crops hold the high byte of the 16-bit raw
    capture); no warning, the layout says so."""
    if linear is not None:
        return bool(linear), None
    t = png_colour_tags(path)
    if t["srgb"]:
        return False, None
    if t["gamma"] is not None:
        return abs(t["gamma"] - 1.0) < 0.01, None
    if radiometric:
        return True, None
    if bit_depth == 16:
        return True, (f"{path}: 16-bit PNG without colour information, read as linear (raw capture); "
                      f"pass --srgb if it is gamma-encoded")
    return False, (f"{path}: 8-bit PNG without colour information, decoded as sRGB; pass --linear if its "
                   f"values are linear")


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def read_png_linear(path: str | Path, linear: bool | None = None, warn=None, radiometric: bool = False) -> np.ndarray:
    """A PNG as linear float64 in [0, 1], (H, W) or (H, W, C) (alpha kept, never decoded).

    `linear` True/False forces the decoding (--linear / --srgb); None follows `png_is_linear`, and
    `warn(message)` hears when that is a guess."""
    a = read_png(path)
    is_linear, guess = png_is_linear(path, 16 if a.dtype == np.uint16 else 8, linear, radiometric)
    if guess and warn:
        warn(guess)
    img = from_unorm(a)
    if is_linear:
        return img
    if img.ndim == 3 and img.shape[2] in (2, 4):  # alpha is linear coverage
        return np.concatenate([srgb_to_linear(img[..., :-1]), img[..., -1:]], axis=-1)
    return srgb_to_linear(img)
