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
    """The start of a run (opening and verifying the corpus, what it holds, the device) has lines of its own
    when it lasts (here: always, MSPS_PROGRESS_EVERY=0), before the first step's."""
    data, _ = tiny
    r = cli("train", "cpu", "--data", data, "--val", data, "--out", tmp_path / "run", "--set", "train.max_steps=3",
            "--set", "train.val_max_patches=16", "--set", "train.batch_size=4", "--set", "train.cache=true",
            env_extra=ENV)
    assert r.returncode == 0, r.stderr[-2000:]
    lines = [l for l in r.stderr.splitlines() if l.startswith("train: ")]
    assert lines[0] == "train: opening the corpus (verifying every shard, decoding it into memory)", lines
    assert re.fullmatch(r"train: [\d,]+ training patches in 3 shards \(in memory\), [\d,]+ validation patches; "
                        r"cpu on cpu \(CPU\), float32 \([\d.]+ s\)", lines[1]), lines
    assert progress_lines("\n".join(lines[2:]), "train")[:1] == [(1, 3)], lines


class _Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def _ticker(clock, out):
    from msps_render.progress import LineTicker

    t = LineTicker("train", 10, unit="step", every_s=15.0, stream=out, first_line=True)
    t._time, t.t0, t._last = clock, 0.0, 0.0
    return t


def test_a_slow_first_step_is_a_line_at_once_and_a_quick_one_is_not(monkeypatch):
    """In a real log (15 s between lines) a first step longer than STARTUP_NOTICE_S (a device warming up)
    is a line as soon as it ends; a quick one waits for the usual cadence, like every later step."""
    import io

    monkeypatch.delenv("MSPS_PROGRESS_EVERY", raising=False)
    clock = _Clock()
    slow, quick = io.StringIO(), io.StringIO()
    a, b = _ticker(clock, slow), _ticker(clock, quick)
    clock.t = 6.0  # > STARTUP_NOTICE_S (5 s)
    a.update(1)
    clock.t = 7.0
    a.update(2)  # not the first, and 15 s have not passed
    clock.t = 4.0
    b.update(1)
    assert progress_lines(slow.getvalue(), "train") == [(1, 10)]
    assert quick.getvalue() == ""


def test_a_startup_stage_speaks_only_when_it_lasts(monkeypatch):
    """`StartupStage`: a stage longer than the notice is announced while it runs and says how it ended; a
    short one prints nothing; one that fails after its notice leaves no 'done' line (its error is last)."""
    import io
    import time

    import msps_render.progress as P

    monkeypatch.delenv("MSPS_PROGRESS_EVERY", raising=False)
    monkeypatch.setattr(P, "STARTUP_NOTICE_S", 0.05)
    out = io.StringIO()
    with P.StartupStage("train", "opening the corpus", stream=out) as st:
        time.sleep(0.3)
        assert out.getvalue() == "train: opening the corpus\n"  # said while the stage still runs
        st.done = "12 patches"
    assert re.fullmatch(r"train: opening the corpus\ntrain: 12 patches \(0\.\d s\)\n", out.getvalue())
    quick = io.StringIO()
    with P.StartupStage("train", "opening the corpus", stream=quick):
        pass
    assert quick.getvalue() == ""
    failed = io.StringIO()
    with pytest.raises(RuntimeError):
        with P.StartupStage("train", "opening the corpus", stream=failed):
            time.sleep(0.3)
            raise RuntimeError("bad shard")
    assert failed.getvalue() == "train: opening the corpus\n"


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
