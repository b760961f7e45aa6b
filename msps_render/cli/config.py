"""Config commands: `msps config show | schema`."""
from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer

from msps_render.atomic import atomic_write
from msps_render.cli.app import app, clean_errors
from msps_render.errors import InputError

config_app = typer.Typer(add_completion=False, no_args_is_help=True,
                         context_settings={"help_option_names": ["-h", "--help"]},
                         help="Inspect configs: the resolved config and its plan, the reference of every key.")
app.add_typer(config_app, name="config")


def config_reference() -> str:
    """Markdown reference of every dataset and model config key (what docs/config.md holds)."""
    from msps_render.config_doc import reference
    from msps_render.models.presets import ModelConfig
    from msps_render.pipeline.config import DatasetConfig

    return reference([
        ("Dataset presets (`msps render`, `msps config show`)",
         "Files in `scenes/` (or any TOML path): `[dataset]`, `[scene]` and an optional `[sweep]`.",
         DatasetConfig),
        ("Model presets (`msps train`)",
         "Files in `models/` (or any TOML path), given to `msps train --config`.", ModelConfig),
    ])


@config_app.command("show")
@clean_errors
def show_cmd(config: str = typer.Argument(..., help="preset name (scenes/NAME.toml) or TOML path"),
             set_: List[str] = typer.Option([], "--set", help="override, e.g. lights.slant_deg=25"),
             probe: int = typer.Option(0, "--probe", min=0,
                                       help="render N frames of the plan (temp dir, deleted) to estimate "
                                            "patches, time and disk (default 0: the plan alone, nothing "
                                            "rendered)"),
             masks: int = typer.Option(32, "--masks", min=1,
                                       help="with --probe: count patches on the masks of N frames of the "
                                            "plan (one ray per pixel; all frames if fewer: then the count "
                                            "is exact)"),
             variant: Optional[str] = typer.Option(None, help="Mitsuba variant for the probe"),
             threads: Optional[int] = typer.Option(None, min=1, help="render threads for the probe"),
             as_json: bool = typer.Option(False, "--json", help="plan and estimates as JSON")):
    """Print the resolved config (every key, as TOML) and the planned work: conditions, shards,
    frames.  Nothing is rendered unless --probe N: then N frames are rendered into a temporary
    directory (deleted) to estimate patches, render time and disk."""
    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.describe import describe, plan_text

    from msps_render.pipeline.run import patch_grid_warning, zero_patch_cause

    cfg = load_config(config, list(set_))
    warning = patch_grid_warning(cfg)
    if warning:  # before the (optional) probe: the user sees it without rendering anything
        typer.echo(f"warning: {warning}", err=True)
    desc = describe(cfg, probe=probe, variant=variant, threads=threads, masks=masks)
    if desc.estimate is not None and desc.estimate.exact and desc.estimate.patches == 0:
        typer.echo(f"warning: this config yields 0 patches (every frame counted): {zero_patch_cause(cfg)}; "
                   "`msps render` would fail", err=True)
    elif desc.estimate is not None and desc.estimate.patches == 0:
        typer.echo(f"warning: the {desc.estimate.mask_frames} frames counted yield 0 patches: "
                   f"{zero_patch_cause(cfg)}", err=True)
    if as_json:
        typer.echo(json.dumps(desc.to_dict(), indent=2, default=str))
        return
    typer.echo(f"# resolved config: {getattr(cfg, '_source', config)}"
               + (f" with --set {' '.join(set_)}" if set_ else ""))
    typer.echo(desc.config_toml)
    typer.echo(plan_text(desc), nl=False)


@config_app.command("schema")
@clean_errors
def schema_cmd(out: Optional[Path] = typer.Option(None, "--out", "-o",
                                                  help="write here (e.g. docs/config.md) instead of stdout")):
    """Reference of every config key (type, default, allowed values, description), from the models."""
    text = config_reference()
    if out is None:
        typer.echo(text, nl=False)
        return
    if out.is_dir():
        raise InputError(out, "is a directory; give a file path")
    with atomic_write(out) as tmp:
        Path(tmp).write_text(text)
    typer.echo(f"wrote {out}")
