"""`msps eval` (issue 13): the plots it promises, the per-object table it prints, numbers that add up."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import render_tiny

pytest.importorskip("torch")

pytestmark = pytest.mark.usefixtures("force_llvm")  # LLVM even where CUDA is preferred (conftest.py)

TINY = """
[dataset]
name = "tiny-eval"
seed = 3
n_shards = 2
frames_per_shard = 2
[dataset.patches]
size = 16
stride = 8
[dataset.storage]
store_frames = true
[scene.shape]
source = "primitive"
primitives = ["torus", "capsule"]
[scene.camera]
width = 32
height = 32
[scene.integrator]
spp = 4
max_depth = 3
"""


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return render_tiny(TINY, tmp_path_factory.mktemp("eval"))


def test_eval_writes_its_plots_and_the_per_object_numbers_add_up(dataset, tmp_path):
    from PIL import Image

    from msps_render.data import iter_frames
    from msps_render.models.baseline import lambertian_ps
    from msps_render.models.metrics import angular_error_deg

    env = dict(os.environ, MSPS_THREADS="1")
    r = subprocess.run([sys.executable, "-m", "msps_render.cli", "eval", "--data", str(dataset), "--out",
                        str(tmp_path / "rep"), "--method", "lambertian"], capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stderr
    rep = json.loads((tmp_path / "rep" / "metrics.json").read_text())
    for name in ("error_hist.png", "per_object.png", "per_object.csv"):
        assert (tmp_path / "rep" / name).is_file() and name in r.stdout
    for name in ("error_hist.png", "per_object.png"):
        im = np.asarray(Image.open(tmp_path / "rep" / name).convert("L"))
        assert im.shape[0] > 200 and im.std() > 10  # a drawn figure, not a blank canvas
    cond = rep["conditions"][""]
    assert sum(cond["patches"]["hist_deg"]) == cond["patches"]["n_pixels"]
    # per-object: recomputed independently, mean of per-frame MAEs; also printed as a table
    frame_mae = defaultdict(list)
    for fr in iter_frames(dataset):
        n = lambertian_ps(fr.image, fr.light_dirs, fr.crosstalk, fr.mask)
        frame_mae[fr.object].append(float(angular_error_deg(n[fr.mask], fr.normal[fr.mask]).mean()))
    det = cond["per_object_detail"]
    assert set(det) == set(frame_mae)
    for obj, maes in frame_mae.items():
        assert det[obj]["n_frames"] == len(maes)
        assert det[obj]["mae_deg"] == pytest.approx(np.mean(maes), rel=1e-6)
        assert cond["per_object"][obj] == pytest.approx(np.mean(maes), rel=1e-6)
        row = next(ln for ln in r.stdout.splitlines() if ln.strip().startswith(obj + " "))
        assert f"{np.mean(maes):.2f}" in row and row.split()[-1] == str(len(maes))
    assert "mean of the object's per-frame MAEs" in r.stdout and "per_object_note" in rep
    # format 2 beside the format-1 keys: the one-column table holds the same per-object numbers
    assert rep["format"] == 2 and rep["table"]["methods"] == ["lambertian"] and "table.md" in r.stdout
    rows = {r_["object"]: r_ for r_ in rep["table"]["rows"] if r_["what"] == "object"}
    assert {o: rows[o]["mae_deg"]["lambertian"] for o in rows} == pytest.approx(cond["per_object"], abs=1e-9)
    assert all(rows[o]["ci95_deg"]["lambertian"][0] <= cond["per_object"][o] + 1e-9 for o in rows)
