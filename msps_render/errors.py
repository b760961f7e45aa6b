"""One error type for bad input, so the CLI can print one clear line and exit 1."""
from __future__ import annotations

import difflib
import errno
import os
import re
from pathlib import Path


class InputError(ValueError):
    """Bad user input: names the offending file (or config key) and what is wrong."""

    def __init__(self, source: str | Path, problem: str):
        self.source = str(source)
        self.problem = problem
        super().__init__(f"{self.source}: {problem}")

    def __reduce__(self):  # crosses process boundaries intact (local pool, Dask)
        return (type(self), (self.source, self.problem))


class WriteFailed(OSError):
    """A file could not be written: the disk is full, a quota or a file-size limit was hit, or the
    place is read-only or forbidden.  Raised by the writers (`atomic.atomic_write`, `atomic.writing`)
    naming the file; printed like an `InputError` ('FILE: cause'), one line, exit 1.  An OSError
    (with the errno) so that callers which handle OS errors keep doing so."""

    def __init__(self, source: str | Path, code: int, problem: str | None = None):
        self.source = str(source)
        self.problem = problem or fault_cause(code)
        super().__init__(code, self.problem, self.source)

    def __str__(self) -> str:
        return f"{self.source}: {self.problem}"

    def __reduce__(self):  # crosses process boundaries intact (local pool, Dask)
        return (type(self), (self.source, self.errno, self.problem))


# Write faults a user can fix (free space, raise a limit, choose another place).
WRITE_FAULTS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG)
# HDF5 (through h5py) wraps the errno in its own message: "..., errno = 28, error message = ...".
_WRAPPED_ERRNO = re.compile(r"errno = (\d+)")
# numpy (`np.save`, `tofile`) reports a short write without the errno: "12288 requested and 992 written"
# (and a full disk as "Not enough free space to write ...": so arrays go through `atomic.save_array`).
_SHORT_WRITE = re.compile(r"^\d+ requested and \d+ written$")
SHORT_WRITE = -1  # the code `write_fault` gives that case (the OS's reason is unknown)


def fault_cause(code: int) -> str:
    """The OS's words for a write fault ('No space left on device'), with the limit to look at for EFBIG."""
    if code == SHORT_WRITE:
        return "the disk took only part of a write (full, or a file-size limit)"
    why = os.strerror(code)
    return why + " (a file-size limit: see `ulimit -f`)" if code == errno.EFBIG else why


def write_fault(exc: BaseException) -> int | None:
    """The errno of a failed write if `exc` is one of `WRITE_FAULTS`, plain (OSError) or wrapped by
    h5py/HDF5 (RuntimeError/OSError whose message names the errno), `SHORT_WRITE` for numpy's short
    write; else None."""
    if isinstance(exc, WriteFailed):
        return exc.errno
    if isinstance(exc, OSError) and exc.errno in WRITE_FAULTS:
        return exc.errno
    if type(exc) is OSError and exc.errno is None and _SHORT_WRITE.match(str(exc)):
        return SHORT_WRITE
    if isinstance(exc, (OSError, RuntimeError)):
        m = _WRAPPED_ERRNO.search(str(exc))
        if m and int(m.group(1)) in WRITE_FAULTS:
            return int(m.group(1))
    return None


def env_count(name: str, what: str) -> int | None:
    """A count from environment variable `name` (a whole number >= 1), None when unset or empty; one
    `InputError` naming the variable otherwise (`what` says what it counts)."""
    v = os.environ.get(name, "").strip()
    if not v:
        return None
    try:
        n = int(v)
    except ValueError:
        n = 0
    if n < 1:
        raise InputError(name, f"must be a whole number >= 1 ({what}), got {v!r}")
    return n


def read_text(path: str | Path, what: str) -> str:
    """A user's text file (UTF-8), or one `InputError` naming it: not found, unreadable, or not text (a binary
    file passed by mistake was a UnicodeDecodeError traceback)."""
    p = Path(path)
    try:
        return p.read_text()
    except FileNotFoundError:
        raise InputError(p, f"{what} not found") from None
    except OSError as e:
        raise InputError(p, f"cannot read {what} ({e.strerror or e})") from None
    except UnicodeDecodeError as e:
        raise InputError(p, f"{what} is not UTF-8 text (byte 0x{e.object[e.start]:02x} at offset {e.start})") from None


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
