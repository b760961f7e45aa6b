"""Checksums of shards: per file and per array value (what determinism and resume are judged on)."""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np


def array_digest(arr) -> str:
    """Checksum of an array's values (dtype + shape + bytes); a `RowBlocks` hashes its blocks in turn
    (the same bytes as its concatenation, without making it)."""
    h = hashlib.sha256()
    blocks = getattr(arr, "blocks", None)
    if blocks is None:
        blocks = [np.ascontiguousarray(arr)]
    h.update(f"{np.dtype(arr.dtype).str}{tuple(arr.shape)}".encode())
    for b in blocks:
        b = np.ascontiguousarray(b)
        h.update(memoryview(b).cast("B") if b.size else b"")  # the same bytes as tobytes(), without a copy
    return h.hexdigest()


def file_digest(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()
