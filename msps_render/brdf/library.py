"""The material library: catalogue loading, MERL file discovery and material sampling.

`sample_materials(rng, n, ...)` draws `n` distinct materials, a configurable
share of them measured (`kind="merl"`). A measured material is the real MERL
file when one can be found, otherwise the built-in Neural-BRDF fit of the same
material (`brdf/nbrdf/`, baked into a MERL table on first use), named `merl:<name>`
or `nbrdf:<name>` so every log, SceneSpec and shard says which was used.
MERL-format tables generated from analytic models (`generated:<name>`) are used
only when asked for (`measured="generated"`), never as a silent fallback.
Held-out materials (`brdf/split.toml`) are excluded from training corpora.
Nothing is downloaded.
"""
from __future__ import annotations

import functools
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from msps_render.errors import InputError
from msps_render.scene.spec import MaterialSpec

log = logging.getLogger(__name__)

REPO_BRDF_DIR = Path(__file__).resolve().parents[2] / "brdf"
DEFAULT_CATALOGUE = REPO_BRDF_DIR / "catalogue.toml"
DEFAULT_SPLIT = REPO_BRDF_DIR / "split.toml"
SOURCES = ("merl", "generated", "analytic")
MEASURED = ("auto", "merl", "nbrdf", "generated")  # where measured materials come from
HOLDOUT = ("train", "test", "all")  # which side of the held-out split a corpus draws from


def brdf_root() -> Path:
    """The material library directory (`brdf/` of the checkout, or $MSPS_BRDF_DIR)."""
    return Path(os.environ["MSPS_BRDF_DIR"]) if os.environ.get("MSPS_BRDF_DIR") else REPO_BRDF_DIR


@dataclass(frozen=True)
class Entry:
    """One catalogue line: `source` is 'merl', 'generated' or 'analytic'; `target` the file/model/family."""

    name: str
    source: str
    target: str
    params: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Catalogue:
    path: str
    entries: tuple[Entry, ...]

    def by_source(self, source: str) -> list[Entry]:
        return [e for e in self.entries if e.source == source]

    def get(self, name: str) -> Entry:
        for e in self.entries:
            if e.name == name:
                return e
        from msps_render.errors import closest

        raise InputError(self.path, f"no material named '{name}'{closest(name, [e.name for e in self.entries])}")


def _catalogue_path(catalogue: str | os.PathLike | None) -> Path:
    if catalogue is not None:
        return Path(catalogue)
    if os.environ.get("MSPS_BRDF_CATALOGUE"):
        return Path(os.environ["MSPS_BRDF_CATALOGUE"])
    return DEFAULT_CATALOGUE


@functools.lru_cache(maxsize=32)
def _load_catalogue(path: str) -> Catalogue:
    from msps_render.brdf.analytic import MODELS
    from msps_render.scene.materials import FAMILIES

    from msps_render.config_io import read_toml

    p = Path(path)
    data = read_toml(p, "material catalogue")
    unknown = set(data) - {"version", "material"}
    if unknown:
        raise InputError(p, f"unknown key(s) {sorted(unknown)}; expected 'version' and [[material]] tables")
    entries: list[Entry] = []
    seen: set[str] = set()
    for i, m in enumerate(data.get("material", [])):
        where = f"material #{i + 1}"
        extra = set(m) - {"name", "source", "params"}
        if extra:
            raise InputError(p, f"{where}: unknown key(s) {sorted(extra)}")
        name, source = m.get("name"), m.get("source")
        if not isinstance(name, str) or not isinstance(source, str) or ":" not in source:
            raise InputError(p, f"{where}: needs name = \"...\" and source = \"merl:<file>\" | "
                                "\"generated:<model>\" | \"analytic:<family>\"")
        kind, target = source.split(":", 1)
        if kind not in SOURCES:
            raise InputError(p, f"{where} ({name}): unknown source kind '{kind}' (known: {', '.join(SOURCES)})")
        if kind == "generated" and target not in MODELS:
            raise InputError(p, f"{where} ({name}): unknown model '{target}' (known: {', '.join(MODELS)})")
        if kind == "analytic" and target not in FAMILIES:
            raise InputError(p, f"{where} ({name}): unknown family '{target}' (known: {', '.join(FAMILIES)})")
        if name in seen:
            raise InputError(p, f"{where}: duplicate material name '{name}'")
        seen.add(name)
        entries.append(Entry(name=name, source=kind, target=target, params=dict(m.get("params", {}))))
    if not entries:
        raise InputError(p, "catalogue lists no [[material]]")
    return Catalogue(path=str(p), entries=tuple(entries))


