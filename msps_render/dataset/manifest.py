"""`dataset.json`: what a dataset directory holds, written atomically after every shard.

On disk it is plain JSON (a dict, written by the pipeline as shards finish);
readers take the typed view `Manifest` from `load_manifest`.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from msps_render.atomic import atomic_write
from msps_render.errors import InputError, not_a_dataset, read_text

MANIFEST = "dataset.json"
SHARD_DIR = "shards"
MANIFEST_VERSION = 1


def manifest_path(root: str | Path) -> Path:
    return Path(root) / MANIFEST


def shard_path(root: str | Path, name: str) -> Path:
    return Path(root) / SHARD_DIR / name


def read_manifest(root: str | Path) -> dict | None:
    """The manifest as stored (a dict), or None where there is none."""
    p = manifest_path(root)
    if not p.is_file():
        return None
    text = read_text(p, "manifest")
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise InputError(p, f"corrupt manifest ({e})") from None


def write_manifest(root: str | Path, manifest: dict) -> Path:
    """Write to a temp file, fsync, rename: readers see the old or the new manifest, never half."""
    p = manifest_path(root)
    with atomic_write(p) as tmp, open(tmp, "w") as f:
        json.dump(manifest, f, indent=1, sort_keys=True)
    return p


def new_manifest(cfg_json: str, cfg_hash: str, seed: int, tasks, versions: dict) -> dict:
    """A manifest with no shard yet. `conditions` lists the sweep conditions by name;
    `condition_values` keeps each one's swept key and typed value."""
    values = {}
    for t in tasks:
        if t.condition:
            values[t.condition] = {"key": t.sweep_key, "value": t.condition_value}
    return {
        "format_version": MANIFEST_VERSION,
        "config": json.loads(cfg_json),
        "config_hash": cfg_hash,
        "seed": seed,
        "versions": versions,
        "conditions": sorted({t.condition for t in tasks}),
        "condition_values": values,
        "planned_shards": [t.name for t in tasks],
        "shards": {},
        "complete": False,
    }


@dataclass(frozen=True)
class Condition:
    """One sweep condition: its name (as stored in shards), the swept key and its typed value."""

    name: str
    key: str | None = None
    value: Any = None


@dataclass(frozen=True)
class ShardEntry:
    name: str
    n_patches: int
    n_frames: int
    condition: str
    file_sha256: str | None


@dataclass(frozen=True)
class Manifest:
    """Typed view of `dataset.json`."""

    root: Path
    complete: bool
    config: dict
    conditions: tuple[Condition, ...]
    planned_shards: tuple[str, ...]
    shards: dict[str, ShardEntry]
    n_patches: int | None = None

    @classmethod
    def from_dict(cls, root: str | Path, m: dict) -> "Manifest":
        shards = {name: ShardEntry(name, int(e.get("n_patches", 0)), int(e.get("n_frames", 0)),
                                   e.get("condition", ""), e.get("file_sha256"))
                  for name, e in m.get("shards", {}).items()}
        return cls(root=Path(root), complete=bool(m.get("complete", False)), config=m.get("config", {}),
                   conditions=_conditions(m), planned_shards=tuple(m.get("planned_shards", list(shards))),
                   shards=shards, n_patches=m.get("n_patches"))

    def shards_of(self, condition: str | None = None) -> list[ShardEntry]:
        """Recorded shards in name order (of one condition, if given)."""
        return [self.shards[n] for n in sorted(self.shards)
                if condition is None or self.shards[n].condition == condition]

    def shard_path(self, name: str) -> Path:
        return shard_path(self.root, name)


def _conditions(m: dict) -> tuple[Condition, ...]:
    names = m.get("conditions") or [""]
    typed = m.get("condition_values")
    if typed is None:  # datasets written before typed conditions: the sweep is in the config
        sweep = (m.get("config") or {}).get("sweep") or {}
        key, values = sweep.get("key"), sweep.get("values") or []
        leaf = key.split(".")[-1] if key else ""
        typed = {f"{leaf}={v}": {"key": key, "value": v} for v in values}
    return tuple(Condition(n, typed.get(n, {}).get("key"), typed.get(n, {}).get("value")) for n in names)


def training_lights(roots) -> dict | None:
    """The light geometry of training datasets (from their manifests), as stored in checkpoints."""
    roots = [roots] if isinstance(roots, (str, Path)) else list(roots)
    lo, hi, tilts, M = [], [], None, None
    for r in roots:
        m = read_manifest(r) or {}
        lc = ((m.get("config") or {}).get("scene") or {}).get("lights")
        if not lc:
            return None
        rng = lc.get("slant_range_deg")
        lo.append(rng[0] if rng else lc["slant_deg"])
        hi.append(rng[1] if rng else lc["slant_deg"])
        tilts, M = tilts or lc.get("tilts_deg"), M or lc.get("crosstalk")
    return {"slant_deg": [min(lo), max(hi)], "tilts_deg": tilts, "crosstalk": M,
            "source": "training data manifests"}


def merge_training_lights(run: dict | None, init: dict | None) -> dict | None:
    """The light geometry a warm-started network has seen: its init checkpoint's and this run's data.

    Why: a fine-tune on slant-30 data from a model trained at 20-40 deg still knows 20-40; recording
    only the fine-tune's data would make `msps predict` warn on geometries the network handles.  Only
    the slant range is widened, and only when tilts and crosstalk agree (else the run's record stands)."""
    if not run or not init:
        return run
    same = (np.allclose(run.get("tilts_deg") or [], init.get("tilts_deg") or [])
            and np.allclose(run.get("crosstalk") or [], init.get("crosstalk") or []))
    if not same:
        return run
    return {**run, "slant_deg": [min(run["slant_deg"][0], init["slant_deg"][0]),
                                 max(run["slant_deg"][1], init["slant_deg"][1])],
            "source": "training data manifests"}


RESUME_HINT = "finish it with `msps render CONFIG --out DIR --resume`"


def at_fault(root: str | Path, name: str) -> Path:
    """The file a status problem is about: a shard, or (name == MANIFEST) the manifest itself."""
    return manifest_path(root) if name == MANIFEST else shard_path(root, name)


def manifest_problems(m: dict) -> dict[str, list[str]]:
    """Why the manifest `m` does not describe a complete dataset: {shard name | MANIFEST: problems}.

    The one definition every status command shares (`dataset.verify.dataset_status` adds the
    files): complete = every planned shard recorded and the render's own `complete` flag set
    (a render stopped by SIGTERM after its last shard leaves it unset)."""
    shards = m.get("shards") or {}
    probs: dict[str, list[str]] = {}
    for name in m.get("planned_shards", list(shards)):
        if name not in shards:
            probs[name] = [f"not rendered ({RESUME_HINT})"]
    if not probs and not m.get("complete", False):
        probs[MANIFEST] = [f"the render did not finish (dataset.json says complete=false; {RESUME_HINT})"]
    return probs


def load_manifest(root: str | Path, need_complete: bool = True) -> Manifest:
    """The typed manifest of a dataset directory; `InputError` if there is none (or it is incomplete,
    naming the first shard at fault)."""
    root = Path(root)
    m = read_manifest(root)
    if m is None:
        raise not_a_dataset(root)
    if need_complete:
        probs = manifest_problems(m)
        if probs:
            name = sorted(probs)[0]
            more = f" (and {len(probs) - 1} more)" if len(probs) > 1 else ""
            raise InputError(at_fault(root, name), f"dataset is incomplete: {probs[name][0]}{more}")
    return Manifest.from_dict(root, m)
