"""A new output directory written all-or-nothing: validate `--out`, fill a hidden sibling, rename at the end."""
from __future__ import annotations

import contextlib
import os
import shutil
from pathlib import Path

from msps_render.atomic import fsync_dir
from msps_render.errors import InputError


def check_new_out(out: Path) -> None:
    """`out` must not exist or be an empty directory, and its parent must be writable."""
    if out.exists():
        if not out.is_dir():
            raise InputError(out, "--out exists and is not a directory")
        if any(out.iterdir()):
            raise InputError(out, "--out exists and is not empty; choose a new or empty directory")
    parent = out.parent
    if not parent.is_dir():
        raise InputError(out, f"cannot create --out: parent {parent} does not exist")
    if not os.access(parent, os.W_OK):
        raise InputError(out, f"cannot create --out: {parent} is not writable")


@contextlib.contextmanager
def staged_dir(out: Path):
    """Yield a temporary directory beside `out`; on success it becomes `out`, on any error it is removed."""
    out = Path(out)
    check_new_out(out)
    stage = out.parent / f".{out.name}.tmp-{os.getpid()}"
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir()
    try:
        yield stage
        if out.exists():
            out.rmdir()  # empty (checked above)
        os.replace(stage, out)
        fsync_dir(out.parent)  # the rename lives in the parent: make it durable
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
