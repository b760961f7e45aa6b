"""The material library: catalogue loading, MERL file discovery, the held-out split,
and the table behind a measured material (`resolve_table`).

Measured tables are real MERL files, built-in Neural-BRDF fits (`brdf/nbrdf/`,
baked into a MERL table on first use) or tables generated from analytic models
(`generated:<name>`, only when asked for).  Held-out materials
(`brdf/split.toml`) are excluded from training corpora.  Nothing is
downloaded.  Drawing materials for a scene is `msps_render.scene.materials`.
"""
from __future__ import annotations

import functools
import os
from dataclasses import dataclass, field
from pathlib import Path

from pydantic import Field, field_validator, model_validator

from msps_render.brdf import analytic, nbrdf
from msps_render.brdf.analytic import MODELS
from msps_render.brdf.families import FAMILIES
from msps_render.config_io import StrictModel, read_toml, validate
from msps_render.errors import InputError, closest
from msps_render.resources import shipped_dir

REPO_BRDF_DIR = shipped_dir("brdf")
DEFAULT_CATALOGUE = REPO_BRDF_DIR / "catalogue.toml"
DEFAULT_SPLIT = REPO_BRDF_DIR / "split.toml"
SOURCES = ("merl", "generated", "analytic")
MEASURED = ("auto", "merl", "nbrdf", "generated")  # where measured materials come from
HOLDOUT = ("train", "test", "all")  # which side of the held-out split a corpus draws from


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
        raise InputError(self.path, f"no material named '{name}'{closest(name, [e.name for e in self.entries])}")


def _catalogue_path(catalogue: str | os.PathLike | None) -> Path:
    if catalogue is not None:
        return Path(catalogue)
    if os.environ.get("MSPS_BRDF_CATALOGUE"):
        return Path(os.environ["MSPS_BRDF_CATALOGUE"])
    return DEFAULT_CATALOGUE


class CatalogueEntry(StrictModel):
    """One `[[material]]` table: `source` is "merl:<file>" | "generated:<model>" | "analytic:<family>"."""

    name: str
    source: str
    params: dict = Field(default_factory=dict)

    @field_validator("source")
    @classmethod
    def _source(cls, v: str) -> str:
        kind, _, target = v.partition(":")
        if not target:
            raise ValueError('needs name = "..." and source = "merl:<file>" | "generated:<model>" | '
                             '"analytic:<family>"')
        if kind not in SOURCES:
            raise ValueError(f"unknown source kind '{kind}' (known: {', '.join(SOURCES)})")
        if kind == "generated" and target not in MODELS:
            raise ValueError(f"unknown model '{target}' (known: {', '.join(MODELS)})")
        if kind == "analytic" and target not in FAMILIES:
            raise ValueError(f"unknown family '{target}' (known: {', '.join(FAMILIES)})")
        return v


class CatalogueFile(StrictModel):
    """`brdf/catalogue.toml`, validated like every other config (unknown keys are errors)."""

    version: int = 1
    material: list[CatalogueEntry] = Field(default_factory=list)

    @model_validator(mode="after")
    def _check(self) -> "CatalogueFile":
        if not self.material:
            raise ValueError("catalogue lists no [[material]]")
        seen: set[str] = set()
        for m in self.material:
            if m.name in seen:
                raise ValueError(f"duplicate material name '{m.name}'")
            seen.add(m.name)
        return self


@functools.lru_cache(maxsize=32)
def _load_catalogue(path: str) -> Catalogue:
    p = Path(path)
    cat = validate(CatalogueFile, read_toml(p, "material catalogue"), p)
    entries = tuple(Entry(name=m.name, source=m.source.split(":", 1)[0], target=m.source.split(":", 1)[1],
                          params=dict(m.params)) for m in cat.material)
    return Catalogue(path=str(p), entries=entries)


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


def find_merl(target: str, dirs: list[Path], listed: dict[Path, frozenset[str]] | None = None) -> Path | None:
    """First existing `<dir>/<target>` (target is the file name from `merl:<file>`).

    `listed` (from `list_files(dirs)`): the folders' file names, read once for many lookups --
    the scene sampler resolves every catalogue entry for every frame (~500 `stat` calls)."""
    plain = listed is not None and "/" not in target and os.sep not in target
    for d in dirs:
        if (target in listed.get(d, ())) if plain else (d / target).is_file():
            return (d / target).resolve()
    return None


def list_files(dirs: list[Path]) -> dict[Path, frozenset[str]]:
    """Names of the regular files in each folder (none when it is not a readable folder)."""
    out = {}
    for d in dirs:
        try:
            with os.scandir(d) as it:
                out[d] = frozenset(e.name for e in it if e.is_file())
        except OSError:
            out[d] = frozenset()
    return out


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


def _search_merl_name(name: str) -> Path:
    dirs = merl_search_dirs()
    p = find_merl(name if name.endswith(".binary") else f"{name}.binary", dirs)
    if p is None:
        raise InputError(f"merl:{name}", "MERL file not found; searched: " + ", ".join(str(d) for d in dirs))
    return p


def resolve_table(m) -> Path:
    """The `.binary` file behind a kind='merl' material (a `MaterialSpec`, or anything with
    `name` and `params`), building a generated table if needed.

    params["table"]: an absolute path; "merl:<name>" (searched like the catalogue);
    or "generated:<name>" with "model" and the model's parameters in params.
    """
    table = m.params.get("table")
    if not isinstance(table, str) or not table:
        raise InputError(f"material '{m.name}'", "a 'merl' material needs params.table (path or id)")
    if table.startswith("nbrdf:"):
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
