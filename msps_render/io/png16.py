"""8/16-bit PNG for export and captures: a small exact writer, and a reader that keeps 16 bits.

Pillow truncates 16-bit RGB PNGs to 8 bits on read and cannot write them, so
the writer here encodes PNG itself (zlib, filter 0; lossless, deterministic)
and the reader uses Mitsuba's `Bitmap` (libpng), which returns the stored
integers.  Values are written and read as stored: no gamma is applied either way.
"""
from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from msps_render.errors import InputError

_SIG = b"\x89PNG\r\n\x1a\n"


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def encode_png(a: np.ndarray) -> bytes:
    """PNG bytes of a uint8 or uint16 array (H, W), (H, W, 1) or (H, W, 3)."""
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
    return _SIG + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", zlib.compress(raw, 6)) + _chunk(b"IEND", b"")


def write_png(path: str | Path, a: np.ndarray) -> Path:
    p = Path(path)
    p.write_bytes(encode_png(a))
    return p


def read_png(path: str | Path) -> np.ndarray:
    """The stored integers of a PNG (uint8 or uint16), (H, W) or (H, W, C), alpha kept."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "image file not found")
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
