"""Material choice: `sample_materials(rng, n, ...)` draws distinct materials for a scene.

A configurable share is measured (`kind="merl"`): the real MERL file when one
can be found, otherwise the built-in Neural-BRDF fit of the same material,
named `merl:<name>` or `nbrdf:<name>` so every log, SceneSpec and shard says
which was used; `generated:<name>` tables only when asked for.  The rest are
analytic families (`brdf.families.FAMILIES`).  The catalogue, MERL discovery
and the held-out split are `msps_render.brdf.library`; translation to Mitsuba
is `msps_render.render.materials`.
"""
from __future__ import annotations

import functools
import logging
import os
from pathlib import Path

import numpy as np

from msps_render.brdf import nbrdf
from msps_render.brdf.families import FAMILIES, MEASURED_KIND, unknown_family
from msps_render.brdf.library import (HOLDOUT, MEASURED, Catalogue, Entry, available_merl, find_merl, held_out,
                                      list_files, load_catalogue, merl_search_dirs)
from msps_render.errors import InputError
from msps_render.scene.spec import MaterialSpec

log = logging.getLogger(__name__)


def sample_analytic(family: str, rng: np.random.Generator, name: str | None = None,
                    gamut: str = "moderate") -> MaterialSpec:
    """A material of an analytic family (`brdf.families.FAMILIES`) with parameters drawn from `rng`
    (albedo colours from `gamut`: 'moderate' or 'full')."""
    fam = FAMILIES.get(family)
    if fam is None:
        raise InputError("materials.families", unknown_family(family))
    return MaterialSpec(name=name or family, kind=fam.bsdf, params=fam.sample(rng, gamut))


def lambertian(albedo=(0.8, 0.8, 0.8), name: str = "lambertian") -> MaterialSpec:
    return MaterialSpec(name=name, kind="diffuse", params={"reflectance": tuple(float(a) for a in albedo)})


# ------------------------------------------------------- measured materials
def measured_pool(cat: Catalogue, measured: str = "auto", merl_dir: str | os.PathLike | None = None
                  ) -> list[MaterialSpec]:
    """Every measured material available under `measured`:

    'auto' = per catalogue entry the real MERL file if found, else the built-in
    Neural-BRDF fit; 'merl' = real files only; 'nbrdf' = built-in fits only;
    'generated' = the analytic stand-ins (explicit, never a fallback).
    """
    if measured not in MEASURED:
        raise InputError("materials.measured", f"unknown source '{measured}' (known: {', '.join(MEASURED)})")
    if measured == "generated":
        return [_measured_spec(e, None) for e in cat.by_source("generated")]
    dirs = merl_search_dirs(merl_dir)
    # one listing per folder, not a stat per entry and folder: this runs for every frame
    listed = list_files(dirs)
    fits = frozenset(nbrdf.builtin_names()) if measured in ("auto", "nbrdf") else frozenset()
    # The pool is a function of the catalogue, the source and the files listed: kept for the next frame
    # while those are the same (building its ~64 specs took ~1.5 ms a frame).
    key = (id(cat), measured, tuple(dirs), tuple(listed.items()), fits)
    hit = _POOLS.get(key)
    if hit is not None and hit[0] is cat:
        return list(hit[1])
    pool = _build_pool(cat, measured, dirs, listed, fits)
    while len(_POOLS) >= 8:
        _POOLS.pop(next(iter(_POOLS)))
    _POOLS[key] = (cat, tuple(pool))
    return pool


_POOLS: dict[tuple, tuple] = {}  # measured_pool's key -> (catalogue, pool): a few entries per process


def _build_pool(cat: Catalogue, measured: str, dirs: list[Path], listed: dict, fits: frozenset[str]
                ) -> list[MaterialSpec]:
    pool = []
    for e in cat.by_source("merl"):
        real = find_merl(e.target, dirs, listed) if measured in ("auto", "merl") else None
        if real is not None:
            pool.append(_measured_spec(e, real))
        elif Path(e.target).stem in fits:
            stem = Path(e.target).stem
            pool.append(MaterialSpec(name=f"nbrdf:{e.name}", kind=MEASURED_KIND, params={"table": f"nbrdf:{stem}"}))
    return pool


def _measured_spec(e: Entry, path: Path | None) -> MaterialSpec:
    if e.source == "merl":
        return MaterialSpec(name=f"merl:{e.name}", kind=MEASURED_KIND, params={"table": str(path)})
    params = {"table": f"generated:{e.name}", "model": e.target}
    for k, v in e.params.items():
        params[k] = tuple(float(x) for x in v) if isinstance(v, (list, tuple)) else float(v)
    return MaterialSpec(name=f"generated:{e.name}", kind=MEASURED_KIND, params=params)


def _base_name(m: MaterialSpec) -> str:
    return m.name.split(":", 1)[1] if ":" in m.name else m.name


