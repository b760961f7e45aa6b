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


def render_tiny(config_text: str, tmp, name: str = "ds"):
    """Render a tiny dataset from TOML text into tmp/name in this process (one worker, LLVM);
    skips where only a scalar variant exists (rendering would take minutes)."""
    from pathlib import Path

    import pytest

    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.run import render_dataset
    from msps_render.render.variant import resolve_variant

    v = resolve_variant("rgb")
    if not v.startswith("llvm"):
        pytest.skip("LLVM variant unavailable: rendering would be too slow")
    tmp = Path(tmp)
    cfg = tmp / f"{name}.toml"
    cfg.write_text(config_text)
    render_dataset(load_config(cfg), tmp / name, workers=1, progress=False, variant=v)
    return tmp / name
