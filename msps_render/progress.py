"""Progress lines for the long model commands (eval, bench-real, predict), as `msps render` shows its own.

Why: a command that prints nothing for minutes looks hung.  One rich `Progress` on stderr (stdout
stays the command's result), one line per stage (a condition's frames, its patches, an object, an
image's tiles), each with its count, elapsed time and ETA.  Disabled, every call is a no-op, so
library callers and tests pass `progress=False` and see nothing.
"""
from __future__ import annotations


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


class Bar:
    """A context manager holding the command's progress lines; `task(...)` is None when disabled."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self._p = None

    def __enter__(self) -> "Bar":
        if self.enabled:
            from rich.console import Console
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                                       TimeRemainingColumn)

            self._p = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                               TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
                               console=Console(stderr=True), transient=False)
            self._p.start()
        return self

    def __exit__(self, *exc) -> None:
        if self._p is not None:
            self._p.stop()
            self._p = None

    def task(self, description: str, total: int | None) -> Task | None:
        if self._p is None:
            return None
        return Task(self._p, self._p.add_task(description, total=total))
