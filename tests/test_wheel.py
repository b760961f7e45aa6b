"""The wheel: `python -m build`, installed into a fresh venv outside the checkout, runs the
README's commands with the presets, the material catalogue and the checkpoint it ships."""
from __future__ import annotations

import os
import shutil
import site
import subprocess
import sys
from pathlib import Path

import pytest

import msps_render

ROOT = Path(__file__).resolve().parents[1]


def test_packages_list_names_every_subpackage():
    import tomllib

    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "msps_render").rglob("__init__.py")}
    assert found <= listed, f"add to [tool.setuptools] packages: {sorted(found - listed)}"


def _run(cmd, cwd, env, timeout=900):
    r = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, f"{' '.join(map(str, cmd))}\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
    return r.stdout


@pytest.mark.slow
def test_wheel_installs_and_runs_outside_the_checkout(tmp_path):
    pytest.importorskip("build")
    # build from a copy of the source tree, so the checkout gets no build/ or egg-info
    src = tmp_path / "src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(
        ".git", ".venv", "__pycache__", "*.egg-info", "build", "dist", "out", "demo-out", ".pytest_cache",
        "tests", "benchmarks", "docs"))
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "MSPS_"))}
    env["MSPS_CACHE_DIR"] = str(tmp_path / "cache")
    _run([sys.executable, "-m", "build", "--wheel", "--no-isolation", "--outdir", str(tmp_path / "dist"), str(src)],
         tmp_path, env)
    wheel = next((tmp_path / "dist").glob("msps-*.whl"))
    # a fresh venv; the heavy dependencies (torch, mitsuba, ...) come from this interpreter's
    # site-packages through a .pth path entry (no network), msps itself only from the wheel
    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)], tmp_path, env)
    py = venv / "bin" / "python"
    purelib = Path(_run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                        tmp_path, env).strip())
    (purelib / "_msps_test_deps.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    _run([sys.executable, "-m", "pip", "--python", str(py), "install", "-q", "--no-deps", str(wheel)],
         tmp_path, env)
    work = tmp_path / "work"  # outside the checkout: nothing to find by relative paths
    work.mkdir()
    where = _run([str(py), "-c", "import msps_render, msps_render.resources as r; "
                  "print(msps_render.__file__); print(r.data_dir('scenes'))"], work, env).split()
    assert where[0].startswith(str(venv)) and where[1].startswith(str(venv)), where
    msps = [str(venv / "bin" / "msps")]
    assert "demo dataset in" in _run(msps + ["demo", "--out", "demo"], work, env)
    assert (work / "demo" / "preview.png").is_file()
    out = _run(msps + ["render", "paper-train", "--out", "train", "--quiet", "--set", "dataset.n_shards=2",
                       "--set", "dataset.frames_per_shard=1"], work, env)
    assert "2 shards" in out and "complete=True" in out
    _run(msps + ["verify", "train"], work, env)
    _run(msps + ["sample-scene", "--out", "scene.json", "--seed", "3"], work, env)
    _run(msps + ["render-scene", "scene.json", "--out", "frame"], work, env)
    out = _run(msps + ["predict", "frame/image.exr", "--out", "pred/normals"], work, env)
    assert (work / "pred" / "normals.npy").is_file() and (work / "pred" / "normals.png").is_file(), out
    assert msps_render.__version__ in _run(msps + ["version"], work, env)
