"""Reading TOML configs into pydantic models with one-line, named errors.

Shared by dataset presets (`pipeline.config`), model presets (`models.presets`),
scene configs (`scene.sample`) and the material catalogue (`brdf.library`).
"""
from __future__ import annotations

import tomllib
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Callable, TypeVar

from pydantic import BaseModel, ConfigDict

from msps_render.errors import InputError, closest, format_validation_error, read_text

M = TypeVar("M", bound=BaseModel)


class StrictModel(BaseModel):
    """The base of every config and spec model: unknown keys are errors."""

    model_config = ConfigDict(extra="forbid")


def omit_defaults(model: BaseModel, d, names) -> dict:
    """`d` (what `model`'s serializer made) without the fields `names` that hold their default or nothing.
    Why: fields added to a format later stay out of what configs and scenes without them serialise to, so
    their JSON, hashes and shards keep their bytes (each such model's `model_serializer` calls this)."""
    if isinstance(d, dict):
        for k in names:
            v = getattr(model, k)
            if k in d and (v == type(model).model_fields[k].default or v in ((), [], None)):
                d.pop(k)
    return d


class FrozenModel(StrictModel):
    """A `StrictModel` whose values are immutable once validated (scene data)."""

    model_config = ConfigDict(extra="forbid", frozen=True)


def read_toml(path: str | Path, what: str = "config") -> dict:
    p = Path(path)
    text = read_text(p, what)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise InputError(p, f"not valid TOML ({e})") from None


def set_path(data: dict, dotted: str, value) -> None:
    keys = dotted.split(".")
    d = data
    for k in keys[:-1]:
        d = d.setdefault(k, {})
        if not isinstance(d, dict):
            raise InputError(dotted, f"'{k}' is not a table")
    d[keys[-1]] = value


def coerce(text: str):
    """`--set` values are TOML literals (30, 0.5, true, [0, 120], "x"); bare words are strings."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def apply_overrides(data: dict, overrides, qualify: Callable[[str], str] = lambda k: k) -> dict:
    for ov in overrides:
        if "=" not in ov:
            raise InputError(f"--set {ov}", "expected key=value")
        k, v = ov.split("=", 1)
        set_path(data, qualify(k.strip()), coerce(v.strip()))
    return data


def check_override_keys(overrides, model: type[BaseModel], qualify: Callable[[str], str] = lambda k: k,
                        normalise: Callable[[dict], dict] = lambda d: d) -> None:
    """`InputError` naming the `--set` option whose key the model does not know (with a did-you-mean),
    so the preset file is not blamed for a typo on the command line."""
    for ov in overrides:
        if "=" not in ov:
            raise InputError(f"--set {ov}", "expected key=value")
        probe: dict = {}
        set_path(probe, qualify(ov.split("=", 1)[0].strip()), None)
        bad = unknown_keys(normalise(probe), model)
        if bad:
            raise InputError(f"--set {ov}", bad[0])


def unknown_keys(data: Any, model: type[BaseModel], prefix: str = "") -> list[str]:
    """Every key the model does not know, with a 'did you mean' suggestion."""
    out: list[str] = []
    if not isinstance(data, dict):
        return out
    fields = model.model_fields
    for k, v in data.items():
        if k not in fields:
            out.append(f"unknown key '{prefix}{k}'{closest(k, fields)}")
            continue
        ann = fields[k].annotation
        for cand in (ann, *getattr(ann, "__args__", ())):
            if isinstance(cand, type) and issubclass(cand, BaseModel):
                out += unknown_keys(v, cand, f"{prefix}{k}.")
                break
    return out


def validate(model: type[M], data: dict, source: str | Path, overrides=(),
             qualify: Callable[[str], str] = lambda k: k) -> M:
    """`data` as `model`; a bad value is blamed on the `--set` among `overrides` that gave it, else on `source`."""
    unknown = unknown_keys(data, model)
    if unknown:
        raise InputError(source, "; ".join(unknown))
    try:
        return model.model_validate(data)
    except Exception as e:
        raise _blame(e, source, overrides, qualify) from None


def _blame(err: Exception, source: str | Path, overrides, qualify: Callable[[str], str]) -> InputError:
    """Why: `--set dataset.n_shards=abc` is a typo on the command line; naming the preset file sends the
    user looking in the wrong place.  Errors outside every `--set` key stay the file's."""
    errors = err.errors() if callable(getattr(err, "errors", None)) else []
    for ov in overrides:
        key = qualify(ov.split("=", 1)[0].strip())
        mine = [e for e in errors if f"{'.'.join(map(str, e.get('loc', ())))}.".startswith(f"{key}.")]
        if mine:
            return InputError(f"--set {ov}", format_validation_error(SimpleNamespace(errors=lambda: mine)))
    return InputError(source, format_validation_error(err))
