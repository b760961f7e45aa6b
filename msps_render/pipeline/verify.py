"""Dataset-level checks: the manifest's shards exist, match their checksums, and pass `verify_shard`."""
from __future__ import annotations

from pathlib import Path

from msps_render.errors import InputError
from msps_render.pipeline.manifest import SHARD_DIR, read_manifest
from msps_render.shards import verify_shard


def verify_dataset(root: str | Path) -> dict[str, list[str]]:
    """{shard name: problems} for every bad shard (empty dict = dataset is good)."""
    root = Path(root)
    m = read_manifest(root)
    if m is None:
        raise InputError(root, "no dataset.json here (not a dataset directory)")
    bad: dict[str, list[str]] = {}
    planned = m.get("planned_shards", list(m["shards"]))
    for name in planned:
        entry = m["shards"].get(name)
        if entry is None:
            bad[name] = ["not rendered (run `msps render ... --resume`)"]
            continue
        probs = verify_shard(root / SHARD_DIR / name, entry.get("file_sha256"))
        if not probs:
            probs += _content_problems(root / SHARD_DIR / name, entry)
        if probs:
            bad[name] = probs
    return bad


def _content_problems(path: Path, entry: dict) -> list[str]:
    """Checks that need the values: patch count, usable crosstalk, not all black."""
    import h5py
    import numpy as np

    from msps_render.scene.lights import crosstalk_problem

    probs = []
    with h5py.File(path, "r") as h:
        if entry.get("n_patches") is not None and int(h.attrs["n_patches"]) != entry["n_patches"]:
            probs.append("patch count differs from the manifest")
        for j, M in enumerate(h["frames/crosstalk"][()]):
            why = crosstalk_problem(M)
            if why:
                probs.append(f"frame {j}: crosstalk {why}")
                break
        img = h["patches/image"]
        if len(img) and not np.any(img[()]):
            probs.append("every patch image is black (all zero)")
    return probs
