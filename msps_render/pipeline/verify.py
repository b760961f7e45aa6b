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
        if not probs and entry.get("n_patches") is not None:
            import h5py

            with h5py.File(root / SHARD_DIR / name, "r") as h:
                if int(h.attrs["n_patches"]) != entry["n_patches"]:
                    probs.append("patch count differs from the manifest")
        if probs:
            bad[name] = probs
    return bad
