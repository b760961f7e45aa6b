"""docs/recipes.md, executed: every recipe's blocks run in order in one working directory.

`toml` blocks starting with `# file: NAME` are written as NAME, `python` blocks
run with this interpreter, `bash` blocks run with `msps` meaning this
interpreter's `-m msps_render.cli`; `msps render` lines get SMALL appended
(48x48 pixels so the network's 40x40 tiles fit, 4 spp, 16-pixel patches).
Then each test checks what its recipe promises.
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

from msps_render.dataset import schema as K  # the shard's HDF5 keys

pytestmark = pytest.mark.usefixtures("force_llvm")  # LLVM even where CUDA is preferred (conftest.py)

DOC = Path(__file__).resolve().parents[1] / "docs" / "recipes.md"
SMALL = ("--set scene.camera.width=48 --set scene.camera.height=48 --set scene.integrator.spp=4 "
         "--set scene.integrator.max_depth=3 --set dataset.patches.size=16 --set dataset.patches.stride=8 --quiet")


def sections() -> dict[str, list[tuple[str, str]]]:
    """{'1': [(lang, code), ...], ...} by the number of each '## N.' heading."""
    out, cur = {}, None
    for part in re.split(r"^(## .*)$", DOC.read_text(), flags=re.M):
        m = re.match(r"## (\d+)\.", part)
        if m:
            cur = m.group(1)
            out[cur] = []
        elif part.startswith("## "):
            cur = None
        elif cur:
            out[cur] += re.findall(r"```(\w+)\n(.*?)```", part, flags=re.S)
    return out


NEEDS = {"3": ["1"], "4": ["1"], "5": ["1"], "6": ["1", "5"], "7": ["1"]}  # recipes that use what others made
_done: dict[tuple[Path, str], list] = {}


def run_recipe(n: str, cwd: Path) -> list[subprocess.CompletedProcess]:
    """Run recipe `n` (after the ones it needs) once per working directory; its processes' results."""
    for m in NEEDS.get(n, []):
        run_recipe(m, cwd)
    if (cwd, n) not in _done:
        _done[(cwd, n)] = _run(n, cwd)
    return _done[(cwd, n)]


def _run(n: str, cwd: Path) -> list[subprocess.CompletedProcess]:
    env = dict(os.environ, MSPS_THREADS="1")
    runs = []
    for lang, code in sections()[n]:
        if lang == "toml":
            first = code.splitlines()[0]
            assert first.startswith("# file: "), f"recipe {n}: toml block without '# file:' line"
            (cwd / first[len("# file: "):].strip()).write_text(code)
            continue
        if lang == "python":
            cmd = [sys.executable, "-c", code]
        elif lang == "bash":
            code = re.sub(r"^(msps render .*)$", rf"\1 {SMALL}", code, flags=re.M)
            script = f'set -euo pipefail\nmsps() {{ "{sys.executable}" -m msps_render.cli "$@"; }}\n{code}'
            cmd = ["bash", "-c", script]
        else:
            continue
        r = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env=env, timeout=900)
        assert r.returncode == 0, f"recipe {n} ({lang}) failed:\n{code}\n--- stderr:\n{r.stderr[-3000:]}"
        runs.append(r)
    return runs


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    from msps_render.render.variant import resolve_variant

    if not resolve_variant("rgb").startswith("llvm"):
        pytest.skip("LLVM variant unavailable: rendering the recipes would be too slow")
    return tmp_path_factory.mktemp("recipes")


def test_every_recipe_has_runnable_blocks():
    s = sections()
    assert set(s) == {"1", "2", "3", "4", "5", "6", "7", "8"}
    for n, blocks in s.items():
        assert any(lang in ("bash", "python") for lang, _ in blocks), f"recipe {n} runs nothing"


def test_recipe_1_own_meshes_fixed_frames_per_mesh(work):
    from collections import Counter

    from msps_render.data import iter_frames

    runs = run_recipe("1", work)
    counts = Counter(f.object for f in iter_frames(work / "my-meshes"))
    assert counts == {"capsule": 2, "torus": 2}
    assert any("Counter({'capsule': 2, 'torus': 2})" in r.stdout for r in runs)


def test_recipe_1_dataset_card(work):
    runs = run_recipe("1", work)
    m = json.loads((work / "my-meshes" / "dataset.json").read_text())
    for png in (work / "my-meshes" / "card.png", work / "my-meshes-card.png"):  # by msps render, by msps card
        assert png.is_file() and png.with_suffix(".json").is_file()
    card = json.loads((work / "my-meshes-card.json").read_text())
    assert card == json.loads((work / "my-meshes" / "card.json").read_text())
    assert (card["counts"]["frames"], card["counts"]["patches"]) == (m["n_frames"], m["n_patches"])
    out = runs[-1].stdout
    assert f"{m['n_frames']} frames, {m['n_patches']} patches, 2 shards" in out
    assert "objects: {'capsule': 2, 'torus': 2}" in out