def load_catalogue(catalogue: str | os.PathLike | None = None) -> Catalogue:
    """Parse and validate a catalogue (default: brdf/catalogue.toml, or $MSPS_BRDF_CATALOGUE)."""
    return _load_catalogue(str(_catalogue_path(catalogue).resolve()))


def merl_search_dirs(merl_dir: str | os.PathLike | None = None) -> list[Path]:
    """Where real MERL files are looked for, in order: config, $MSPS_MERL_DIR, brdf/merl, brdf."""
    dirs = []
    if merl_dir:
        dirs.append(Path(merl_dir))
    if os.environ.get("MSPS_MERL_DIR"):
        dirs.append(Path(os.environ["MSPS_MERL_DIR"]))
    dirs += [REPO_BRDF_DIR / "merl", REPO_BRDF_DIR]
    return dirs


def find_merl(target: str, dirs: list[Path]) -> Path | None:
    """First existing `<dir>/<target>` (target is the file name from `merl:<file>`)."""
    for d in dirs:
        p = d / target
        if p.is_file():
            return p.resolve()
    return None


def available_merl(cat: Catalogue, merl_dir: str | os.PathLike | None = None) -> list[tuple[Entry, Path]]:
    """The catalogue's MERL entries whose file exists, with its path."""
    dirs = merl_search_dirs(merl_dir)
    out = []
    for e in cat.by_source("merl"):
        p = find_merl(e.target, dirs)
        if p is not None:
            out.append((e, p))
    return out


@functools.lru_cache(maxsize=8)
def _read_split(path: str) -> frozenset[str]:
    from msps_render.config_io import read_toml

    p = Path(path)
    if not p.is_file():
        raise InputError(p, "held-out material split file not found")
    data = read_toml(p, "material split")
    unknown = set(data) - {"version", "test"}
    if unknown:
        raise InputError(p, f"unknown key(s) {sorted(unknown)}; expected 'version' and 'test'")
    test = data.get("test")
    if not isinstance(test, list) or not all(isinstance(x, str) for x in test):
        raise InputError(p, "needs test = [\"<material name>\", ...]")
    return frozenset(test)


def held_out(split_file: str | os.PathLike | None = None) -> frozenset[str]:
    """Names of the held-out (test-only) materials, validated against the default catalogue."""
    p = Path(split_file) if split_file else DEFAULT_SPLIT
    names = _read_split(str(p.resolve()))
    return names


def measured_pool(cat: Catalogue, measured: str = "auto", merl_dir: str | os.PathLike | None = None
                  ) -> list[MaterialSpec]:
    """Every measured material available under `measured`:

    'auto' = per catalogue entry the real MERL file if found, else the built-in
    Neural-BRDF fit; 'merl' = real files only; 'nbrdf' = built-in fits only;
    'generated' = the analytic stand-ins (explicit, never a fallback).
    """
    from msps_render.brdf import nbrdf

    if measured not in MEASURED:
        raise InputError("materials.measured", f"unknown source '{measured}' (known: {', '.join(MEASURED)})")
    if measured == "generated":
        return [_measured_spec(e, None) for e in cat.by_source("generated")]
    dirs = merl_search_dirs(merl_dir)
    pool = []
    for e in cat.by_source("merl"):
        real = find_merl(e.target, dirs) if measured in ("auto", "merl") else None
        if real is not None:
            pool.append(_measured_spec(e, real))
        elif measured in ("auto", "nbrdf") and nbrdf.weights_path(Path(e.target).stem) is not None:
            stem = Path(e.target).stem
            pool.append(MaterialSpec(name=f"nbrdf:{e.name}", kind="merl", params={"table": f"nbrdf:{stem}"}))
    return pool


