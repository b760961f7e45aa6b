"""A reference of every config key, generated from the pydantic models themselves.

`reference()` walks config models (`DatasetConfig`, `ModelConfig`: the CLI's
`cli.config.config_reference` names them) field by field: key path, type,
default, constraints and the field's `description`.  `msps config schema` prints it; `docs/config.md` is its output and
`tests/test_cli_config.py` fails when the file is out of sync.
"""
from __future__ import annotations

import inspect
import json
import types
import typing
from typing import Any, Literal

from pydantic import BaseModel
from pydantic_core import PydanticUndefined

HEADER = """# Config reference

Generated from the pydantic models by `msps config schema > docs/config.md`
(`msps_render/config_doc.py`); do not edit by hand:
`tests/test_cli_config.py` fails when this file and the models differ.

Every key below can be set in a preset's TOML or on the command line with
`--set key=value` (`lights.slant_deg=25` is short for `scene.lights.slant_deg=25`).
`msps config show CONFIG` prints the resolved value of every key.
Units: angles in degrees (`*_deg`), lengths in scene units (the object fits in
the unit sphere), light values in the renderer's linear radiometric units.
"""


def _model_of(ann) -> type[BaseModel] | None:
    """The pydantic model inside `ann` (`M` or `M | None`), else None."""
    for cand in (ann, *typing.get_args(ann)):
        if isinstance(cand, type) and issubclass(cand, BaseModel):
            return cand
    return None


def type_name(ann) -> str:
    origin = typing.get_origin(ann)
    args = typing.get_args(ann)
    if ann is type(None):
        return "none"
    if origin is Literal:
        return " \\| ".join(json.dumps(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        return " \\| ".join(type_name(a) for a in args)
    if origin in (list, tuple):
        if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
            return f"list of {type_name(args[0])}"
        if origin is tuple:
            return f"[{', '.join(type_name(a) for a in args)}]"
        return f"list of {type_name(args[0])}" if args else "list"
    if isinstance(ann, type) and issubclass(ann, BaseModel):
        return "table"
    if ann is Any:
        return "any"
    return getattr(ann, "__name__", str(ann))


def _default(field) -> str:
    if field.default_factory is not None:
        v = field.default_factory()
    elif field.default is PydanticUndefined:
        return "*required*"
    else:
        v = field.default
    if isinstance(v, BaseModel):
        return "(table)"
    if v is None:
        return "unset"
    if isinstance(v, tuple):
        v = list(v)
    return "`" + json.dumps(v) + "`"


def _bounds(field) -> str:
    words = {"gt": ">", "ge": ">=", "lt": "<", "le": "<=", "min_length": "length >=", "max_length": "length <="}
    out = []
    for m in field.metadata:
        for attr, sym in words.items():
            v = getattr(m, attr, None)
            if v is not None:
                out.append(f"{sym} {v:g}" if isinstance(v, float) else f"{sym} {v}")
    return ", ".join(out)


def _doc(model: type[BaseModel]) -> str:
    d = model.__dict__.get("__doc__")
    return inspect.cleandoc(d) if d else ""


def _cell(text: str) -> str:
    return text.replace("\n", " ").replace("|", "\\|") if text else ""


def model_sections(model: type[BaseModel], prefix: str = "") -> list[tuple[str, type[BaseModel], list]]:
    """[(table path, model, [(key, FieldInfo)])] depth-first, in declaration order."""
    rows, subs = [], []
    for name, f in model.model_fields.items():
        sub = _model_of(f.annotation)
        if sub is not None:
            subs.append((f"{prefix}{name}", sub))
        else:
            rows.append((name, f))
    out = [(prefix.rstrip("."), model, rows)] if rows or not prefix else []
    for path, sub in subs:
        out += model_sections(sub, f"{path}.")
    return out


def _section(title: str, intro: str, model: type[BaseModel]) -> list[str]:
    L = [f"## {title}", "", intro, ""]
    optional = {}
    for path, m, rows in model_sections(model):
        if not path:
            continue
        L.append(f"### `[{path}]`")
        L.append("")
        parent, _, leaf = path.rpartition(".")
        holder = model
        for part in [p for p in parent.split(".") if p]:
            holder = _model_of(holder.model_fields[part].annotation)
        f = holder.model_fields[leaf]
        if f.default is None:
            optional[path] = True
            L.append("Optional table: absent (unset) unless given.")
            L.append("")
        doc = _doc(m)
        if doc:
            L += [doc, ""]
        L.append("| key | type | default | allowed | description |")
        L.append("|---|---|---|---|---|")
        for name, fi in rows:
            L.append(f"| `{path}.{name}` | {type_name(fi.annotation)} | {_default(fi)} | {_cell(_bounds(fi))} "
                     f"| {_cell(fi.description or '')} |")
        L.append("")
    return L


def reference(sections: list[tuple[str, str, type[BaseModel]]]) -> str:
    """The whole reference (Markdown, deterministic): one section per (title, intro, root model)."""
    L = [HEADER]
    for title, intro, model in sections:
        L += _section(title, intro, model)
    return "\n".join(L).rstrip("\n") + "\n"