def sample_materials(rng: np.random.Generator, n: int, catalogue: str | os.PathLike | None = None,
                     merl_fraction: float = 0.5, merl_dir: str | os.PathLike | None = None,
                     families: list[str] | None = None, require_merl: bool | None = None,
                     measured: str = "auto", holdout: str = "train",
                     split_file: str | os.PathLike | None = None, gamut: str = "moderate") -> list[MaterialSpec]:
    """Draw `n` distinct materials; each is measured with probability `merl_fraction`.

    Measured materials come from `measured_pool(measured)`, restricted by
    `holdout` to the training side ('train': held-out materials excluded),
    the held-out side ('test') or everything ('all'). An empty pool is an
    InputError, never a silent substitution. `require_merl` (default: true when
    `merl_dir` or $MSPS_MERL_DIR is set) makes missing real MERL files an error
    listing every place searched. Analytic ones use `families` (config) or the
    catalogue's analytic entries. Consumes `rng` in a fixed order.
    """
    if n < 1:
        raise ValueError(f"need at least one material, got n={n}")
    if not 0.0 <= merl_fraction <= 1.0:
        raise InputError("materials.merl_fraction", f"must be in [0, 1], got {merl_fraction}")
    if holdout not in HOLDOUT:
        raise InputError("materials.holdout", f"unknown value '{holdout}' (known: {', '.join(HOLDOUT)})")
    cat = load_catalogue(catalogue)
    if require_merl is None:
        require_merl = merl_fraction > 0 and bool(merl_dir or os.environ.get("MSPS_MERL_DIR"))
    pool: list[MaterialSpec] = []
    if merl_fraction > 0:
        if require_merl and measured in ("auto", "merl") and not available_merl(cat, merl_dir):
            where = merl_dir or os.environ.get("MSPS_MERL_DIR")
            missing = "" if Path(where).is_dir() else " (directory does not exist)"
            searched = ", ".join(str(d) for d in merl_search_dirs(merl_dir))
            raise InputError(where, f"no MERL .binary files of the catalogue found{missing}; searched: {searched}")
        pool = measured_pool(cat, measured, merl_dir)
        if holdout != "all" and measured != "generated":
            test = held_out(split_file)
            pool = [m for m in pool if (_base_name(m) in test) == (holdout == "test")]
        if not pool:
            raise InputError(cat.path, f"no measured materials available (measured='{measured}', "
                                       f"holdout='{holdout}'); add MERL files or the built-in brdf/nbrdf/ weights, "
                                       "or set materials.merl_fraction = 0")
    n_measured = min(int(rng.binomial(n, merl_fraction)), len(pool)) if pool else 0
    measured_mats = [pool[i] for i in rng.choice(len(pool), size=n_measured, replace=False)] if n_measured else []
    fams = list(families) if families else [e.target for e in cat.by_source("analytic")]
    k = n - n_measured
    if k and not fams:
        raise InputError(cat.path, "no analytic families to draw from (and not enough measured materials)")
    picks = rng.choice(len(fams), size=k, replace=len(fams) < k) if k else []
    analytic = [sample_analytic(fams[int(i)], rng, gamut=gamut) for i in picks]
    mats = measured_mats + analytic
    order = rng.permutation(len(mats))
    out = [mats[int(i)] for i in order]
    log.info("materials: %s", ", ".join(m.name for m in out))
    return out


# ------------------------------------------------------- the measured-material pool of a host
@functools.lru_cache(maxsize=1024)
def _file_sha256(path: str, mtime_ns: int, size: int) -> str:
    """Content digest of a table or weights file, read once per file version (a MERL file is 33 MB;
    a resume or a worker asks once per process)."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _table_digest(m) -> str:
    """What a pool entry renders with: the MERL file's or Neural-BRDF weights' content digest, or
    (generated tables) the digest of the model parameters they are built from."""
    import hashlib
    import json

    table = m.params.get("table", "")
    if table.startswith("nbrdf:"):
        p = nbrdf.weights_path(table[6:])
    elif table.startswith("generated"):
        blob = json.dumps({k: v for k, v in m.params.items()}, sort_keys=True, default=list)
        return "params:" + hashlib.sha256(blob.encode()).hexdigest()
    else:
        p = Path(table)
    if p is None or not Path(p).is_file():
        return "missing"
    st = Path(p).stat()
    return _file_sha256(str(Path(p).resolve()), st.st_mtime_ns, st.st_size)


def material_pool(mc) -> dict[str, str]:
    """{material name: content digest} of the measured materials a scene may draw from here, under
    the `[scene.materials]` config `mc` (catalogue, measured source, held-out side, merl_dir).

    Why: which files exist (MSPS_MERL_DIR, brdf/, the built-in fits) is not part of the config, so
    two hosts with one config hash can draw different materials.  The manifest records this pool; a
    resume or a worker that sees another one stops (`pool_difference`).  Empty when no measured
    material is drawn (merl_fraction = 0)."""
    if not mc.merl_fraction > 0:
        return {}

    pool = measured_pool(load_catalogue(mc.catalogue), mc.measured, mc.merl_dir)
    if mc.holdout != "all" and mc.measured != "generated":
        test = held_out(mc.split_file)
        pool = [m for m in pool if (_base_name(m) in test) == (mc.holdout == "test")]
    return {m.name: _table_digest(m) for m in pool}


def pool_difference(stored: dict[str, str], here: dict[str, str], limit: int = 4) -> str | None:
    """None if both pools are the same, else a short description naming the differing materials."""
    if stored == here:
        return None
    only_stored = sorted(set(stored) - set(here))
    only_here = sorted(set(here) - set(stored))
    changed = sorted(n for n in set(stored) & set(here) if stored[n] != here[n])

    def names(xs: list[str]) -> str:
        return ", ".join(xs[:limit]) + (f" and {len(xs) - limit} more" if len(xs) > limit else "")

    parts = []
    if only_stored:
        parts.append(f"missing here: {names(only_stored)}")
    if only_here:
        parts.append(f"only here: {names(only_here)}")
    if changed:
        parts.append(f"different file content: {names(changed)}")
    return "; ".join(parts)
