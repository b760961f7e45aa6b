"""`atomic_write`: the one temp-then-rename writer (fsynced), so a reader sees the old file or the new one."""
from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Iterator


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
        yield tmp
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
        fsync_dir(path.parent)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
