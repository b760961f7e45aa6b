"""Long commands write plain progress lines when their output is a file (issue 44): a run under nohup,
Slurm or CI shows it moving, not only its end.  MSPS_PROGRESS_EVERY=0 makes every update a line, so
the tests see lines for runs of seconds; a real log gets one every 15 s (`progress.LINE_EVERY_S`)."""
from __future__ import annotations

import re

import numpy as np
import pytest

from cli_helpers import cli, llvm_forced

ENV = {"MSPS_PROGRESS_EVERY": "0"}


def progress_lines(stderr: str, name: str) -> list[tuple[int, int]]:
    """(done, total) of every plain progress line of `name` ('render', 'train', or a stage's name)."""
    return [(int(a), int(b)) for a, b in re.findall(rf"^{re.escape(name)}: (\d+)/(\d+) ", stderr, re.M)]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    with llvm_forced() as v:
        if v is None:
            pytest.skip("LLVM variant unavailable: rendering would be too slow")
        out = tmp_path_factory.mktemp("progress") / "demo"
        r = cli("render", "demo", "--out", out, "--set", "dataset.n_shards=3", "--set", "dataset.frames_per_shard=1",
                "--workers", "1", env_extra=ENV)
        assert r.returncode == 0, r.stderr[-2000:]
        return out, r


def test_render_writes_lines_before_the_end(tiny):
    _, r = tiny
    lines = progress_lines(r.stderr, "render")
    assert (1, 3) in lines and (3, 3) in lines, r.stderr[-1500:]
    assert "patches/s" in r.stderr


def test_eval_writes_lines_before_the_end(tiny, tmp_path):
    data, _ = tiny
    r = cli("eval", "--data", data, "--out", tmp_path / "ev", "--method", "lambertian", "--steps", "none",
            env_extra=ENV)
    assert r.returncode == 0, r.stderr[-2000:]
    lines = progress_lines(r.stderr, f"{data.name}: frames") + progress_lines(r.stderr, f"{data.name}: patches")
    assert any(d < t for d, t in lines) and any(d == t for d, t in lines), r.stderr[-1500:]


def test_train_writes_lines_before_the_end(tiny, tmp_path):
    data, _ = tiny
    r = cli("train", "cpu", "--data", data, "--val", data, "--out", tmp_path / "run", "--set", "train.max_steps=3",
            "--set", "train.val_max_patches=16", "--set", "train.batch_size=4", env_extra=ENV)
    assert r.returncode == 0, r.stderr[-2000:]
    lines = progress_lines(r.stderr, "train")
    assert (1, 3) in lines and (3, 3) in lines, r.stderr[-1500:]


def test_train_says_what_it_does_before_its_first_step(tiny, tmp_path):
    """With a real log's 15 s between lines, a short run still shows its start: opening (and verifying) the
    corpus, what it holds and on which device, and the first step as soon as it is done -- the start of a
    run on a GPU node (corpus check, device warm-up) once left a log empty for 35 s."""
    data, _ = tiny
    r = cli("train", "cpu", "--data", data, "--val", data, "--out", tmp_path / "run", "--set", "train.max_steps=3",
            "--set", "train.val_max_patches=16", "--set", "train.batch_size=4", "--set", "train.cache=true")
    assert r.returncode == 0, r.stderr[-2000:]
    lines = [l for l in r.stderr.splitlines() if l.startswith("train: ")]
    assert lines[0] == "train: opening the corpus (verifying every shard, decoding it into memory)", lines
    assert re.fullmatch(r"train: [\d,]+ training patches in 3 shards \(in memory\), [\d,]+ validation patches: "
                        r"[\d.]+ s; cpu on cpu \(CPU\), float32", lines[1]), lines
    assert progress_lines("\n".join(lines[2:]), "train")[:1] == [(1, 3)], lines  # the first step, at once


@pytest.mark.parametrize("lights", [None, "all"])
def test_bench_real_writes_lines_before_the_end(tmp_path, lights):
    from msps_render.testing import write_sphere_capture

    rng = np.random.default_rng(0)
    from scipy.io import savemat

    for name in ("ballPNG", "catPNG"):
        cap = write_sphere_capture(tmp_path / name, [(30, t) for t in (0, 60, 120, 180, 240, 300)], 48, rng)
        savemat(tmp_path / name / "Normal_gt.mat", {"Normal_gt": cap["normal"]})
    args = ["bench-real", tmp_path / "ballPNG", tmp_path / "catPNG", "--out", tmp_path / "out"]
    if lights:
        args += ["--lights", lights]
    r = cli(*args, env_extra=ENV)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (1, 2) in progress_lines(r.stderr, "objects"), r.stderr[-1500:]


def test_predict_on_a_large_image_writes_lines_before_the_end(tmp_path):
    """From 512 x 512 px on, `msps predict` reports its network passes tile by tile."""
    img = tmp_path / "big.npy"
    np.save(img, np.random.default_rng(0).uniform(0.1, 1.0, (512, 512, 3)).astype(np.float32))
    r = cli("predict", img, "--out", tmp_path / "out", "--steps", "none", env_extra=ENV)
    assert r.returncode == 0, r.stderr[-2000:]
    lines = progress_lines(r.stderr, "big.npy: net")
    assert any(0 < d < t for d, t in lines) and any(d == t for d, t in lines), r.stderr[-1500:]