def _measured_spec(e: Entry, path: Path | None) -> MaterialSpec:
    if e.source == "merl":
        return MaterialSpec(name=f"merl:{e.name}", kind="merl", params={"table": str(path)})
    params = {"table": f"generated:{e.name}", "model": e.target}
    for k, v in e.params.items():
        params[k] = tuple(float(x) for x in v) if isinstance(v, (list, tuple)) else float(v)
    return MaterialSpec(name=f"generated:{e.name}", kind="merl", params=params)


def _base_name(m: MaterialSpec) -> str:
    return m.name.split(":", 1)[1] if ":" in m.name else m.name


def sample_materials(rng: np.random.Generator, n: int, catalogue: str | os.PathLike | None = None,
                     merl_fraction: float = 0.5, merl_dir: str | os.PathLike | None = None,
                     families: list[str] | None = None, require_merl: bool | None = None,
                     measured: str = "auto", holdout: str = "train",
                     split_file: str | os.PathLike | None = None) -> list[MaterialSpec]:
    """Draw `n` distinct materials; each is measured with probability `merl_fraction`.

    Measured materials come from `measured_pool(measured)`, restricted by
    `holdout` to the training side ('train': held-out materials excluded),
    the held-out side ('test') or everything ('all'). An empty pool is an
    InputError, never a silent substitution. `require_merl` (default: true when
    `merl_dir` or $MSPS_MERL_DIR is set) makes missing real MERL files an error
    listing every place searched. Analytic ones use `families` (config) or the
    catalogue's analytic entries. Consumes `rng` in a fixed order.
    """
    from msps_render.scene.materials import sample_analytic

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
    analytic = [sample_analytic(fams[int(i)], rng) for i in picks]
    mats = measured_mats + analytic
    order = rng.permutation(len(mats))
    out = [mats[int(i)] for i in order]
    log.info("materials: %s", ", ".join(m.name for m in out))
    return out


def _search_merl_name(name: str) -> Path:
    dirs = merl_search_dirs()
    p = find_merl(name if name.endswith(".binary") else f"{name}.binary", dirs)
    if p is None:
        raise InputError(f"merl:{name}", "MERL file not found; searched: " + ", ".join(str(d) for d in dirs))
    return p


def resolve_table(m: MaterialSpec) -> Path:
    """The `.binary` file behind a kind='merl' MaterialSpec (building a generated table if needed).

    params["table"]: an absolute path; "merl:<name>" (searched like the catalogue);
    or "generated:<name>" with "model" and the model's parameters in params.
    """
    from msps_render.brdf import analytic

    table = m.params.get("table")
    if not isinstance(table, str) or not table:
        raise InputError(f"material '{m.name}'", "a 'merl' material needs params.table (path or id)")
    if table.startswith("nbrdf:"):
        from msps_render.brdf import nbrdf

        w = nbrdf.weights_path(table[6:])
        if w is None:
            raise InputError(f"material '{m.name}'", f"no built-in Neural-BRDF weights '{table[6:]}.h5' in "
                                                     f"{nbrdf.builtin_dir()}")
        return nbrdf.baked_table(w)
    if table.startswith("generated"):
        model = m.params.get("model")
        if not isinstance(model, str):
            raise InputError(f"material '{m.name}'", "a generated table needs params.model")
        mp = {k: v for k, v in m.params.items() if k not in ("table", "model", "lobe_alpha", "lobe_weight")}
        try:
            return analytic.generated_table(model, mp)
        except (TypeError, ValueError) as e:
            raise InputError(f"material '{m.name}'", f"bad generated-table parameters ({e})") from None
    if table.startswith("merl:"):
        return _search_merl_name(table[5:])
    p = Path(table)
    if not p.is_file():
        raise InputError(p, f"MERL table of material '{m.name}' not found")
    return p.resolve()
