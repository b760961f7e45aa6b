"""Ctrl-C while `msps` only imports (its commands, then Mitsuba): nothing has been opened or written
yet, so end at once with one line and 128 + SIGINT.  A KeyboardInterrupt raised inside an import
prints a traceback through half-imported modules, and inside drjit's extension import it even turns
into a NameError.  Standard library only: this runs before anything else is imported."""
from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading


def _interrupted_while_starting(signum, frame):  # pragma: no cover - exercised by tests/test_faults.py
    sys.stderr.write("msps: interrupted while starting; nothing was written\n")
    sys.stderr.flush()
    os._exit(128 + signal.SIGINT)


@contextlib.contextmanager
def nothing_written_yet():
    """Within: SIGINT ends the process at once (one line, exit 130).  After: Python's default
    KeyboardInterrupt again, which the commands rely on (a render stops cleanly on it).  Only where
    SIGINT is Python's default handler in the main thread (never inside someone else's program)."""
    own = (threading.current_thread() is threading.main_thread()
           and signal.getsignal(signal.SIGINT) is signal.default_int_handler)
    if own:
        signal.signal(signal.SIGINT, _interrupted_while_starting)
    try:
        yield
    finally:
        if own:
            signal.signal(signal.SIGINT, signal.default_int_handler)
