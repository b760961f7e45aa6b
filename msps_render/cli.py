"""`msps` command line: a thin typer layer over the pipeline stages.

Every command turns `InputError` into one line on stderr and exit code 1, and
writes nothing until its inputs have been validated.
"""
from __future__ import annotations

import functools
import json
import sys
from pathlib import Path
from typing import Optional

import typer

from msps_render.errors import InputError, Interrupted, WorkerDied

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  context_settings={"help_option_names": ["-h", "--help"]},
                  help="Synthetic data for multispectral photometric stereo (Mitsuba 3) and the dual-cue network.")


def _print_version(value: bool) -> None:
    if value:
        import msps_render

        typer.echo(f"msps {msps_render.__version__}")
        raise typer.Exit()


@app.callback()
def _main(version: bool = typer.Option(False, "--version", "-V", is_eager=True, callback=_print_version,
                                       help="print the toolkit version and exit "
                                            "(`msps version`: with Mitsuba's)")) -> None:
    """Synthetic data for multispectral photometric stereo (Mitsuba 3) and the dual-cue network."""


def fail(msg: str, code: int = 1):
    typer.echo(f"error: {msg}", err=True)
    raise typer.Exit(code)


def _os_error_line(e: OSError) -> str:
    """'PATH: reason' for an OSError (read-only directory, path is a file, disk full, ...)."""
    what = e.strerror or (str(e).splitlines()[0] if str(e) else type(e).__name__)
    if isinstance(e, FileNotFoundError):
        what = "not found"
    if e.filename is None:
        return f"{what} ({type(e).__name__})"
    target = e.filename if e.filename2 is None else f"{e.filename} -> {e.filename2}"
    return f"{target}: {what}"


def clean_errors(fn):
    """Decorator: bad input or an unusable path -> one line + exit 1 (no traceback);
    an interrupted render -> its summary line + exit 128 + signal (130 SIGINT, 143 SIGTERM)."""

    @functools.wraps(fn)
    def wrapper(*a, **kw):
        try:
            return fn(*a, **kw)
        except (InputError, WorkerDied) as e:
            fail(str(e))
        except Interrupted as e:
            typer.echo(str(e), err=True)
            raise typer.Exit(e.exit_code)
        except OSError as e:
            if e.filename is None and not isinstance(e, (PermissionError, FileNotFoundError, IsADirectoryError,
                                                         NotADirectoryError, FileExistsError)):
                raise
            fail(_os_error_line(e))

    return wrapper


@app.command("render-scene")
@clean_errors
def render_scene(scene: Path = typer.Argument(..., help="SceneSpec JSON (see `msps sample-scene`)"),
                 out: Path = typer.Option(..., "--out", "-o", help="output directory"),
                 variant: Optional[str] = typer.Option(None, help="Mitsuba variant (default: best available)"),
                 threads: Optional[int] = typer.Option(None, help="render threads"),
                 per_light: bool = typer.Option(False, "--per-light", help="also write one image per light")):
    """Render one scene: image/normal/depth EXR + PNG previews + scene.json."""
    from msps_render.pipeline.outdir import check_writable
    from msps_render.render import render_frame
    from msps_render.scene.spec import SceneSpec

    spec = SceneSpec.load(scene)
    check_writable(out)
    import time

    c, n = spec.camera, len(spec.lights) + (spec.environment is not None)
    typer.echo(f"rendering {scene}: {c.width}x{c.height}, {spec.integrator.spp} spp, {n} emitter(s) rendered "
               "one by one ...")  # stdout: stderr is kept for the one error line
    t0 = time.perf_counter()
    frame = render_frame(spec, variant=variant, threads=threads, per_light=per_light)
    files = frame.save(out)
    typer.echo(f"rendered {scene} with {frame.variant} in {time.perf_counter() - t0:.1f} s -> {out} "
               f"({len(files)} files)")


@app.command("sample-scene")
@clean_errors
def sample_scene_cmd(out: Path = typer.Option(..., "--out", "-o", help="SceneSpec JSON to write"),
                     seed: int = typer.Option(0, help="seed"),
                     config: Optional[Path] = typer.Option(None, help="TOML with a \\[scene] table (SceneConfig)"),
                     show: bool = typer.Option(False, help="print the scene summary")):
    """Draw one SceneSpec from a seed (default scene config) and save it as JSON."""
    import numpy as np

    from msps_render.scene.sample import SceneConfig, load_scene_config, sample_scene

    from msps_render.pipeline.outdir import check_writable

    check_writable(out.parent)
    cfg = load_scene_config(config) if config else SceneConfig()
    spec = sample_scene(cfg, np.random.default_rng(seed), seed=seed)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(spec.to_json())
    if show:
        typer.echo(spec.summary())
    typer.echo(f"wrote {out}")


@app.command("demo")
@clean_errors
def demo(out: Path = typer.Option(Path("demo-out"), "--out", "-o", help="output directory")):
    """Render, verify and preview a tiny demo dataset (the README's first command)."""
    try:
        from msps_render.pipeline.demo import run_demo
    except ImportError:  # pipeline not installed: fall back to one rendered scene
        run_demo = None
    if run_demo is not None:
        sheet = run_demo(out)
        typer.echo(f"demo dataset in {out}; preview: {sheet}")
        return
    import numpy as np

    from msps_render.render import render_frame
    from msps_render.scene.sample import SceneConfig, sample_scene

    spec = sample_scene(SceneConfig(), np.random.default_rng(0), seed=0)
    frame = render_frame(spec)
    frame.save(out)
    typer.echo(f"demo scene rendered with {frame.variant} -> {out}")


@app.command("version")
def version():
    """Toolkit, Mitsuba and variant versions."""
    import msps_render

    info = {"msps": msps_render.__version__}
    try:
        import mitsuba as mi

        info["mitsuba"] = mi.__version__
        info["variants"] = mi.variants()
    except ImportError:
        info["mitsuba"] = None
    typer.echo(json.dumps(info, indent=2))


def _mount_subapps() -> None:
    """Pipeline and model commands live in their own modules (optional parts)."""
    for mod in ("msps_render.pipeline.cli", "msps_render.models.cli", "msps_render.workflows_cli"):
        try:
            sub = __import__(mod, fromlist=["app"]).app
        except ImportError:
            continue
        for cmd in sub.registered_commands:
            app.registered_commands.append(cmd)


_mount_subapps()


def main() -> None:  # pragma: no cover
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
