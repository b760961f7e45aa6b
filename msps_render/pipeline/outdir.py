"""The `--out` directory of `msps render`: what is ours, is it usable, and one writer at a time.

A dataset directory holds only `dataset.json` (+ its `.dataset.json.tmp`
while being replaced), the dataset card (`card.png`, `card.json`) and `shards/`
with `shard-NNNNN.h5` files (+ `.shard-NNNNN.h5.tmp` while one is written).  Those are the only files the
toolkit ever deletes (`--force`, stale temporaries); anything else is the
user's and is left alone.  A directory holding other files and no
`dataset.json` is refused: rendering into it would mix our files with theirs.
"""
from __future__ import annotations

import errno
import os
import re
from pathlib import Path

from msps_render.dataset.card import CARD_JSON, CARD_PNG
from msps_render.dataset.manifest import MANIFEST, SHARD_DIR
from msps_render.errors import InputError

_TOP = {MANIFEST, f".{MANIFEST}.tmp", CARD_PNG, CARD_JSON}
_SHARD = re.compile(r"shard-\d{5,}\.h5")
_SHARD_TMP = re.compile(r"\.shard-\d{5,}\.h5\.tmp")


def is_ours(rel: Path) -> bool:
    """True for a path (relative to the dataset root) the toolkit writes."""
    parts = rel.parts
    if len(parts) == 1:
        return parts[0] in _TOP or parts[0] == SHARD_DIR
    if len(parts) == 2 and parts[0] == SHARD_DIR:
        return bool(_SHARD.fullmatch(parts[1]) or _SHARD_TMP.fullmatch(parts[1]))
    return False


def foreign_entries(out: Path) -> list[str]:
    """Entries under `out` the toolkit did not write (first level and inside shards/)."""
    found = []
    for p in sorted(out.iterdir()):
        rel = p.relative_to(out)
        if not is_ours(rel) or (p.name == SHARD_DIR and not p.is_dir()):
            found.append(str(rel))
        elif p.name == SHARD_DIR:
            found += [str(q.relative_to(out)) for q in sorted(p.iterdir()) if not is_ours(q.relative_to(out))
                      or not q.is_file()]
    return found


def _probe_writable(d: Path) -> str | None:
    """None if a file can be created in `d` (tried for real: permissions, read-only mounts, quotas)."""
    probe = d / f".msps-write-probe-{os.getpid()}"
    try:
        fd = os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
    except OSError as e:
        return e.strerror or str(e)
    os.close(fd)
    probe.unlink(missing_ok=True)
    return None


def check_out_dir(out: Path, has_manifest: bool) -> None:
    """Refuse an unusable `--out` with one line; writes nothing (a probe file at most, removed)."""
    if out.exists() and not out.is_dir():
        raise InputError(out, "--out exists and is not a directory")
    if out.is_dir():
        why = _probe_writable(out)
        if why:
            raise InputError(out, f"--out is not writable ({why})")
        if not has_manifest:
            foreign = foreign_entries(out)
            if foreign:
                shown = ", ".join(foreign[:4]) + (f" and {len(foreign) - 4} more" if len(foreign) > 4 else "")
                raise InputError(out, f"--out is not empty and holds no msps dataset ({shown}); "
                                      "choose a new or empty directory")
        return
    parent = out.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise InputError(out, f"cannot create --out: {parent} is not a directory")
    why = _probe_writable(parent)
    if why:
        raise InputError(out, f"cannot create --out ({parent}: {why})")


def check_writable(path: Path, what: str = "output") -> None:
    """Before any work: `path` (a directory to write into) is, or can be created as, a writable directory."""
    path = Path(path)
    if path.exists():
        if not path.is_dir():
            raise InputError(path, f"{what} directory exists and is not a directory")
        why = _probe_writable(path)
        if why:
            raise InputError(path, f"{what} directory is not writable ({why})")
        return
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise InputError(path, f"cannot create the {what} directory: {parent} is not a directory")
    why = _probe_writable(parent)
    if why:
        raise InputError(path, f"cannot create the {what} directory ({parent}: {why})")


class OutLock:
    """An exclusive `flock` on the dataset directory itself, held for the whole render.

    Two renders into one directory: the second fails at once with a clear line
    instead of both writing.  The kernel drops the lock when the holder dies
    (even by SIGKILL), so a crash never leaves a stale lock behind.
    """

    def __init__(self, out: Path):
        self.out = out
        self.fd: int | None = None

    def __enter__(self) -> "OutLock":
        import fcntl

        self.fd = os.open(self.out, os.O_RDONLY)
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            os.close(self.fd)
            self.fd = None
            if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise InputError(self.out, "another msps render is writing to this directory "
                                           "(locked); wait for it or choose another --out") from None
            raise
        return self

    def __exit__(self, *exc) -> None:
        if self.fd is not None:
            os.close(self.fd)  # closing releases the flock
            self.fd = None


def remove_temporaries(out: Path) -> None:
    """Partial shards and a half-written manifest left by a crash or an interrupt."""
    for stale in list((out / SHARD_DIR).glob(".shard-*.h5.tmp")) + [out / f".{MANIFEST}.tmp"]:
        stale.unlink(missing_ok=True)


def remove_unrecorded(out: Path, manifest: dict) -> None:
    """Complete shard files the manifest does not record (a worker killed between its atomic rename
    and its report): deterministic, re-rendered by --resume, so removed to keep disk == manifest.
    Call only once every local worker is dead."""
    shards = out / SHARD_DIR
    if not shards.is_dir():
        return
    for p in shards.glob("shard-*.h5"):
        if p.name not in manifest.get("shards", {}):
            p.unlink(missing_ok=True)


def remove_dataset(out: Path) -> None:
    """`--force`: delete the toolkit's files only (shards, manifest, temporaries), nothing else."""
    shards = out / SHARD_DIR
    if shards.is_dir():
        for p in shards.iterdir():
            if p.is_file() and is_ours(p.relative_to(out)):
                p.unlink()
    for name in (MANIFEST, CARD_PNG, CARD_JSON):  # the card describes the dataset being replaced
        (out / name).unlink(missing_ok=True)
    remove_temporaries(out)


def remove_if_empty(d: Path) -> None:
    try:
        d.rmdir()
    except OSError:
        pass


__all__ = ["OutLock", "check_out_dir", "check_writable", "foreign_entries", "is_ours", "remove_dataset",
           "remove_temporaries", "remove_if_empty"]
