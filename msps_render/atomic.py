"""`atomic_write`: the one temp-then-rename writer (fsynced), so a reader sees the old file or the new one.

Every writer here turns a write fault (disk full, quota, read-only, permission, file-size limit:
`errors.WRITE_FAULTS`) into one `WriteFailed` naming the file, so every command reports it as one
line and the temporary is gone.  Libraries that write files themselves do not always survive a
full disk (HDF5 crashed the process; torch reports 'unexpected pos' without the errno): their
bytes are built in memory and written here (`write_bytes`), where the error is a plain OSError.
"""
from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Iterator

from msps_render.errors import WriteFailed, write_fault


def temp_name(path: str | Path) -> Path:
    """The temporary sibling `atomic_write` writes first: `.NAME.tmp` (hidden, same directory)."""
    p = Path(path)
    return p.with_name(f".{p.name}.tmp")


def fsync_dir(d: str | Path) -> None:
    """fsync a directory so a rename into it survives a power cut (the rename lives in the directory's
    entries, not in the file).  Skipped where directories cannot be opened (Windows)."""
    try:
        fd = os.open(d, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:  # some filesystems (e.g. certain FUSE mounts) refuse fsync on a directory
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_write(path: str | Path, unique: bool = False) -> Iterator[Path]:
    """Yield a temporary path next to `path`; on success fsync it and rename it over `path`.

    On any error (or interrupt) the temporary file is removed and `path` is untouched.
    `unique=True` adds the process id to the temporary name, for files several
    processes may write at once (caches).
    """
    path = Path(path)
    tmp = temp_name(path) if not unique else path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with writing(path):
            yield tmp
            with open(tmp, "rb") as f:
                os.fsync(f.fileno())
            os.replace(tmp, path)
            fsync_dir(path.parent)
    except BaseException:
        discard(tmp)
        raise


def discard(tmp: Path) -> None:
    """Remove a temporary file, emptying it first: a library that failed mid-write may still hold it
    open (HDF5 after a failed close), and an unlinked file that is open keeps its space."""
    try:
        os.truncate(tmp, 0)
    except OSError:
        pass
    tmp.unlink(missing_ok=True)


def write_bytes(path: str | Path, data: bytes | memoryview, unique: bool = False) -> Path:
    """`data` to `path` atomically (`atomic_write`); a write fault is one `WriteFailed` naming `path`."""
    with atomic_write(path, unique) as tmp, open(tmp, "wb") as f:
        f.write(data)
    return Path(path)


def write_text(path: str | Path, text: str) -> Path:
    """`text` (UTF-8) to `path` atomically, like `write_bytes`."""
    return write_bytes(path, text.encode("utf-8"))


@contextlib.contextmanager
def writing(path: str | Path) -> Iterator[None]:
    """Within: a write fault (`errors.write_fault`) becomes `WriteFailed(path, cause)`; for files not
    written through `atomic_write` (a log appended line by line, a directory being filled)."""
    try:
        yield
    except WriteFailed:
        raise
    except (OSError, RuntimeError) as e:
        code = write_fault(e)
        if code is None:
            raise
        raise WriteFailed(path, code) from None


def save_array(path: str | Path, a, unique: bool = False) -> Path:
    """`np.save` to `path` atomically (`atomic_write`, `unique` as there).  Why through memory: numpy
    writing to a file reports a full disk in its own words, without the errno or the file."""
    import io

    import numpy as np

    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return write_bytes(path, buf.getbuffer(), unique)


def save_figure(fig, path: str | Path, **kw) -> Path:
    """`fig.savefig` (matplotlib) to `path` atomically, its format from the suffix."""
    with atomic_write(path) as tmp:
        fig.savefig(tmp, format=Path(path).suffix.lstrip(".") or "png", **kw)
    return Path(path)


class AppendLog:
    """A text file appended a record at a time (a training run's metrics.jsonl): each `write` goes to
    disk at once (no buffer left to fail again at close), and a write fault is one `WriteFailed`
    naming the file.  A fault may leave a torn last line: readers skip it."""

    def __init__(self, path: str | Path):
        self.name = str(path)
        with writing(self.name):
            self._fd = os.open(self.name, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)

    def write(self, text: str) -> None:
        data = memoryview(text.encode("utf-8"))
        with writing(self.name):
            while data:
                data = data[os.write(self._fd, data):]

    def flush(self) -> None:
        """Nothing to do: every `write` is already in the file."""

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> "AppendLog":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
