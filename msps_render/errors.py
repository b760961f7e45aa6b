"""One error type for bad input, so the CLI can print one clear line and exit 1."""
from __future__ import annotations

import difflib
from pathlib import Path


class InputError(ValueError):
    """Bad user input: names the offending file (or config key) and what is wrong."""

    def __init__(self, source: str | Path, problem: str):
        self.source = str(source)
        self.problem = problem
        super().__init__(f"{self.source}: {problem}")

    def __reduce__(self):  # crosses process boundaries intact (local pool, Dask)
        return (type(self), (self.source, self.problem))


class WorkerDied(RuntimeError):
    """A worker process ended without reporting its shard (killed, crashed, out of memory)."""


class Interrupted(Exception):
    """A render stopped by SIGINT/SIGTERM after cleaning up; the CLI exits 128 + signum."""

    def __init__(self, signum: int, done: int, total: int):
        self.signum, self.done, self.total = int(signum), int(done), int(total)
        super().__init__(f"interrupted: {done} of {total} shards done; rerun with --resume")

    def __reduce__(self):
        return (type(self), (self.signum, self.done, self.total))

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


def brief(text: str, limit: int = 120) -> str:
    """First line of `text`, cut at a word boundary to at most `limit` characters (with '...')."""
    line = (text or "").strip().splitlines()[0] if (text or "").strip() else ""
    if len(line) <= limit:
        return line
    cut = line[:limit - 3]
    if " " in cut[limit // 2:]:
        cut = cut[:cut.rindex(" ")]
    return cut.rstrip(" ,;:") + "..."


def closest(name: str, choices) -> str:
    """' (did you mean X?)' suffix for an unknown name, or ''."""
    match = difflib.get_close_matches(name, list(choices), n=1, cutoff=0.5)
    return f" (did you mean '{match[0]}'?)" if match else ""


def not_a_dataset(root: str | Path) -> InputError:
    """The error for a path that should be a dataset directory but holds no dataset.json: says
    first whether the path exists at all (a typo), then whether it is a directory."""
    p = Path(root)
    if not p.exists():
        return InputError(p, "does not exist")
    if not p.is_dir():
        return InputError(p, "is a file, not a dataset directory")
    return InputError(p, "no dataset.json here (not a dataset directory)")


def format_validation_error(err: Exception) -> str:
    """Compress a pydantic ValidationError to one line naming each bad key."""
    errors = getattr(err, "errors", None)
    if errors is None:
        return str(err)
    parts = []
    for e in errors():
        loc = ".".join(str(x) for x in e.get("loc", ()))
        if e.get("type") == "extra_forbidden":
            parts.append(f"unknown key '{loc}'")
        else:
            msg = e.get("msg", "invalid")
            parts.append(f"{loc}: {msg}" if loc else msg)
    return "; ".join(parts)
