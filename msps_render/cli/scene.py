"""Scene commands: `msps render-scene | sample-scene | demo | version`."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from msps_render.cli.app import app, clean_errors


@app.command("render-scene")
@clean_errors
def render_scene(scene: Path = typer.Argument(..., help="SceneSpec JSON (see `msps sample-scene`)"),
                 out: Path = typer.Option(..., "--out", "-o", help="output directory"),
                 variant: Optional[str] = typer.Option(None, help="Mitsuba variant (default: best available)"),
                 threads: Optional[int] = typer.Option(None, min=1, help="render threads"),
                 per_light: bool = typer.Option(False, "--per-light", help="also write one image per light")):
    """Render one scene: image/normal/depth EXR + PNG previews + scene.json."""
    from msps_render.pipeline.outdir import check_writable
    from msps_render.render import render_frame, resolve_variant
    from msps_render.scene.spec import SceneSpec

    spec = SceneSpec.load(scene)
    variant = resolve_variant(spec.mode, variant)  # a wrong --variant: one line before anything is written
    check_writable(out)
    import time

    c, n = spec.camera, len(spec.lights) + (spec.environment is not None)
    how = "in one pass" if spec.integrator.lights == "one-pass" else "one by one"
    typer.echo(f"rendering {scene}: {c.width}x{c.height}, {spec.integrator.spp} spp, {n} emitter(s) rendered "
               f"{how} ...")  # stdout: stderr is kept for the one error line
    t0 = time.perf_counter()
    frame = render_frame(spec, variant=variant, threads=threads, per_light=per_light)
    files = frame.save(out)
    typer.echo(f"rendered {scene} with {frame.variant} in {time.perf_counter() - t0:.1f} s -> {out} "
               f"({len(files)} files)")


@app.command("sample-scene")
@clean_errors
def sample_scene_cmd(out: Path = typer.Option(..., "--out", "-o", help="SceneSpec JSON to write"),
                     seed: int = typer.Option(0, min=0, help="seed"),
                     config: Optional[Path] = typer.Option(None, help="TOML with a \\[scene] table (SceneConfig)"),
                     show: bool = typer.Option(False, help="print the scene summary")):
    """Draw one SceneSpec from a seed (default scene config) and save it as JSON."""
    import numpy as np

    from msps_render.atomic import write_text
    from msps_render.pipeline.outdir import check_writable
    from msps_render.scene.sample import SceneConfig, load_scene_config, sample_scene

    check_writable(out.parent)
    cfg = load_scene_config(config) if config else SceneConfig()
    spec = sample_scene(cfg, np.random.default_rng(seed), seed=seed)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_text(out, spec.to_json())
    if show:
        typer.echo(spec.summary())
    typer.echo(f"wrote {out}")


@app.command("demo")
@clean_errors
def demo(out: Path = typer.Option(Path("demo-out"), "--out", "-o", help="output directory")):
    """Render, verify and preview a tiny demo dataset (the README's first command)."""
    from msps_render.pipeline.demo import run_demo

    sheet = run_demo(out)
    typer.echo(f"demo dataset in {out}; preview: {sheet}")


@app.command("version")
def version():
    """Toolkit, Mitsuba and variant versions."""
    import msps_render
    from msps_render.render.variant import mitsuba_info

    typer.echo(json.dumps({"msps": msps_render.__version__, **mitsuba_info()}, indent=2))
