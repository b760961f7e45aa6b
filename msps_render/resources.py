"""Where the shipped data lives: `brdf/` (material library), `scenes/` (dataset presets),
`models/` (model presets and the shipped checkpoint).

One resolver for all three, in this order: an environment variable
(`MSPS_BRDF_DIR`, `MSPS_SCENES_DIR`, `MSPS_MODELS_DIR`), the folder of the
checkout this package runs from, then the copy installed with the package
(`msps_render/_data/<kind>`, package data of the wheel, read through
`importlib.resources`).
"""
from __future__ import annotations

import os
from importlib import resources
from pathlib import Path

KINDS = ("brdf", "scenes", "models")
ENV = {"brdf": "MSPS_BRDF_DIR", "scenes": "MSPS_SCENES_DIR", "models": "MSPS_MODELS_DIR"}
CHECKOUT = Path(__file__).resolve().parents[1]
PACKAGE_DATA = "_data"  # msps_render/_data/<kind> in an installed wheel


def shipped_dir(kind: str) -> Path:
    """The folder shipped with the code: the checkout's `<kind>/`, else the installed package data."""
    if kind not in KINDS:
        raise ValueError(f"unknown data kind {kind!r} (known: {', '.join(KINDS)})")
    checkout = CHECKOUT / kind
    if (CHECKOUT / "pyproject.toml").is_file() and checkout.is_dir():  # running from a source checkout
        return checkout
    return Path(str(resources.files("msps_render") / PACKAGE_DATA / kind))


def data_dir(kind: str) -> Path:
    """`$MSPS_<KIND>_DIR` if set, else `shipped_dir(kind)`."""
    env = os.environ.get(ENV[kind]) if kind in ENV else None
    return Path(env) if env else shipped_dir(kind)


def find(kind: str, name: str | os.PathLike, suffix: str = ".toml") -> Path | None:
    """An existing file `name`, or the preset `<data_dir(kind)>/<name><suffix>`, or None."""
    p = Path(name)
    if p.is_file():
        return p
    cand = data_dir(kind) / f"{name}{suffix}"
    return cand if cand.is_file() else None


def names(kind: str, suffix: str = ".toml") -> list[str]:
    """The presets of a kind (file stems), sorted."""
    d = data_dir(kind)
    return sorted(q.stem for q in d.glob(f"*{suffix}")) if d.is_dir() else []
