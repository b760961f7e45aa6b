"""Running `msps` in a subprocess and checking the one-line error contract (shared by workflow tests)."""
from __future__ import annotations

import os
import subprocess
import sys


def cli(*args, env_extra: dict | None = None, timeout: int = 300) -> subprocess.CompletedProcess:
    env = dict(os.environ, MSPS_THREADS="1", **(env_extra or {}))
    return subprocess.run([sys.executable, "-m", "msps_render.cli", *map(str, args)], capture_output=True,
                          text=True, env=env, timeout=timeout)


def one_line_error(r: subprocess.CompletedProcess) -> str:
    """The single 'error: ...' line of a run that exited 1 (asserts that shape)."""
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 1, (r.returncode, r.stderr[-2000:])
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr[-2000:]
    return lines[0]
