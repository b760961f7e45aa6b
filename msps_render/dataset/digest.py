"""Checksums of shards: per file and per array value (what determinism and resume are judged on)."""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np


def array_digest(arr: np.ndarray) -> str:
    """Checksum of an array's values (dtype + shape + bytes)."""
    h = hashlib.sha256()
    a = np.ascontiguousarray(arr)
    h.update(f"{a.dtype.str}{a.shape}".encode())
    h.update(memoryview(a).cast("B") if a.size else b"")  # the same bytes as tobytes(), without a copy
    return h.hexdigest()


def file_digest(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()
