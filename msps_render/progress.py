"""Progress lines for the long model commands (eval, bench-real, predict), as `msps render` shows its own.

Why: a command that prints nothing for minutes looks hung.  One rich `Progress` on stderr (stdout
stays the command's result), one line per stage (a condition's frames, its patches, an object, an
image's tiles), each with its count, elapsed time and ETA.  Disabled, every call is a no-op, so
library callers and tests pass `progress=False` and see nothing.
"""
from __future__ import annotations

import os


class Task:
    """One stage's line: `advance(n)` as units finish; `describe(text)` when the stage's work changes."""

    def __init__(self, progress, task_id):
        self._p, self._id = progress, task_id

    def advance(self, n: int = 1) -> None:
        self._p.advance(self._id, n)

    def describe(self, text: str) -> None:
        self._p.update(self._id, description=text)

    def set(self, completed: int, total: int | None = None) -> None:
        self._p.update(self._id, completed=completed, **({} if total is None else {"total": total}))


class _PlainTask:
    """A `Task` that writes plain lines (`LineTicker`) instead of redrawing a bar: output to a file."""

    def __init__(self, description: str, total: int | None):
        self.n = 0
        self.t = LineTicker(description, total, unit="item")

    def advance(self, n: int = 1) -> None:
        self.n += n
        self.t.update(self.n)

    def describe(self, text: str) -> None:
        self.t.note(text)

    def set(self, completed: int, total: int | None = None) -> None:
        if total is not None:
            self.t.total = total
        self.n = completed
        self.t.update(completed)

    def close(self) -> None:
        self.t.close()


class Bar:
    """A context manager holding the command's progress lines; `task(...)` is None when disabled.
    On a terminal: rich bars; when stderr is a file (nohup, Slurm, CI): plain lines every
    `LINE_EVERY_S` seconds and one when each stage ends (`LineTicker`)."""

    def __init__(self, enabled: bool = True):
        import sys

        self.enabled = enabled
        self._p = None
        self._plain: list[_PlainTask] | None = [] if enabled and not sys.stderr.isatty() else None

    def __enter__(self) -> "Bar":
        if self.enabled and self._plain is None:
            from rich.console import Console
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                                       TimeRemainingColumn)

            self._p = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                               TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
                               console=Console(stderr=True), transient=False)
            self._p.start()
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if self._p is not None:
            self._p.stop()
            self._p = None
        for t in self._plain or ():
            if exc_type is None:  # a failing command ends on its one error line, not on a progress line
                t.close()
            else:
                t.t.enabled = False

    def task(self, description: str, total: int | None) -> Task | None:
        if self._plain is not None:
            if self._plain and self._plain[-1].t.enabled:  # the previous stage is over: its last line
                self._plain[-1].close()
            self._plain.append(_PlainTask(description, total))
            return self._plain[-1]
        if self._p is None:
            return None
        return Task(self._p, self._p.add_task(description, total=total))


LINE_EVERY_S = 15.0  # plain lines at least this often (s) in a log; $MSPS_PROGRESS_EVERY changes it


def line_every_s() -> float:
    """Seconds between plain progress lines: $MSPS_PROGRESS_EVERY (>= 0; 0: every update), else
    `LINE_EVERY_S`.  Read when a loop starts, not at import: a bad value is one line naming the variable
    (it was a ValueError traceback at import, which broke every command)."""
    from msps_render.errors import InputError

    v = os.environ.get("MSPS_PROGRESS_EVERY", "").strip()
    if not v:
        return LINE_EVERY_S
    try:
        s = float(v)
    except ValueError:
        s = -1.0
    if not s >= 0:  # also NaN
        raise InputError("MSPS_PROGRESS_EVERY", f"must be a number of seconds >= 0, got {v!r}")
    return s


def _duration(s: float) -> str:
    s = max(0, int(round(s)))
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


STARTUP_NOTICE_S = 5.0  # a start-up stage (or a first step) longer than this says so (0 with MSPS_PROGRESS_EVERY=0)


def startup_notice_s() -> float:
    return 0.0 if line_every_s() == 0 else STARTUP_NOTICE_S


