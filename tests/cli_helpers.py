"""Running `msps` in a subprocess and checking the one-line error contract (shared by workflow tests)."""
from __future__ import annotations

import contextlib
import os
import subprocess
import sys


@contextlib.contextmanager
def llvm_forced():
    """Within: MSPS_VARIANT=llvm (every resolve, in this process and in subprocesses, gives the LLVM
    variant) where llvm_ad_rgb works and MSPS_VARIANT is not already set; yields the variant forced
    (None: nothing changed).  The `force_llvm` fixture of conftest.py."""
    try:
        import mitsuba as mi
    except ImportError:
        mi = None
    from msps_render.render.variant import probe_variant

    if (os.environ.get("MSPS_VARIANT") or mi is None or "llvm_ad_rgb" not in mi.variants()
            or not probe_variant("llvm_ad_rgb")[0]):
        yield None
        return
    old = os.environ.get("MSPS_VARIANT")
    os.environ["MSPS_VARIANT"] = "llvm"
    try:
        yield "llvm_ad_rgb"
    finally:
        if old is None:
            os.environ.pop("MSPS_VARIANT", None)
        else:
            os.environ["MSPS_VARIANT"] = old


def cli(*args, env_extra: dict | None = None, timeout: int = 300) -> subprocess.CompletedProcess:
    env = {**os.environ, "MSPS_THREADS": "1", **(env_extra or {})}
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
