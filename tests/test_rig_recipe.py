"""docs/rigs.md "Recipe: my lab's rig from `light_directions.txt`", executed block by block in one folder.

The `python` block writes the light files, the `toml` block is written under the name its first line
gives (`# my-rig.toml: ...`), `bash` blocks run with `msps` meaning this interpreter's CLI and
`msps render` made small (48 px, 4 spp, 16 px patches).  Then the test checks what the page promises.
"""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.usefixtures("force_llvm")  # LLVM even where CUDA is preferred (conftest.py)

DOC = Path(__file__).resolve().parents[1] / "docs" / "rigs.md"
SMALL = ("--set scene.camera.width=48 --set scene.camera.height=48 --set scene.integrator.spp=4 "
         "--set dataset.patches.size=16 --set dataset.patches.stride=8 --quiet")


def recipe_blocks() -> list[tuple[str, str]]:
    section = re.search(r"^## Recipe: my lab's rig.*?(?=^## )", DOC.read_text(), flags=re.S | re.M)
    assert section, "docs/rigs.md has no 'Recipe: my lab's rig' section"
    return re.findall(r"```(\w+)\n(.*?)```", section.group(0), flags=re.S)


@pytest.fixture(scope="module")
def recipe(tmp_path_factory):
    from msps_render.render.variant import resolve_variant

    if not resolve_variant("rgb").startswith("llvm"):
        pytest.skip("LLVM variant unavailable: rendering the recipe would be too slow")
    cwd = tmp_path_factory.mktemp("rig-recipe")
    env = dict(os.environ, MSPS_THREADS="1")
    runs = []
    for lang, code in recipe_blocks():
        if lang == "toml":
            name = re.match(r"# (\S+\.toml):", code)
            assert name, f"toml block without '# NAME.toml:' first line: {code.splitlines()[0]}"
            (cwd / name.group(1)).write_text(code)
            continue
        if lang == "python":
            cmd = [sys.executable, "-c", code]
        elif lang == "bash":
            code = re.sub(r"^(msps render \S+ --out \S+)(.*)$", rf"\1 {SMALL}\2", code, flags=re.M)
            cmd = ["bash", "-c", f'set -euo pipefail\nmsps() {{ "{sys.executable}" -m msps_render.cli "$@"; }}\n{code}']
        else:
            continue
        r = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env=env, timeout=900)
        assert r.returncode == 0, f"recipe block ({lang}) failed:\n{code}\n--- stderr:\n{r.stderr[-3000:]}"
        runs.append(r)
    return cwd, runs


def test_the_recipe_renders_the_labs_rig_and_config_show_says_so(recipe):
    from msps_render.data import iter_frames

    cwd, runs = recipe
    assert "# rig file: 12 directional lights x 3 channel(s), sequential" in runs[1].stdout  # config show
    d = np.loadtxt(cwd / "light_directions.txt")
    frames = list(iter_frames(cwd / "my-rig"))
    assert len(frames) == 4  # 2 shards of 2 frames
    for f in frames:  # every frame lit by the file's 12 lights, as written (float32 storage)
        np.testing.assert_allclose(f.light_dirs, d, atol=1e-6)
    assert (cwd / "my-rig-sheet.png").stat().st_size > 0


def test_the_export_and_bench_real_agree_with_eval_on_the_shards(recipe):
    """The page: `msps bench-real` on the DiLiGenT-layout export gives the numbers `msps eval` gives on the
    shards, up to the 16-bit PNG quantisation."""
    cwd, _ = recipe
    folders = sorted((cwd / "my-rig-diligent").glob("*PNG"))
    assert len(folders) == 4
    for f in folders:
        assert len(sorted(f.glob("[0-9][0-9][0-9].png"))) == 12
        np.testing.assert_allclose(np.loadtxt(f / "light_directions.txt"), np.loadtxt(cwd / "light_directions.txt"),
                                   atol=1e-5)
    ev = json.loads((cwd / "my-rig-eval" / "metrics.json").read_text())["per_frame"]
    bench = json.loads((cwd / "my-rig-bench" / "results.json").read_text())["objects"]
    assert len(ev) == len(bench) == 4
    # frame by frame, in the export's order (NNNN-object): the same pixels, the same least squares; apart
    # only by the 16-bit PNG quantisation (measured: <= 0.0002 deg)
    for row, (name, obj) in zip(ev, sorted(bench.items())):
        assert name.endswith(row["object"]) and obj["pixels"] == row["pixels"], (name, row)
        assert 0 < row["lambertian"] < 60 and abs(obj["lambertian"] - row["lambertian"]) < 0.01, (name, obj, row)
