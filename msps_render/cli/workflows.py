"""Researchers' workflows: `msps export` (data out in other tools' layouts) and `msps compose`
(real per-light captures in)."""
from __future__ import annotations

import shlex
from pathlib import Path
from typing import Optional

import typer

from msps_render.cli.app import app, clean_errors
from msps_render.cli.models import PNG_HELP


def _run(fn):
    return clean_errors(fn)()


def _format_help() -> str:
    from msps_render.export import FORMATS

    seen, parts = set(), []
    for name, f in FORMATS.items():
        if f.name not in seen:
            seen.add(f.name)
            parts.append(f"{f.name}{' (per-light: needs --rerender)' if f.per_light else ''}")
    return "one of: " + ", ".join(parts) + "; pmsdata = diligent"


@app.command("export")
def export_cmd(dataset: Path = typer.Argument(..., help="dataset directory rendered with "
                                              "dataset.storage.store_frames = true"),
               format: str = typer.Option(..., "--format", "-f", help=_format_help()),
               out: Path = typer.Option(..., "--out", "-o", help="new (or empty) output directory"),
               rerender: bool = typer.Option(False, "--rerender", help="re-render per-light images from the "
                                             "scenes stored in the shards (needs Mitsuba; only for shards "
                                             "rendered without dataset.storage.store_per_light)")):
    """Write a dataset's whole frames as per-frame PNG16/EXR, or in the PS-FCN or DiLiGenT layout."""

    def go():
        from msps_render.export import export_dataset

        def progress(i, ef):
            if rerender:
                typer.echo(f"  frame {i + 1}: {ef.id}", err=True)

        idx = export_dataset(dataset, format, out, rerender=rerender, progress=progress)
        typer.echo(f"exported {idx['n_frames']} frames as {idx['format']} -> {out} (index: export.json)")

    _run(go)


@app.command("compose")
def compose_cmd(capture: Path = typer.Argument(..., help="DiLiGenT-style folder: one photo per white light, "
                                               "light_directions.txt, light_intensities.txt, mask.png"),
                out: Path = typer.Option(..., "--out", "-o", help="new (or empty) output directory"),
                slant: float = typer.Option(30.0, help="target slant of the three lights (deg)"),
                tilts: str = typer.Option("0,120,240", help="target tilts (deg, comma-separated)"),
                crosstalk: Optional[str] = typer.Option(None, help="'paper' (default, 0.92/0.04), 'identity' "
                                                        "or a JSON 3x3 (rows: channels, columns: lights)"),
                linear: Optional[bool] = typer.Option(None, "--linear/--srgb", help=PNG_HELP)):
    """Combine three per-light photos into one pseudo-multispectral image + calibration.json for `msps predict`."""

    def go():
        from msps_render.compose import compose_capture, parse_crosstalk
        from msps_render.errors import InputError

        try:
            t = [float(x) for x in tilts.split(",") if x.strip()]
        except ValueError:
            raise InputError("--tilts", f"not a comma-separated list of numbers: {tilts!r}") from None
        r = compose_capture(capture, out, slant, t, parse_crosstalk(crosstalk), linear)
        for w in r["warnings"]:
            typer.echo(f"warning: {w}", err=True)
        dev = ", ".join(f"{n} ({d:.1f} deg off)" for n, d in zip(r["images"], r["deviation_deg"]))
        q = {n: shlex.quote(str(out / n)) for n in ("image.exr", "mask.png", "calibration.json", "normals")}
        typer.echo(f"composed {dev} -> {out}/image.exr; predict with: msps predict "
                   f"{q['image.exr']} --mask {q['mask.png']} --calibration {q['calibration.json']} --out {q['normals']}")

    _run(go)