def test_recipe_2_own_env_map(work):
    import h5py

    run_recipe("2", work)
    for p in sorted((work / "my-env" / "shards").glob("*.h5")):
        with h5py.File(p, "r") as h:
            assert (h[K.FRAME_ENV_RATIO][()] == np.float32(0.2)).all()
            scenes = [json.loads(s) for s in h[K.FRAME_SCENE_JSON].asstr()[()]]
    assert all(s["environment"]["source"].endswith("envmaps/my-sky.exr") for s in scenes)


def test_recipe_3_measured_materials(work):
    from msps_render.data import iter_frames

    run_recipe("3", work)
    built_in = [m for f in iter_frames(work / "my-meshes-measured") for m in f.materials.split(";")]
    assert built_in and all(m.startswith("nbrdf:") for m in built_in), built_in
    # measured materials are drawn without replacement: one file -> once per object, other parts analytic
    own = [f.materials.split(";") for f in iter_frames(work / "my-meshes-merl")]
    assert own and all(ms.count("merl:alum-bronze") == 1 for ms in own), own
    assert not any(m.startswith("nbrdf:") for ms in own for m in ms)


def test_recipe_4_pytorch(work):
    runs = run_recipe("4", work)
    assert "patches" in runs[0].stdout and "'image': (3, 16, 16)" in runs[0].stdout


def test_recipe_5_export_and_read_back(work):
    runs = run_recipe("5", work)
    for d in ("export-png16", "export-exr", "export-dl", "export-psfcn", "export-psfcn-stored",
              "export-png16-stored"):
        idx = json.loads((work / d / "export.json").read_text())
        assert idx["n_frames"] == 4
    assert len((work / "export-dl" / "objects.txt").read_text().split()) == 4
    assert json.loads((work / "export-psfcn-stored" / "export.json").read_text())["per_light"]["source"].startswith("stored")
    assert json.loads((work / "export-dl" / "export.json").read_text())["per_light"]["source"].startswith("re-rendered")
    out = runs[-1].stdout  # the reading block: pypng, OpenCV (BGR), OpenEXR, as the recipe shows
    png_vs_exr = float(re.search(r"png16 vs exr: (\S+) 16-bit steps", out).group(1))
    assert png_vs_exr <= 0.51  # rounding to the nearest 16-bit code
    steps = float(re.search(r"per-light sum vs image: (\S+) steps", out).group(1))
    # three rounded lights vs the rounded image (half a step each) + float16 storage (2^-11 of 65535)
    assert steps <= 4 * 0.51 + 65535 * 2.0 ** -11, steps
    assert re.search(r"psfcn: 3 lights, mask pixels: [1-9]", out)


def test_recipe_6_compose_and_predict(work):
    from msps_render.data import iter_frames
    from msps_render.io.images import read_image

    runs = run_recipe("6", work)
    assert "warning" not in runs[0].stderr  # the exported lights are the trained geometry
    for stem in ("normals", "normals-lambertian"):
        n = np.load(work / "composed" / f"{stem}.npy")
        assert n.shape == (48, 48, 3)
    # the capture was frame 0 exported as DiLiGenT: composing its three lights with the same
    # crosstalk rebuilds the rendered image divided by the lights' irradiance (3.0, the default)
    fr = next(iter(iter_frames(work / "my-meshes")))
    comp = read_image(work / "composed" / "image.exr")
    rel = np.abs(comp * 3.0 - fr.image)[fr.mask].max() / fr.image.max()
    assert rel < 1e-3, rel  # three 16-bit quantisations (<= 1.5/65535 of the max) and text rounding


def test_recipe_7_custom_scene_in_python(work):
    from msps_render.io.images import read_image

    runs = run_recipe("7", work)
    assert "shape: mesh torus" in runs[0].stdout and "material" in runs[0].stdout
    d = work / "my-scene"
    img = read_image(d / "image.exr")
    per = [read_image(d / f"light{k}.exr") for k in range(3)]
    assert img.shape == (128, 128, 3)
    np.testing.assert_allclose(sum(per), img, rtol=1e-5, atol=1e-6)  # image = sum of the per-light images


def test_recipe_8_robustness_sweep(work):
    runs = run_recipe("8", work)
    rep = json.loads((work / "my-sweep-report" / "metrics.json").read_text())
    assert set(rep["conditions"]) == {"slant_deg=20.0", "slant_deg=30.0", "slant_deg=40.0"}
    assert rep["robustness"]["reference"] == "slant_deg=30.0" and rep["robustness"]["alpha"]["slant_deg=30.0"] == 0
    assert (work / "my-sweep-report" / "robustness.png").is_file() and "robustness" in runs[-1].stdout
