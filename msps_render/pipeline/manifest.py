"""`dataset.json`: what a dataset directory holds, written atomically after every shard."""
from __future__ import annotations

import json
import os
from pathlib import Path

MANIFEST = "dataset.json"
SHARD_DIR = "shards"


def manifest_path(root: str | Path) -> Path:
    return Path(root) / MANIFEST


def read_manifest(root: str | Path) -> dict | None:
    p = manifest_path(root)
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError as e:
        from msps_render.errors import InputError

        raise InputError(p, f"corrupt manifest ({e})") from None


def write_manifest(root: str | Path, manifest: dict) -> Path:
    """Write to a temp file, fsync, rename: readers see the old or the new manifest, never half."""
    p = manifest_path(root)
    tmp = p.with_name(f".{p.name}.tmp")
    with open(tmp, "w") as f:
        json.dump(manifest, f, indent=1, sort_keys=True)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, p)
    return p


def new_manifest(cfg_json: str, cfg_hash: str, seed: int, tasks, versions: dict) -> dict:
    return {
        "format_version": 1,
        "config": json.loads(cfg_json),
        "config_hash": cfg_hash,
        "seed": seed,
        "versions": versions,
        "conditions": sorted({t.condition for t in tasks}),
        "planned_shards": [t.name for t in tasks],
        "shards": {},
        "complete": False,
    }
