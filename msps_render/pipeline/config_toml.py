"""A resolved `DatasetConfig` as TOML: every key, defaults included.

TOML has no null, so a key whose value is None (unset optional) is written as a
comment (`# key = (unset)`); reading the text back gives the same config
(`config_hash` equal), which `tests/test_cli_config.py` checks.
"""
from __future__ import annotations

import tomli_w

from msps_render.pipeline.config import DatasetConfig


def _value(v) -> str:
    return tomli_w.dumps({"v": v}).split("=", 1)[1].strip()


def _table(data: dict, path: list[str], out: list[str]) -> None:
    scalars = [(k, v) for k, v in data.items() if not isinstance(v, dict)]
    tables = [(k, v) for k, v in data.items() if isinstance(v, dict)]
    if path and (scalars or not tables):
        out.append(f"\n[{'.'.join(path)}]")
    for k, v in scalars:
        out.append(f"# {k} = (unset)" if v is None else f"{k} = {_value(v)}")
    for k, v in tables:
        _table(v, path + [k], out)


def config_toml(cfg: DatasetConfig) -> str:
    """Every key of the resolved config (defaults included) as TOML text."""
    data = cfg.model_dump(mode="json")
    out: list[str] = []
    top_none = [k for k, v in data.items() if v is None]
    for k in top_none:  # e.g. no [sweep]
        out.append(f"# [{k}] (unset)")
    _table({k: v for k, v in data.items() if v is not None}, [], out)
    return "\n".join(out).lstrip("\n") + "\n"
