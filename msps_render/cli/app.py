"""The `msps` typer app and its error contract (`clean_errors`), shared by every command group."""
from __future__ import annotations

import functools
import signal

import typer

from msps_render.errors import InputError, Interrupted, WorkerDied, WriteFailed, fault_cause, write_fault

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


def _write_fault_line(e: BaseException, code: int, kw: dict) -> str:
    """'FILE: cause' for a write fault; where the library did not say which file, the command's
    --out (the place it was writing to).  Commands that resume say how to go on once it is fixed."""
    cause = fault_cause(code)
    if isinstance(e, WriteFailed):
        line = str(e)
    elif isinstance(e, OSError) and e.filename is not None:
        line = f"{e.filename}: {cause}"
    else:
        line = f"{kw['out']}: {cause}" if kw.get("out") is not None else cause
    if isinstance(e, WriteFailed) and "resume" in kw:  # our writers were writing: the run can go on
        line += "; nothing finished is lost: make room (or fix the place), then rerun with --resume"
    return line


def check_environment() -> None:
    """Settings read from the environment (MSPS_THREADS, MSPS_PROGRESS_EVERY), checked before a command
    does any work: a bad one is one line naming it, with nothing written."""
    from msps_render.progress import line_every_s
    from msps_render.render.variant import env_threads

    env_threads()
    line_every_s()


def clean_errors(fn):
    """Decorator: bad input or an unusable path -> one line + exit 1 (no traceback); a write fault
    (disk full, quota, read-only, file-size limit: `errors.write_fault`) likewise, naming the file;
    an interrupted render -> its summary line + exit 128 + signal (130 SIGINT, 143 SIGTERM)."""

    @functools.wraps(fn)
    def wrapper(*a, **kw):
        try:
            check_environment()
            return fn(*a, **kw)
        except (InputError, WorkerDied, OSError, RuntimeError) as e:
            code = write_fault(e)
            if code is not None:
                fail(_write_fault_line(e, code, kw))
            if isinstance(e, (InputError, WorkerDied)):
                fail(str(e))
            if isinstance(e, OSError) and (e.filename is not None or isinstance(e, (
                    PermissionError, FileNotFoundError, IsADirectoryError, NotADirectoryError, FileExistsError))):
                fail(_os_error_line(e))
            raise
        except Interrupted as e:
            typer.echo(str(e), err=True)
            raise typer.Exit(e.exit_code)
        except KeyboardInterrupt:  # Ctrl-C before a render's own handling began (config, validation)
            typer.echo("msps: interrupted", err=True)
            raise typer.Exit(128 + signal.SIGINT)

    return wrapper
