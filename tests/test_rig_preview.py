"""`msps preview` of a rig dataset (format-2 shards): each sample shows its first, middle and last shot
(captioned with the light it holds) beside the normal map and the mask, and names the rig."""
from __future__ import annotations

import json

import numpy as np
import pytest

from cli_helpers import cli, render_tiny
from msps_render.pipeline.preview import LABEL_LINES, LINE, PAD, PLOTS_H, layout, pick, preview_dataset, rig_views

PIL = pytest.importorskip("PIL")
from PIL import Image  # noqa: E402

pytestmark = pytest.mark.usefixtures("force_llvm")  # LLVM even where CUDA is preferred (conftest.py)

RIG = """
[dataset]
name = "rig-preview"
seed = 3
n_shards = 1
frames_per_shard = 2
[dataset.patches]
size = 16
stride = 16
[dataset.storage]
store_frames = {frames}
[scene.materials]
families = ["grey"]
[scene.rig]
layout = "hemisphere"
n_lights = 5
slant_range_deg = [10.0, 50.0]
capture = "sequential"
[scene.camera]
width = 32
height = 32
[scene.integrator]
spp = 2
max_depth = 2
"""


@pytest.fixture(scope="module")
def rig_frames(tmp_path_factory):
    return render_tiny(RIG.format(frames="true"), tmp_path_factory.mktemp("rig-pv"), "frames")


def test_rig_sheet_shows_three_shots_normal_and_mask(rig_frames, tmp_path):
    out = preview_dataset(rig_frames, tmp_path / "sheet.png", n=2, tile=160)
    im = np.asarray(Image.open(out).convert("RGB"))
    L = layout(2, 160, 2, tiles=5, lines=LABEL_LINES + 1)  # shots 0, 2, 4 of 5; normal; mask; + a rig line
    # 2 samples in one row: 5 tiles of 160 px + 4 gaps of 4 px per cell, 8 px padding each side
    assert (L.width, L.height) == (8 + 2 * (5 * 160 + 4 * 4 + 8), 30 + 160 + 5 * LINE + 6 + PAD + PLOTS_H + PAD)
    assert im.shape == (L.height, L.width, 3)
    from msps_render.dataset.reader import iter_rig_frames

    fr = next(iter_rig_frames(rig_frames / "shards" / "shard-00000.h5"))
    want = np.asarray(Image.fromarray(fr.mask.astype(np.uint8) * 255).resize((160, 160), Image.NEAREST))
    x0, y0, x1, y1 = L.tile_box(0, 4)  # the mask tile, below its caption band
    assert np.array_equal(im[y0 + LINE + 2:y1, x0:x1, 0], want[LINE + 2:])
    shots = [im[slice(*L.tile_box(0, j)[1::2]), slice(*L.tile_box(0, j)[0::2])][LINE + 2:].astype(int)
             for j in range(3)]
    assert all(s.max() > 0 for s in shots)  # lit
    assert np.abs(shots[0] - shots[2]).mean() > 1  # shot 0 and shot 4: two different lights


def test_rig_patch_samples_and_cli(tmp_path):
    root = render_tiny(RIG.format(frames="false"), tmp_path, "patches")
    n = min(3, json.loads((root / "dataset.json").read_text())["n_patches"])  # one patch sample each
    assert n >= 1
    r = cli("preview", root, "--out", tmp_path / "p.png", "--n", "3")
    assert r.returncode == 0, r.stderr[-2000:]
    L = layout(n, 160, 2, tiles=5, lines=LABEL_LINES + 1)
    assert Image.open(tmp_path / "p.png").size == (L.width, L.height)


def test_views_of_one_multiplexed_shot_are_its_channels():
    from msps_render.rig import Rig

    assert pick(8) == [0, 4, 7] and pick(2) == [0, 1] and pick(1) == [0]
    shots = np.zeros((1, 4, 4, 6), np.float32)
    shots[0, ..., 3] = 1.0
    rig = Rig(np.tile([[0.0, 0.0, 1.0]], (6, 1)), np.eye(6), shots=(tuple(range(6)),))
    names = [f"{c}nm" for c in (440, 490, 540, 590, 640, 690)]
    views = rig_views(shots, rig, np.full((6, 3), 1 / 3), names)
    assert [c for c, _ in views] == ["channel 440nm", "channel 590nm", "channel 690nm"]
    assert views[1][1].min() == 1.0 and views[0][1].max() == 0.0
    rgb = Rig(np.eye(3), np.eye(3), shots=((0,), (1,), (2,)))
    views = rig_views(np.ones((3, 2, 2, 3), np.float32), rgb, np.eye(3), ["R", "G", "B"])
    assert [c for c, _ in views] == ["shot 0: light 0", "shot 1: light 1", "shot 2: light 2"]
    assert json.dumps([v.shape for _, v in views]) == json.dumps([[2, 2, 3]] * 3)
