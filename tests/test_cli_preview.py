"""`msps preview`: labelled, >= 160 px tiles at the places the layout says, deterministic bytes,
one-line errors.  The datasets are written with `write_shard` from synthetic arrays (no render)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from msps_render.dataset import FrameRecord, Patches, ShardContent, write_shard, write_manifest
from msps_render.pipeline.preview import LABEL_H, PAD, PLOTS_H, label_lines, layout, preview_dataset

PIL = pytest.importorskip("PIL")
from PIL import Image  # noqa: E402

S = 48  # frame side (px)
P = 16  # patch side


def _frame(rng, k):
    yy, xx = np.mgrid[:S, :S]
    r = 10 + 3 * k
    mask = (yy - S / 2) ** 2 + (xx - S / 2 + k) ** 2 < r * r
    normal = np.zeros((S, S, 3), np.float32)
    normal[..., 2] = 1.0
    normal[mask, 0] = 0.3
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    image = (rng.random((S, S, 3)) * mask[..., None]).astype(np.float32)
    return image, normal, mask


def make_dataset(root: Path, store_frames: bool, n_shards: int = 2, frames: int = 3) -> Path:
    rng = np.random.default_rng(1)
    shards = {}
    (root / "shards").mkdir(parents=True)
    for s in range(n_shards):
        recs, pats, fidx = [], [], []
        for j in range(frames):
            image, normal, mask = _frame(rng, j)
            scene = json.dumps({"shape": {"kind": "primitive", "name": "torus"}})
            recs.append(FrameRecord(scene_json=scene, light_dirs=np.eye(3), crosstalk=np.eye(3),
                                    light_rgb=np.eye(3), slant_deg=30.0, env_ratio=0.0, env_rotation_deg=0.0,
                                    spp=4, frame_seed=j, object="torus", materials="diffuse;mat-b",
                                    condition=f"slant_deg={20 + 20 * s}",
                                    image=image if store_frames else None, normal=normal if store_frames else None,
                                    mask=mask if store_frames else None))
            yx = np.array([[16, 16], [8, 16]], np.int32)
            pats.append(Patches(image=np.stack([image[y:y + P, x:x + P] for y, x in yx]),
                                normal=np.stack([normal[y:y + P, x:x + P] for y, x in yx]),
                                mask=np.stack([mask[y:y + P, x:x + P] for y, x in yx]).astype(np.uint8), yx=yx))
            fidx.append(np.full(2, j, np.int32))
        name = f"shard-{s:05d}.h5"
        info = write_shard(root / "shards" / name, ShardContent(Patches.concat(pats, P), np.concatenate(fidx), recs))
        shards[name] = {**info, "condition": f"slant_deg={20 + 20 * s}"}
    write_manifest(root, {"shards": shards, "complete": True})
    return root


def cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "msps_render.cli", *map(str, args)], capture_output=True,
                          text=True, env=dict(os.environ), timeout=300)


def one_line_error(r: subprocess.CompletedProcess) -> str:
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 1, (r.returncode, r.stderr[-2000:])
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr[-2000:]
    return lines[0]


@pytest.fixture(scope="module")
def frames_ds(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("pv") / "frames", store_frames=True)


def test_sheet_size_and_tiles(frames_ds, tmp_path):
    out = preview_dataset(frames_ds, tmp_path / "sheet.png", n=5)
    im = np.asarray(Image.open(out).convert("RGB"))
    L = layout(5, 160, 2)
    # 5 samples, 2 per row, 3 tiles of 160 px + 2 gaps of 4 px per cell, 8 px padding:
    # width 8 + 2 * (488 + 8) = 1000; height 30 header + 3 rows * (160 + 70 label + 8) + 240 plots + 8
    assert (L.width, L.height) == (1000, 30 + 3 * (160 + LABEL_H + PAD) + PLOTS_H + PAD) == (1000, 992)
    assert im.shape == (L.height, L.width, 3)
    # samples spread over both shards (3 + 2); each mask tile is the frame's mask upscaled to
    # 160 px (nearest neighbour) exactly where the layout puts tile 2 of the cell
    for k, frame in enumerate([0, 1, 2, 0, 1]):
        _, _, mask = _frame(np.random.default_rng(0), frame)
        want = np.asarray(Image.fromarray(mask.astype(np.uint8) * 255).resize((160, 160), Image.NEAREST))
        x0, y0, x1, y1 = L.tile_box(k, 2)
        assert np.array_equal(im[y0:y1, x0:x1, 0], want), k
        x0, y0, x1, y1 = L.tile_box(k, 1)  # the normal tile: (n + 1) / 2 colouring, background black
        tile = im[y0:y1, x0:x1]
        assert tile[want == 0].max() == 0 and abs(float(tile[want > 0][:, 2].mean()) - 250) <= 1  # z = 1/sqrt(1.09)


def test_labels_drawn_and_nowhere_else(frames_ds, tmp_path):
    a = np.asarray(Image.open(preview_dataset(frames_ds, tmp_path / "a.png", n=4)).convert("L")).astype(int)
    b = np.asarray(Image.open(preview_dataset(frames_ds, tmp_path / "b.png", n=4, labels=False)).convert("L"))
    assert a.shape == b.shape  # labels take their band either way: same layout
    diff = np.abs(a - b.astype(int)) > 0
    L = layout(4, 160, 2)
    inside = np.zeros_like(diff)
    inside[:30] = True  # the title
    for k in range(4):
        x0, y0, x1, y1 = L.label_box(k)
        band = diff[y0:y1, x0:x1]
        assert band.sum() > 1000, (k, band.sum())  # four lines of text: ~3500 changed pixels measured
        inside[y0:y1, x0:x1] = True
    assert diff[:30].sum() > 1000  # the title line: ~3500 measured
    assert not diff[~inside].any()  # tiles and plots unchanged


def test_label_text_names_shard_frame_shape_materials_condition(tmp_path):
    from msps_render.dataset.samples import shard_samples

    root = make_dataset(tmp_path / "patches", store_frames=False, n_shards=1)
    got, cover = shard_samples(root / "shards" / "shard-00000.h5", 2, np.random.default_rng(0))
    assert len(got) == 2 and len(cover) == 6
    lines = label_lines(got[0])
    assert lines[0].startswith(f"shard-00000.h5 frame {got[0].frame}, patch at y=")
    assert lines[1:] == ["shape: primitive torus", "materials: diffuse, mat-b", "condition: slant_deg=20"]
    frames = make_dataset(tmp_path / "frames", store_frames=True, n_shards=1)
    whole, _ = shard_samples(frames / "shards" / "shard-00000.h5", 1, np.random.default_rng(0))
    assert label_lines(whole[0])[0] == "shard-00000.h5 frame 0 (whole frame)"


def test_deterministic_bytes_and_cli(frames_ds, tmp_path):
    r1 = cli("preview", frames_ds, "--out", tmp_path / "1.png", "--n", "3", "--tile", "200")
    r2 = cli("preview", frames_ds, "--out", tmp_path / "2.png", "--n", "3", "--tile", "200")
    assert r1.returncode == 0 and r2.returncode == 0, r1.stderr + r2.stderr
    assert (tmp_path / "1.png").read_bytes() == (tmp_path / "2.png").read_bytes()
    assert Image.open(tmp_path / "1.png").size == (layout(3, 200, 2).width, layout(3, 200, 2).height)


def test_one_line_errors_write_nothing(frames_ds, tmp_path):
    line = one_line_error(cli("preview", tmp_path / "nowhere", "--out", tmp_path / "x.png"))
    assert "nowhere" in line and "does not exist" in line  # the missing path itself, not "no dataset.json" (issue 22)
    bad = make_dataset(tmp_path / "bad", store_frames=True, n_shards=1)
    (bad / "shards" / "shard-00000.h5").write_bytes(b"not hdf5")
    line = one_line_error(cli("preview", bad, "--out", tmp_path / "x.png"))
    assert "shard-00000.h5" in line
    assert not (tmp_path / "x.png").exists()
    r = cli("preview", frames_ds, "--out", tmp_path / "y.png", "--tile", "64")  # tiles under 160 px refused
    assert r.returncode == 2 and not (tmp_path / "y.png").exists()
