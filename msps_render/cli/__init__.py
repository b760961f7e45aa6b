"""`msps` command line: a thin typer layer over the pipeline stages, one module per command group
(`scene`, `dataset`, `config`, `models`, `workflows`), all registered on the one `app` of `cli.app`.

Every command turns `InputError` into one line on stderr and exit code 1, and
writes nothing until its inputs have been validated.  torch and Mitsuba are
imported only inside the commands that need them.
"""
import os
import signal
import sys
import threading


def _interrupted_while_starting(signum, frame):  # pragma: no cover - exercised by tests/test_faults.py
    """Ctrl-C while the commands are still being imported: nothing has been opened or written yet, so end
    at once with one line and 128 + SIGINT (a traceback through half-imported modules says nothing)."""
    sys.stderr.write("msps: interrupted while starting; nothing was written\n")
    sys.stderr.flush()
    os._exit(128 + signal.SIGINT)


_own_handler = (threading.current_thread() is threading.main_thread()
                and signal.getsignal(signal.SIGINT) is signal.default_int_handler)
if _own_handler:
    signal.signal(signal.SIGINT, _interrupted_while_starting)
try:
    from msps_render.cli import scene, dataset, config, models, workflows  # noqa: F401, I001, E402  (registers the commands, in help order)
    from msps_render.cli.app import app, clean_errors, fail  # noqa: E402
finally:
    if _own_handler:  # the commands rely on KeyboardInterrupt from here on (a render stops cleanly on it)
        signal.signal(signal.SIGINT, signal.default_int_handler)

__all__ = ["app", "clean_errors", "fail", "main"]


def main() -> None:  # pragma: no cover
    app()
