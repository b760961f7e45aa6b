"""Issue 22: resume from the stored config, one renderer and one material pool per dataset, 0-patch
renders, status commands that agree on "complete" and "damaged", and durable writes.

Renders are tiny (24x24 frames, one frame per shard, 2 spp): the whole file runs in well under a minute.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import stat
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import one_line_error
from msps_render.dataset.manifest import read_manifest, write_manifest
from msps_render.errors import InputError

TINY = """
[dataset]
name = "resume"
seed = 5
n_shards = {n_shards}
frames_per_shard = 1
[dataset.patches]
size = 16
stride = 8
min_coverage = 0.5
[scene.camera]
width = 24
height = 24
[scene.integrator]
spp = 2
max_depth = 2
{extra}
"""


def cli(*args, env_extra: dict | None = None):
    """`msps ARGS` in this process (the renders reuse this process's compiled kernels: a subprocess
    per call would recompile them, ~1 min each on a loaded machine); .returncode/.stdout/.stderr."""
    from types import SimpleNamespace

    from typer.testing import CliRunner

    from msps_render.cli import app

    r = CliRunner().invoke(app, [str(a) for a in args], env=env_extra, catch_exceptions=False)
    return SimpleNamespace(returncode=r.exit_code, stdout=r.stdout, stderr=r.stderr)


def _llvm() -> str:
    from msps_render.render.variant import resolve_variant

    v = resolve_variant("rgb")
    if not v.startswith("llvm"):
        pytest.skip("LLVM variant unavailable: rendering would be too slow")
    return v


def _toml(tmp: Path, n_shards: int = 2, extra: str = "", name: str = "tiny.toml") -> Path:
    p = tmp / name
    p.write_text(TINY.format(n_shards=n_shards, extra=extra))
    return p


def _render(cfg_path: Path, out: Path, overrides=(), **kw) -> dict:
    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.run import render_dataset

    return render_dataset(load_config(cfg_path, list(overrides)), out, workers=1, progress=False,
                          variant=_llvm(), **kw)


def _stop_after_first(out: Path) -> None:
    """Make `out` what an interrupted render leaves: shard 0 finished and recorded, the rest not."""
    m = read_manifest(out)
    for name in sorted(m["shards"])[1:]:
        (out / "shards" / name).unlink()
        del m["shards"][name]
    m["complete"] = False
    write_manifest(out, m)
    for p in (out / "card.png", out / "card.json"):
        p.unlink(missing_ok=True)


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def width32(tmp_path_factory):
    """A finished 2-shard dataset rendered with `--set scene.camera.width=32` (the TOML says 24)."""
    tmp = tmp_path_factory.mktemp("w32")
    cfg = _toml(tmp)
    out = tmp / "ref"
    _render(cfg, out, ["scene.camera.width=32"])
    return cfg, out


def _copy(src: Path, tmp: Path, name: str = "ds") -> Path:
    dst = tmp / name
    shutil.copytree(src, dst)
    return dst


# ------------------------------------------------------------------------ 1. resume from the stored config
def test_resume_without_retyped_set_finishes_from_the_stored_config(width32, tmp_path):
    cfg, ref = width32
    out = _copy(ref, tmp_path)
    _stop_after_first(out)
    r = cli("render", cfg, "--out", out, "--resume", "--quiet")
    assert r.returncode == 0, r.stderr[-2000:]
    m = read_manifest(out)
    assert m["complete"] and sorted(m["shards"]) == ["shard-00000.h5", "shard-00001.h5"]
    assert m["config"]["scene"]["camera"]["width"] == 32  # the stored --set, not the TOML's 24
    assert "resumed with the config stored in dataset.json" in r.stdout, r.stdout
    assert "scene.camera.width: stored 32 vs given 24" in r.stdout
    # the re-rendered shard is the one the uninterrupted run wrote (same config, same seeds)
    assert m["shards"]["shard-00001.h5"]["file_sha256"] == read_manifest(ref)["shards"]["shard-00001.h5"]["file_sha256"]


def test_resume_with_a_differing_set_is_refused_showing_the_difference(width32, tmp_path):
    cfg, ref = width32
    out = _copy(ref, tmp_path)
    _stop_after_first(out)
    before = (out / "dataset.json").read_bytes()
    line = one_line_error(cli("render", cfg, "--out", out, "--resume", "--quiet", "--set",
                              "scene.camera.width=40"))
    assert "scene.camera.width: stored 32 vs given 40" in line, line
    assert f"--force deletes the 1 finished shard in {out}" in line, line
    assert (out / "dataset.json").read_bytes() == before
    assert sorted(p.name for p in (out / "shards").iterdir()) == ["shard-00000.h5"]
    # the same --set as stored is no difference: accepted
    r = cli("render", cfg, "--out", out, "--resume", "--quiet", "--set", "scene.camera.width=32")
    assert r.returncode == 0, r.stderr[-2000:]


def test_no_message_suggests_force_without_saying_what_it_deletes(width32, tmp_path):
    cfg, ref = width32
    out = _copy(ref, tmp_path)
    same = one_line_error(cli("render", cfg, "--out", out, "--quiet", "--set", "scene.camera.width=32"))
    other = one_line_error(cli("render", cfg, "--out", out, "--quiet"))  # the TOML as is: another config
    for line in (same, other):
        assert f"--force deletes the 2 finished shards in {out}" in line, line
    assert "scene.camera.width: stored 32 vs given 24" in other, other
    assert "already holds this dataset (2 of 2 shards finished)" in same, same


# ------------------------------------------------------------------------ 2. one renderer per dataset
@pytest.mark.parametrize("key,stored", [("variant", "scalar_rgb"), ("mitsuba", "0.0.1"), ("drjit", "0.0.2")])
def test_resume_refuses_another_renderer(key, stored, width32, tmp_path):
    from msps_render.pipeline.run import _versions

    cfg, ref = width32
    out = _copy(ref, tmp_path)
    _stop_after_first(out)
    m = read_manifest(out)
    here = _versions(_llvm())[key]
    m["versions"][key] = stored
    write_manifest(out, m)
    line = one_line_error(cli("render", cfg, "--out", out, "--resume", "--quiet"))
    assert f"rendered with {key} {stored}, this run would use {key} {here}" in line, line
    assert "--force deletes the 1 finished shard" in line
    assert sorted(p.name for p in (out / "shards").iterdir()) == ["shard-00000.h5"]


def test_manifest_records_drjit_version(width32):
    from importlib.metadata import version

    assert read_manifest(width32[1])["versions"]["drjit"] == version("drjit")


# ------------------------------------------------------------------------ 3. the measured-material pool
MEASURED = "[scene.materials]\nmerl_fraction = 1.0\nmin_count = 1\nmax_count = 1\n"


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    """A 2-shard dataset drawing only measured materials (the built-in Neural-BRDF fits here)."""
    tmp = tmp_path_factory.mktemp("measured")
    cfg = _toml(tmp, 2, MEASURED, "measured.toml")
    out = tmp / "ref"
    with pytest.MonkeyPatch.context() as mp:
        mp.delenv("MSPS_MERL_DIR", raising=False)  # the built-in fits, whatever this host has
        _render(cfg, out)
    return cfg, out


def test_manifest_records_the_pool_with_content_digests(measured):
    from msps_render.brdf import nbrdf
    from msps_render.brdf.library import held_out

    pool = read_manifest(measured[1])["material_pool"]
    assert list(pool) == [""]
    names = pool[""]
    test = held_out()
    expected = {f"nbrdf:{n}" for n in nbrdf.builtin_names() if n not in test}
    # the catalogue names materials like their files; every training-side built-in fit is in the pool
    assert set(names) <= {f"nbrdf:{n}" for n in nbrdf.builtin_names()} and len(names) >= 0.8 * len(expected)
    first = sorted(names)[0]
    assert names[first] == _sha(nbrdf.weights_path(first[len("nbrdf:"):]))


def _fake_merl_dir(tmp: Path, material: str) -> Path:
    """A folder with one MERL-shaped file (valid header and size, zero table) for `material`."""
    from msps_render.brdf import merl

    d = tmp / "merl"
    d.mkdir()
    with open(d / f"{material}.binary", "wb") as f:
        f.write(np.asarray(merl.DIMS, dtype="<i4").tobytes())
        f.truncate(merl.FILE_BYTES)
    return d


def test_resume_with_another_pool_stops_naming_the_materials(measured, tmp_path):
    from msps_render.brdf.library import load_catalogue

    cfg, ref = measured
    out = _copy(ref, tmp_path)
    _stop_after_first(out)
    pool = read_manifest(out)["material_pool"][""]
    entry = next(e for e in load_catalogue().by_source("merl") if f"nbrdf:{e.name}" in pool)
    d = _fake_merl_dir(tmp_path, Path(entry.target).stem)
    line = one_line_error(cli("render", cfg, "--out", out, "--resume", "--quiet",
                              env_extra={"MSPS_MERL_DIR": str(d)}))
    assert f"missing here: nbrdf:{entry.name}" in line and f"only here: merl:{entry.name}" in line, line
    assert sorted(p.name for p in (out / "shards").iterdir()) == ["shard-00000.h5"]


def test_worker_with_another_pool_stops_before_rendering(measured, tmp_path):
    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.execute import WorkerSettings, render_shard
    from msps_render.pipeline.plan import plan

    cfg, ref = measured
    pool = read_manifest(ref)["material_pool"]
    name = sorted(pool[""])[0]
    changed = {"": {**pool[""], name: "0" * 64}}  # the same material, other file content
    (tmp_path / "shards").mkdir()
    task = plan(load_config(cfg))[0]
    with pytest.raises(InputError, match=f"different file content: {name}") as e:
        render_shard(task, WorkerSettings(out_dir=str(tmp_path), variant=_llvm(), material_pool=changed))
    assert "this worker sees other measured materials" in str(e.value)
    assert list((tmp_path / "shards").iterdir()) == []  # stopped before writing anything


# ------------------------------------------------------------------------ 4. renders of 0 patches
# 40x40 patches in 48x48 frames (the case); min_coverage = 1 makes 0 patches certain (no object
# here fills a whole 40x40 window: at 0.5 this scene still keeps 4 windows)
ZERO = TINY.replace("size = 16\nstride = 8\nmin_coverage = 0.5", "size = 40\nstride = 20\nmin_coverage = 1.0").replace(
    "width = 24\nheight = 24", "width = 48\nheight = 48")


def test_zero_patch_render_exits_1_naming_the_cause_and_keeps_nothing(tmp_path):
    _llvm()
    cfg = tmp_path / "zero.toml"
    cfg.write_text(ZERO.format(n_shards=1, extra=""))
    out = tmp_path / "ds"
    line = one_line_error(cli("render", cfg, "--out", out, "--quiet"))
    assert "yielded 0 patches" in line and "no 40x40 window (stride 20) of the 48x48 frames" in line, line
    assert "min_coverage" in line
    assert not out.exists()


def test_config_show_warns_before_rendering(tmp_path):
    cfg = tmp_path / "zero.toml"
    cfg.write_text(ZERO.format(n_shards=1, extra=""))
    r = cli("config", "show", cfg)
    assert r.returncode == 0, r.stderr
    warn = [ln for ln in r.stderr.splitlines() if ln.startswith("warning:")]
    assert len(warn) == 1 and "40x40 patches in 48x48 frames: only 4 windows per frame" in warn[0], r.stderr
    assert "covers 100% of it" in warn[0]
    assert "0 patches" in warn[0]
    ok = cli("config", "show", _toml(tmp_path, 1, "", "fine.toml"), "--set", "scene.camera.width=32",
             "--set", "scene.camera.height=32")
    assert ok.returncode == 0 and "warning:" not in ok.stderr, ok.stderr


def test_verify_does_not_call_an_empty_dataset_ok(tmp_path):
    """What the 0-patch render used to leave: complete=true, no patch at all."""
    write_manifest(tmp_path, {"format_version": 1, "config": {}, "planned_shards": [], "shards": {},
                              "complete": True, "n_patches": 0})
    r = cli("verify", tmp_path)
    assert r.returncode == 1, r.stdout
    assert f"BAD {tmp_path / 'dataset.json'}: holds 0 patches" in r.stderr, r.stderr


# ------------------------------------------------------------------------ 5. status commands agree
def _truncate(p: Path) -> None:
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])


def _states(ref: Path, tmp: Path) -> dict[str, tuple[Path, str | None]]:
    """Datasets in several states: {state: (dir, the file at fault or None)}."""
    good = _copy(ref, tmp, "good")
    trunc = _copy(ref, tmp, "trunc")
    _truncate(trunc / "shards" / "shard-00001.h5")
    stopped = _copy(ref, tmp, "stopped")  # SIGTERM after the last shard: every shard, complete=false
    m = read_manifest(stopped)
    m["complete"] = False
    write_manifest(stopped, m)
    partial = _copy(ref, tmp, "partial")
    _stop_after_first(partial)
    return {"good": (good, None), "trunc": (trunc, "shards/shard-00001.h5"),
            "stopped": (stopped, "dataset.json"), "partial": (partial, "shards/shard-00001.h5")}


def test_inspect_verify_and_training_agree(width32, tmp_path):
    from msps_render.data import PatchDataset
    from msps_render.dataset.manifest import load_manifest

    for state, (d, fault) in _states(width32[1], tmp_path).items():
        ins, ver = cli("inspect", d), cli("verify", d)
        try:
            PatchDataset(d, verify=True)
            load_manifest(d)
            train_err = None
        except InputError as e:
            train_err = str(e)
        if fault is None:
            assert ins.returncode == 0 and ver.returncode == 0 and train_err is None, (state, ins.stderr, ver.stderr)
            assert "complete=True" in ins.stdout
            continue
        assert ins.returncode == 1 and ver.returncode == 1 and train_err, (state, ins.stderr, ver.stderr)
        for text in (ins.stderr, ver.stderr, train_err):
            assert str(d / fault) in text, (state, text)
        assert "complete=True" not in ins.stdout, (state, ins.stdout)
        assert "Traceback" not in ins.stderr + ver.stderr


def test_inspect_of_a_truncated_shard_is_one_line(width32, tmp_path):
    d = _copy(width32[1], tmp_path)
    shard = d / "shards" / "shard-00001.h5"
    _truncate(shard)
    line = one_line_error(cli("inspect", shard))
    assert str(shard) in line and "unreadable shard" in line, line


def test_inspect_names_a_truncated_shard_as_damaged(width32, tmp_path):
    d = _copy(width32[1], tmp_path)
    _truncate(d / "shards" / "shard-00000.h5")
    r = cli("inspect", d)
    assert r.returncode == 1
    assert f"BAD {d / 'shards' / 'shard-00000.h5'}: damaged:" in r.stderr and "truncated" in r.stderr, r.stderr


# ------------------------------------------------------------------------ 6. durability
def test_atomic_write_fsyncs_the_directory(tmp_path, monkeypatch):
    from msps_render import atomic

    synced = []
    real = os.fsync

    def spy(fd):
        synced.append(stat.S_ISDIR(os.fstat(fd).st_mode))
        return real(fd)

    monkeypatch.setattr(atomic.os, "fsync", spy)
    with atomic.atomic_write(tmp_path / "x.json") as tmp:
        tmp.write_text("{}")
    assert synced == [False, True]  # the file, then its directory (after the rename)


def test_eval_metrics_json_is_written_atomically(width32, tmp_path, monkeypatch):
    """A write that dies half-way (disk full) leaves the previous metrics.json whole."""
    from msps_render.models.evaluate import evaluate, resolve_methods

    out = tmp_path / "eval"
    evaluate(width32[1], out, resolve_methods(methods=["lambertian"]))
    before = (out / "metrics.json").read_text()
    real = Path.write_text

    def half_then_enospc(self, text, *a, **kw):
        if self.name.endswith("metrics.json") or self.name.endswith("metrics.json.tmp"):
            real(self, text[: len(text) // 2], *a, **kw)
            raise OSError(28, "No space left on device")
        return real(self, text, *a, **kw)

    monkeypatch.setattr(Path, "write_text", half_then_enospc)
    with pytest.raises(OSError):
        evaluate(width32[1], out, resolve_methods(methods=["lambertian"]))
    monkeypatch.undo()
    assert (out / "metrics.json").read_text() == before
    assert not list(out.glob(".*.tmp"))


def test_drain_surfaces_a_failed_manifest_write():
    import multiprocessing as mp
    from types import SimpleNamespace

    from msps_render.pipeline.execute import WorkerPool

    parent, child = mp.Pipe()
    child.send(("ok", "shard-00000.h5", {"n_patches": 1}))
    pool = WorkerPool.__new__(WorkerPool)
    pool.workers = [SimpleNamespace(task=SimpleNamespace(name="shard-00000.h5"), conn=parent)]

    def on_done(task, info):
        raise OSError(28, "No space left on device", "dataset.json")

    with pytest.raises(OSError, match="No space left"):
        pool.drain(on_done)


def test_dask_error_cancels_outstanding_futures(monkeypatch):
    pytest.importorskip("dask.distributed")
    import dask.distributed as dd

    from msps_render.pipeline.execute import WorkerSettings, run_dask
    from msps_render.pipeline.plan import Task

    class Fut:
        def __init__(self, key, status):
            self.key, self.status = key, status

        def result(self, timeout=None):
            raise RuntimeError("boom")

    class Client:
        def __init__(self, *a, **kw):
            self.cancelled, self.futs = [], []

        def submit(self, fn, t, ws, key, pure):
            f = Fut(key, "error" if not self.futs else "pending")
            self.futs.append(f)
            return f

        def cancel(self, futs):
            self.cancelled += list(futs)

        def close(self):
            pass

    made = []
    monkeypatch.setattr(dd, "Client", lambda *a, **kw: made.append(Client()) or made[-1])
    class AsCompleted:  # the slice of dask's as_completed that execute.collect uses: the first future fails
        def __init__(self, futs):
            self.futs = list(futs[:1])

        def is_empty(self):
            return not self.futs

        def has_ready(self):
            return bool(self.futs)

        def next_batch(self, block=True):
            out, self.futs = self.futs, []
            return out

    monkeypatch.setattr(dd, "as_completed", AsCompleted)
    tasks = [Task(i, f"shard-{i:05d}.h5", "", i, 0, "{}") for i in range(3)]
    with pytest.raises(RuntimeError, match="boom"):
        run_dask(tasks, WorkerSettings("/nonexistent", "llvm_ad_rgb"), "tcp://nowhere:1", 1, lambda t, i: None)
    c = made[0]
    assert {f.key for f in c.cancelled} == {f.key for f in c.futs}  # none was recorded: all cancelled


def test_empty_out_is_removed_while_still_locked(tmp_path, monkeypatch):
    import errno
    import fcntl

    from msps_render.pipeline import run

    out = tmp_path / "new"
    seen = []

    def spy(d):
        fd = os.open(d, os.O_RDONLY)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            seen.append("unlocked")
        except OSError as e:
            seen.append("locked" if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN) else str(e))
        finally:
            os.close(fd)
        os.rmdir(d)

    def fail(*a, **kw):
        raise RuntimeError("render failed")

    monkeypatch.setattr(run, "remove_if_empty", spy)
    monkeypatch.setattr(run, "_render_locked", fail)
    from msps_render.pipeline.config import load_config

    with pytest.raises(RuntimeError):
        run.render_dataset(load_config(_toml(tmp_path, 1)), out, progress=False, variant="llvm_ad_rgb")
    assert seen == ["locked"] and not out.exists()