class StartupStage:
    """What a command does before its loop starts, as plain lines on a terminal and in a log alike: `name:
    text` once the stage has lasted `startup_notice_s()`, then, when it ends, `name: done` (set `.done` to
    say what came of it) with its seconds.  Why: reading and verifying a corpus or starting a device can
    take longer than the 15 s between progress lines, and a command that says nothing that long looks
    hung.  A short stage prints nothing, so a run that fails at once still ends on its one error line."""

    def __init__(self, name: str, text: str, enabled: bool = True, stream=None):
        import sys

        self.name, self.text, self.enabled = name, text, enabled
        self.stream = stream or sys.stderr
        self.done = "done"
        self._said = False
        self._timer = None

    def _say(self) -> None:
        self._said = True
        print(f"{self.name}: {self.text}", file=self.stream, flush=True)

    def __enter__(self) -> "StartupStage":
        import threading
        import time

        self._t0 = time.perf_counter()
        if self.enabled:
            wait = startup_notice_s()
            if wait == 0:
                self._say()
            else:
                self._timer = threading.Timer(wait, self._say)
                self._timer.daemon = True
                self._timer.start()
        return self

    def __exit__(self, exc_type, *exc) -> None:
        import time

        if self._timer is not None:
            self._timer.cancel()
            self._timer.join()
        if self._said and exc_type is None:
            print(f"{self.name}: {self.done} ({time.perf_counter() - self._t0:.1f} s)", file=self.stream, flush=True)


class LineTicker:
    """Progress of one long loop: a tqdm bar on a terminal; plain lines (`name: done/total unit, rate, ETA,
    note`) every `every_s` seconds on stderr when it is a file (nohup, Slurm, CI logs), so a log shows
    the run moving, not only its end.  `first_line`: also a line at the loop's first unit when it took
    longer than `startup_notice_s()` (a training's first step includes the device's warm-up)."""

    def __init__(self, name: str, total: int | None, enabled: bool = True, unit: str = "it", start: int = 0,
                 every_s: float | None = None, stream=None, budget_s: float | None = None, first_line: bool = False):
        import sys
        import time

        self.name, self.total, self.unit = name, total, unit
        self.every_s = every_s if every_s is not None else line_every_s()
        self.budget_s = budget_s  # a time budget that may end the loop before `total`
        self.enabled, self._time = enabled, time.perf_counter
        self.stream = stream or sys.stderr
        self.n = self.n0 = start
        self.t0 = self._last = self._time()
        self._note = ""
        self._bar = None
        self._first = first_line
        if enabled and self.stream.isatty():
            from tqdm import tqdm

            self._bar = tqdm(total=total, initial=start, unit=unit, dynamic_ncols=True, file=self.stream)

    def line(self) -> str:
        dt = self._time() - self.t0
        rate = (self.n - self.n0) / dt if dt > 0 else 0.0
        of = f"/{self.total}" if self.total else ""
        left = (self.total - self.n) / rate if self.total and rate > 0 else None
        if self.budget_s is not None:
            left = max(0.0, self.budget_s - dt) if left is None else min(left, max(0.0, self.budget_s - dt))
        eta = f", ETA {_duration(left)}" if left is not None else ""
        return (f"{self.name}: {self.n}{of} {self.unit}s, {rate:.2f} {self.unit}/s, elapsed {_duration(dt)}{eta}"
                + (f"; {self._note}" if self._note else ""))

    def update(self, n: int) -> None:
        if not self.enabled:
            return
        if self._bar is not None:
            self._bar.update(n - self.n)
            self.n = n
            return
        self.n = n
        first = self._first and n > self.n0
        if first:
            self._first = False
            first = self._time() - self.t0 >= startup_notice_s()
        if first or self._time() - self._last >= self.every_s:
            self._last = self._time()
            print(self.line(), file=self.stream, flush=True)

    def note(self, text: str) -> None:
        self._note = text
        if self._bar is not None:
            self._bar.set_postfix_str(text)

    def close(self, ok: bool = True) -> None:
        """The last line (`ok` False: the loop failed -- its command ends on its one error line instead)."""
        if self._bar is not None:
            self._bar.close()
        elif self.enabled and ok:
            print(self.line(), file=self.stream, flush=True)
        self.enabled = False
