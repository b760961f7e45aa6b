"""A new output directory written all-or-nothing: validate `--out`, fill a hidden sibling, rename at the end."""
from __future__ import annotations

import contextlib
import os
import shutil
from pathlib import Path

from msps_render.atomic import fsync_dir
from msps_render.errors import InputError, WriteFailed, write_fault


def _missing_parents(out: Path) -> list[Path]:
    """The ancestors of `out` that do not exist yet, deepest first."""
    missing = []
    p = out.absolute().parent
    while not p.exists() and p != p.parent:
        missing.append(p)
        p = p.parent
    return missing


def check_new_out(out: Path) -> None:
    """`out` must not exist or be an empty directory, and the nearest existing ancestor must be a
    writable directory (missing parent folders are created, as `msps render` does)."""
    if out.exists():
        if not out.is_dir():
            raise InputError(out, "--out exists and is not a directory")
        if any(out.iterdir()):
            raise InputError(out, "--out exists and is not empty; choose a new or empty directory")
    missing = _missing_parents(out)
    base = missing[-1].parent if missing else out.absolute().parent
    if not base.is_dir():
        raise InputError(out, f"cannot create --out: {base} is not a directory")
    if not os.access(base, os.W_OK):
        raise InputError(out, f"cannot create --out: {base} is not writable")


@contextlib.contextmanager
def staged_dir(out: Path):
    """Yield a temporary directory beside `out`; on success it becomes `out`, on any error it is removed.
    A write fault (disk full, ...) is one `WriteFailed` naming the file as it would have been under `out`."""
    out = Path(out)
    check_new_out(out)
    created = _missing_parents(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    stage = out.parent / f".{out.name}.tmp-{os.getpid()}"
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir()
    try:
        yield stage
        if out.exists():
            out.rmdir()  # empty (checked above)
        os.replace(stage, out)
        fsync_dir(out.parent)  # the rename lives in the parent: make it durable
    except BaseException as e:
        shutil.rmtree(stage, ignore_errors=True)
        for d in created:  # the parent folders made for `out`, deepest first: nothing left behind
            with contextlib.suppress(OSError):
                d.rmdir()
        code = write_fault(e)
        if code is None:
            raise
        raise WriteFailed(_under(out, stage, getattr(e, "filename", None)), code) from None


def _under(out: Path, stage: Path, name: str | None) -> Path:
    """`name` (a file in `stage`) as it would have been in `out`; `out` itself when unknown or elsewhere."""
    if name and Path(name).absolute().is_relative_to(stage.absolute()):
        return out / Path(name).absolute().relative_to(stage.absolute())
    return out
