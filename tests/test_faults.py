"""Fault matrix: every bad input or hostile situation -> exit code, one line naming the
input, nothing partial on disk.  Plus interrupts, orphan workers, worker recycling, locking, errors
crossing process boundaries.  The chaos test (random SIGKILL/SIGINT + --resume) is `slow`.
"""
from __future__ import annotations

import json
import os
import pickle
import random
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from msps_render.dataset import schema as K  # the shard's HDF5 keys
from msps_render.errors import InputError, Interrupted
from msps_render.pipeline.config import load_config
from msps_render.dataset.manifest import read_manifest
from msps_render.pipeline.run import render_dataset
from msps_render.dataset import file_digest, read_digests

pytestmark = pytest.mark.usefixtures("force_llvm")  # LLVM even where CUDA is preferred (conftest.py)

TINY = """
[dataset]
name = "faults"
seed = 11
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
"""


# Shards in the runs the interrupt/kill tests stop midway: the tiny shards render in ~10-20 ms each
# once kernels are reused, so the run must be long enough never to finish before the signal.
LONG_RUN = 3000


def tiny(tmp: Path, n_shards: int = 4, extra: str = "", name: str = "tiny.toml") -> Path:
    p = tmp / name
    p.write_text(TINY.format(n_shards=n_shards) + extra)
    return p


def cli(*args, cwd=None, timeout=300) -> subprocess.CompletedProcess:
    env = dict(os.environ, MSPS_THREADS="1")
    return subprocess.run([sys.executable, "-m", "msps_render.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, timeout=timeout, env=env)


def one_line_error(r: subprocess.CompletedProcess, code: int = 1) -> str:
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == code, (r.returncode, r.stderr[-2000:])
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr[-2000:]
    assert "Traceback" not in r.stderr
    return lines[0]


def listing(d: Path) -> list[str]:
    return sorted(str(p.relative_to(d)) for p in d.rglob("*")) if d.exists() else []


def digests(root: Path) -> dict:
    return {p.name: read_digests(p) for p in sorted((root / "shards").glob("shard-*.h5"))}


def _variant():
    from msps_render.render.variant import resolve_variant

    v = resolve_variant("rgb")
    if not v.startswith("llvm"):
        pytest.skip("LLVM variant unavailable: fault tests would be too slow")
    return v


def readonly_dir(tmp: Path) -> Path:
    """A directory this process cannot write into (chmod 555; as root, where chmod does not bind, /sys/kernel)."""
    d = tmp / "ro"
    d.mkdir(exist_ok=True)
    d.chmod(0o555)
    probe = d / ".probe"
    try:
        probe.touch()
    except OSError:
        return d
    probe.unlink()
    d.chmod(0o755)
    if Path("/sys/kernel").is_dir() and _cannot_write("/sys/kernel"):
        return Path("/sys/kernel")
    pytest.skip("no read-only directory available (root without a read-only /sys)")


def _cannot_write(d: str) -> bool:
    try:
        Path(d, f".msps-probe-{os.getpid()}").touch()
    except OSError:
        return True
    Path(d, f".msps-probe-{os.getpid()}").unlink()
    return False


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted in-process render of the 4-shard tiny config."""
    tmp = tmp_path_factory.mktemp("faults-ref")
    cfg = load_config(tiny(tmp, 4))
    out = tmp / "ref"
    render_dataset(cfg, out, workers=1, progress=False, variant=_variant())
    return cfg, out


# ----------------------------------------------------------------------------- bad inputs
def _write_exr(path: Path, img: np.ndarray) -> None:
    import OpenEXR

    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {"RGB": np.ascontiguousarray(img, dtype=np.float32)}) as f:
        f.write(str(path))


def _case_files(case: str, tmp: Path) -> tuple[str, str, str]:
    """(extra TOML, expected text in the error, the name the line must contain)."""
    if case == "missing mesh":
        return f'[scene.shape]\nsource = "mesh"\nmeshes = ["{tmp}/nope.obj"]\n', "no mesh file", "nope.obj"
    if case == "NaN vertex":
        (tmp / "nan.obj").write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 2 3 4\nf 1 3 4\n")
        return f'[scene.shape]\nsource = "mesh"\nmeshes = ["{tmp}/nan.obj"]\n', "NaN", "nan.obj"
    if case == "empty mesh":
        (tmp / "empty.obj").write_text("# nothing\n")
        return f'[scene.shape]\nsource = "mesh"\nmeshes = ["{tmp}/empty.obj"]\n', "no faces", "empty.obj"
    if case == "garbage env map":
        (tmp / "env.exr").write_bytes(os.urandom(2048))
        return (f'[scene.environment]\nenabled = true\nsource = "{tmp}/env.exr"\nratio = 0.2\n', "cannot read EXR",
                "env.exr")
    if case == "NaN env map":
        img = np.ones((8, 16, 3), np.float32)
        img[2, 3, 1] = np.nan
        _write_exr(tmp / "nanenv.exr", img)
        return (f'[scene.environment]\nenabled = true\nsource = "{tmp}/nanenv.exr"\nratio = 0.2\n', "NaN",
                "nanenv.exr")
    if case == "missing catalogue":
        return (f'[scene.materials]\nmerl_fraction = 0.5\ncatalogue = "{tmp}/nope-catalogue.toml"\n',
                "material catalogue not found", "nope-catalogue.toml")
    if case == "bad MERL table":
        (tmp / "merl").mkdir()
        (tmp / "merl" / "bad.binary").write_bytes(np.array([90, 90, 180], "<i4").tobytes() + b"\0" * 1000)
        (tmp / "cat.toml").write_text('[[material]]\nname = "bad"\nsource = "merl:bad.binary"\n'
                                      '[[material]]\nname = "white"\nsource = "analytic:diffuse"\n')
        return (f'[scene.materials]\nmerl_fraction = 1.0\ncatalogue = "{tmp}/cat.toml"\nmerl_dir = "{tmp}/merl"\n',
                "truncated MERL file", "bad.binary")
    M = {"NaN crosstalk": "[[nan, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]",
         "negative crosstalk": "[[1.0, -0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]",
         "zero crosstalk": "[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]",
         "dead light": "[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]]",
         "singular crosstalk": "[[0.5, 0.5, 0.0], [0.5, 0.5, 0.0], [0.0, 0.0, 1.0]]"}[case]
    want = {"NaN crosstalk": "NaN", "negative crosstalk": "negative", "zero crosstalk": "reaches no camera channel",
            "dead light": "light 2 reaches no camera channel", "singular crosstalk": "singular"}[case]
    return f"[scene.lights]\ncrosstalk = {M}\n", want, "lights.crosstalk"


INPUT_CASES = ["missing mesh", "NaN vertex", "empty mesh", "garbage env map", "NaN env map", "missing catalogue",
               "bad MERL table",
               "NaN crosstalk", "negative crosstalk", "zero crosstalk", "dead light", "singular crosstalk"]


@pytest.mark.parametrize("case", INPUT_CASES)
def test_bad_input_is_one_line_and_writes_nothing(case, tmp_path):
    extra, want, name = _case_files(case, tmp_path)
    cfg = tiny(tmp_path, 2, extra)
    out = tmp_path / "out"
    line = one_line_error(cli("render", cfg, "--out", out, "--workers", "2", "--quiet"))
    assert want in line and name in line, line
    assert not out.exists()  # nothing half-written: no dataset.json, no empty shards/
    if "crosstalk" in case:
        assert str(cfg) in line  # names the config file too


def test_fixed_config_after_a_failed_run_needs_no_force(tmp_path, reference):
    """A run that failed before its first shard leaves nothing that would refuse the fixed config."""
    extra, _, _ = _case_files("missing mesh", tmp_path)
    out = tmp_path / "out"
    assert cli("render", tiny(tmp_path, 4, extra, "bad.toml"), "--out", out, "--quiet").returncode == 1
    r = cli("render", tiny(tmp_path, 4), "--out", out, "--quiet")
    assert r.returncode == 0, r.stderr
    assert digests(out) == digests(reference[1])


@pytest.mark.parametrize("suffix", [".exr", ".hdr"])
def test_environment_map_files_render(suffix, tmp_path):
    """Env-map files (not only the procedural sky) render: in a scene and through the pipeline."""
    import mitsuba as mi

    from msps_render.render import render_frame
    from msps_render.scene.sample import SceneConfig, sample_scene

    img = np.full((16, 32, 3), 0.5, np.float32)
    img[:8] *= 4.0  # brighter sky than ground
    path = tmp_path / f"env{suffix}"
    if suffix == ".exr":
        _write_exr(path, img)
    else:
        mi.Bitmap(img).write(str(path))
    extra = (f'[scene.environment]\nenabled = true\nsource = "{path}"\nratio = 0.5\n'
             "[dataset.storage]\nstore_frames = true\n")
    cfg = load_config(tiny(tmp_path, 1, extra))
    spec = sample_scene(cfg.scene, np.random.default_rng(0))
    frame = render_frame(spec, variant=_variant())
    assert frame.env_image is not None and np.isfinite(frame.env_image).all()
    assert frame.env_image[frame.mask].mean() > 0
    m = render_dataset(cfg, tmp_path / "ds", progress=False, variant=_variant())
    assert m["complete"]
    with h5py.File(tmp_path / "ds" / "shards" / "shard-00000.h5", "r") as h:
        assert h[K.FRAME_ENV_RATIO][0] == pytest.approx(0.5)


# ----------------------------------------------------------------------------- --out
def test_out_is_a_file(tmp_path):
    f = tmp_path / "file"
    f.write_text("mine")
    line = one_line_error(cli("render", tiny(tmp_path), "--out", f, "--quiet"))
    assert str(f) in line and "not a directory" in line and f.read_text() == "mine"


def test_out_read_only(tmp_path):
    ro = readonly_dir(tmp_path)
    before = listing(ro) if ro.is_relative_to(tmp_path) else None
    line = one_line_error(cli("render", tiny(tmp_path), "--out", ro, "--quiet"))
    assert str(ro) in line and ("not writable" in line or "not empty" in line)
    line = one_line_error(cli("render", tiny(tmp_path), "--out", ro / "sub" / "ds", "--quiet"))
    assert "cannot create --out" in line
    if before is not None:
        assert listing(ro) == before


def test_out_foreign_directory_refused_and_untouched(tmp_path):
    out = tmp_path / "photos"
    out.mkdir()
    (out / "holiday.jpg").write_bytes(b"jpeg")
    line = one_line_error(cli("render", tiny(tmp_path), "--out", out, "--quiet"))
    assert "not empty" in line and "holiday.jpg" in line
    assert listing(out) == ["holiday.jpg"]
    line = one_line_error(cli("render", tiny(tmp_path), "--out", out, "--quiet", "--force"))
    assert listing(out) == ["holiday.jpg"]


def test_force_deletes_only_toolkit_files(tmp_path, reference):
    cfg, ref = reference
    out = tmp_path / "ds"
    shutil.copytree(ref, out)
    (out / "shards" / "my-notes.txt").write_text("keep me")
    (out / "README.txt").write_text("keep me too")
    (out / "shards" / "shard-00099.h5").write_bytes(b"stale shard of an older, bigger run")
    r = cli("render", tiny(tmp_path, 2), "--out", out, "--set", "lights.slant_deg=25", "--force", "--quiet")
    assert r.returncode == 0, r.stderr
    assert (out / "shards" / "my-notes.txt").read_text() == "keep me"
    assert (out / "README.txt").read_text() == "keep me too"
    assert not (out / "shards" / "shard-00099.h5").exists()  # ours (toolkit name): replaced dataset
    assert sorted(read_manifest(out)["shards"]) == ["shard-00000.h5", "shard-00001.h5"]


def test_lock_refuses_a_second_render(tmp_path):
    from msps_render.pipeline.outdir import OutLock

    out = tmp_path / "ds"
    out.mkdir()
    with OutLock(out):
        line = one_line_error(cli("render", tiny(tmp_path), "--out", out, "--quiet"))
    assert "another msps render is writing" in line and str(out) in line
    assert listing(out) == []


def test_two_concurrent_renders_one_wins(tmp_path, reference):
    out = tmp_path / "ds"
    cfg = tiny(tmp_path, 12)
    env = dict(os.environ, MSPS_THREADS="1")
    a = subprocess.Popen([sys.executable, "-m", "msps_render.cli", "render", str(cfg), "--out", str(out), "--quiet"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.time() + 120
    while time.time() < deadline and not (out / "dataset.json").is_file():
        time.sleep(0.05)
    b = cli("render", cfg, "--out", out, "--quiet", "--resume")
    line = one_line_error(b)
    assert "another msps render is writing" in line
    assert a.wait(timeout=300) == 0, a.stderr.read()
    m = read_manifest(out)
    assert m["complete"] and len(m["shards"]) == 12
    assert {k: v for k, v in digests(out).items() if k in digests(reference[1])} == digests(reference[1])


# ----------------------------------------------------------------------------- errors across processes
def test_input_error_pickles():
    e = pickle.loads(pickle.dumps(InputError("a/b.obj", "mesh has no faces")))
    assert isinstance(e, InputError) and str(e) == "a/b.obj: mesh has no faces" and e.source == "a/b.obj"
    i = pickle.loads(pickle.dumps(Interrupted(2, 3, 10)))
    assert i.exit_code == 130 and str(i) == "interrupted: 3 of 10 shards done; rerun with --resume"


def _missing_mesh_tasks(tmp_path):
    """Tasks whose worker raises InputError (validation bypassed: the mesh vanished after planning)."""
    from msps_render.pipeline.plan import plan

    cfg = load_config(tiny(tmp_path, 3, f'[scene.shape]\nsource = "mesh"\nmeshes = ["{tmp_path}/gone.obj"]\n'))
    return plan(cfg)


def test_worker_input_error_same_as_in_process(tmp_path):
    from msps_render.pipeline.execute import WorkerSettings, run_local

    tasks = _missing_mesh_tasks(tmp_path)
    (tmp_path / "o" / "shards").mkdir(parents=True)
    ws = WorkerSettings(out_dir=str(tmp_path / "o"), variant=_variant(), threads=1)
    msgs = []
    for workers in (1, 2):
        with pytest.raises(InputError) as ei:
            run_local(tasks, ws, workers, lambda t, i: None)
        msgs.append(str(ei.value))
    assert msgs[0] == msgs[1] and "gone.obj" in msgs[0]


def test_worker_input_error_through_dask(tmp_path):
    pytest.importorskip("dask.distributed")
    from msps_render.pipeline.execute import WorkerSettings, run_dask

    tasks = _missing_mesh_tasks(tmp_path)[:1]
    (tmp_path / "o" / "shards").mkdir(parents=True)
    ws = WorkerSettings(out_dir=str(tmp_path / "o"), variant=_variant(), threads=1)
    with pytest.raises(InputError, match="gone.obj: no mesh file matches"):
        run_dask(tasks, ws, "dask-local", 1, lambda t, i: None)


def test_dask_with_relative_out(tmp_path, reference):
    pytest.importorskip("dask.distributed")
    r = cli("render", tiny(tmp_path, 4), "--out", "rel/ds", "--scheduler", "dask-local", "--workers", "1",
            "--quiet", cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert digests(tmp_path / "rel" / "ds") == digests(reference[1])


def test_dask_scheduler_elsewhere_with_relative_out(tmp_path, reference):
    """A tcp:// cluster whose worker runs in another directory: a relative --out must still mean the driver's."""
    pytest.importorskip("dask.distributed")
    bindir = Path(sys.executable).parent
    if not (bindir / "dask").exists():
        pytest.skip("dask CLI not installed")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    sf = tmp_path / "scheduler.json"
    env = dict(os.environ, MSPS_THREADS="1")
    common = dict(cwd=elsewhere, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    sched = subprocess.Popen([str(bindir / "dask"), "scheduler", "--scheduler-file", str(sf), "--port", "0",
                              "--no-dashboard", "--host", "127.0.0.1"], **common)
    worker = None
    try:
        deadline = time.time() + 60
        while time.time() < deadline and not sf.is_file():
            time.sleep(0.2)
        time.sleep(0.5)
        address = json.loads(sf.read_text())["address"]
        worker = subprocess.Popen([str(bindir / "dask"), "worker", address, "--nworkers", "1", "--nthreads", "1",
                                   "--no-nanny", "--no-dashboard"], **common)
        r = cli("render", tiny(tmp_path, 4), "--out", "rel/ds", "--scheduler", address, "--quiet", cwd=tmp_path)
        assert r.returncode == 0, r.stderr[-2000:]
        assert digests(tmp_path / "rel" / "ds") == digests(reference[1])
        assert not (elsewhere / "rel").exists()
    finally:
        for p in (worker, sched):
            if p is not None:
                p.kill()
                p.wait(10)


# ----------------------------------------------------------------------------- worker pool
def test_pool_recycles_workers_past_the_period(tmp_path):
    """6 shards, 2 workers, a new worker every 2 shards: no gh-115634 deadlock, same arrays."""
    from msps_render.pipeline.execute import WorkerPool, WorkerSettings, render_shard
    from msps_render.pipeline.plan import plan

    cfg = load_config(tiny(tmp_path, 6))
    tasks = plan(cfg)
    v = _variant()
    for d in ("pool", "inproc"):
        (tmp_path / d / "shards").mkdir(parents=True)
    pool = WorkerPool(2, v, 1, recycle_after=2)
    got = {}
    t0 = time.time()
    try:
        pool.run(tasks, WorkerSettings(str(tmp_path / "pool"), v, 1), lambda t, info: got.setdefault(t.name, info))
    finally:
        pool.close()
    assert time.time() - t0 < 240
    assert sorted(got) == [t.name for t in tasks]
    assert pool.spawned == 4  # 2 initial + 2 replacements (the last two retire with nothing left to do)
    for t in tasks:
        info = render_shard(t, WorkerSettings(str(tmp_path / "inproc"), v, 1))
        assert info["arrays"] == got[t.name]["arrays"]


def _children(pid: int) -> list[int]:
    r = subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True)
    return [int(x) for x in r.stdout.split()]


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def _own_group_default_sigint() -> None:
    """In the child before exec: its own process group (so the tests can signal the render and its
    workers together, as a terminal's Ctrl-C does, without hitting pytest), and SIGINT back to its
    default.  A test run started in the background by a non-interactive shell inherits SIGINT
    ignored, and Python then never raises KeyboardInterrupt -- the render would (rightly) ignore
    the Ctrl-C these tests send."""
    os.setpgid(0, 0)
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _signal_group(proc: subprocess.Popen, sig: int) -> None:
    """What Ctrl-C (SIGINT) or a job scheduler's kill (SIGTERM) does: the signal to every process
    of the render's group -- the driver and each worker at once."""
    os.killpg(proc.pid, sig)


def _reap_group(proc: subprocess.Popen) -> None:
    """After a test: nothing of the render's group may outlive it (also when an assert failed)."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait(30)


def _start_render(cfg: Path, out: Path, workers: int, *extra) -> subprocess.Popen:
    env = dict(os.environ, MSPS_THREADS="1")
    return subprocess.Popen([sys.executable, "-m", "msps_render.cli", "render", str(cfg), "--out", str(out),
                             "--workers", str(workers), "--quiet", *extra], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, env=env, preexec_fn=_own_group_default_sigint)


def _wait_for_shards(out: Path, n: int, proc: subprocess.Popen, timeout: float = 180) -> list[float]:
    """Wait until `n` shards are recorded; the times at which the count first reached 1, 2, ..."""
    deadline = time.time() + timeout
    seen: list[float] = []
    while time.time() < deadline:
        m = read_manifest(out) if (out / "dataset.json").is_file() else None
        k = len(m["shards"]) if m else 0
        seen += [time.time()] * (k - len(seen))
        if k >= n:
            return seen
        assert proc.poll() is None, proc.stderr.read()
        time.sleep(0.05)
    raise AssertionError("no shard finished in time")


def _interrupt_and_check(cfg: Path, out: Path, workers: int, sig: int, n_shards: int, after: int = 2) -> int:
    """Start a render, signal its process group once `after` shards are recorded; check it stops
    in time with 128 + sig and the one-line message, every finished shard recorded (digest as in
    the manifest), no temporaries, no worker left.  Returns the number of shards done.

    In time: < 5 s with workers (the driver waits on a pipe and SIGKILLs them).  In-process
    (1 worker) the signal is handled when the frame in flight returns from Mitsuba's C++ render
    loop, which runs no Python signal handler: < 5 s after one frame's time, measured here as the
    longest gap between shard records before the signal.  Measured at load ~11 on 2 cores: tiny
    in-process 4.90 s stop (gap 2.33 s), 128 x 128 in-process 5.90 s (a fixed 5 s failed) and
    5.40 s (gap 2.20 s); 2 workers stopped within 5 s."""
    proc = _start_render(cfg, out, workers)
    try:
        seen = _wait_for_shards(out, after, proc)
        frame_s = max(b - a for a, b in zip(seen, seen[1:]))
        kids = _children(proc.pid)
        t0 = time.time()
        _signal_group(proc, sig)
        err = proc.communicate(timeout=60)[1]
        stopped = time.time() - t0
    finally:
        _reap_group(proc)
    assert proc.returncode == 128 + sig, err
    print(f"workers {workers}, signal {sig}: stopped in {stopped:.2f} s, longest shard gap {frame_s:.2f} s")
    assert stopped < 5 + (frame_s if workers <= 1 else 0), (stopped, frame_s)
    m = read_manifest(out)
    n = len(m["shards"])
    assert not m["complete"] and n < n_shards
    assert err.strip().splitlines()[-1] == f"interrupted: {n} of {n_shards} shards done; rerun with --resume", err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    files = sorted(p.name for p in (out / "shards").iterdir())
    assert files == sorted(m["shards"])  # every finished shard recorded, no temporaries, nothing else
    assert not list(out.glob(".*.tmp"))
    for name, e in m["shards"].items():
        assert file_digest(out / "shards" / name) == e["file_sha256"]
    time.sleep(1)
    assert not [k for k in kids if _alive(k)]
    return n


@pytest.mark.parametrize("sig,workers", [(signal.SIGINT, 2), (signal.SIGTERM, 2), (signal.SIGINT, 1)])
def test_interrupt_stops_fast_and_keeps_finished_shards(sig, workers, tmp_path):
    """Ctrl-C / SIGTERM to the whole process group (driver and workers at once) of a long tiny run."""
    _interrupt_and_check(tiny(tmp_path, LONG_RUN), tmp_path / "ds", workers, sig, LONG_RUN)


# A realistic frame: 128 x 128 (the demo renders 96 x 96) with the demo's patches (40 px, stride 20)
# and the tiny sampling; enough shards that the signal lands mid-run on a 2-core machine.
REALISTIC = TINY.replace("width = 24", "width = 128").replace("height = 24", "height = 128").replace(
    "size = 16", "size = 40").replace("stride = 8", "stride = 20")
REALISTIC_SHARDS = 10


@pytest.fixture(scope="module")
def realistic_reference(tmp_path_factory):
    """File digests of an uninterrupted in-process render of the realistic config."""
    tmp = tmp_path_factory.mktemp("faults-realistic")
    cfg = tmp / "real.toml"
    cfg.write_text(REALISTIC.format(n_shards=REALISTIC_SHARDS))
    render_dataset(load_config(cfg), tmp / "ref", workers=1, progress=False, variant=_variant())
    return cfg, {p.name: file_digest(p) for p in sorted((tmp / "ref" / "shards").glob("shard-*.h5"))}


@pytest.mark.slow
@pytest.mark.parametrize("sig,workers", [(signal.SIGINT, 1), (signal.SIGINT, 2), (signal.SIGTERM, 2)])
def test_interrupt_at_demo_frame_size_then_resume_is_byte_identical(sig, workers, realistic_reference, tmp_path):
    """Ctrl-C (or SIGTERM) to the process group of a 128 x 128 run mid-way, then `--resume`: every
    finished shard was recorded, and the resumed dataset's shard files are byte-identical to an
    uninterrupted run's (docs/reliability.md: Ctrl-C, resume, determinism)."""
    cfg, ref = realistic_reference
    out = tmp_path / "ds"
    assert REALISTIC.count("128") == 2 and len(ref) == REALISTIC_SHARDS
    done = _interrupt_and_check(cfg, out, workers, sig, REALISTIC_SHARDS)
    assert done >= 2
    r = cli("render", cfg, "--out", out, "--workers", workers, "--quiet", "--resume")
    assert r.returncode == 0, r.stderr[-2000:]
    assert read_manifest(out)["complete"]
    got = {p.name: file_digest(p) for p in sorted((out / "shards").glob("shard-*.h5"))}
    assert got == ref
    assert not list((out / "shards").glob(".*.tmp"))


def test_sigkill_of_driver_leaves_no_worker(tmp_path):
    cfg = tiny(tmp_path, LONG_RUN)
    out = tmp_path / "ds"
    proc = _start_render(cfg, out, 2)
    _wait_for_shards(out, 1, proc)
    kids = _children(proc.pid)
    assert len(kids) >= 2
    proc.kill()
    proc.wait()
    deadline = time.time() + 5
    while time.time() < deadline and [k for k in kids if _alive(k)]:
        time.sleep(0.1)
    assert not [k for k in kids if _alive(k)], "orphan workers survived the driver"
    n = len(read_manifest(out)["shards"])
    time.sleep(1)  # and nobody keeps writing shards the manifest never records
    assert len(list((out / "shards").glob("shard-*.h5"))) <= n + 2


# ----------------------------------------------------------------------------- other commands
@pytest.fixture(scope="module")
def framed(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("framed")
    cfg = load_config(tiny(tmp, 1, "[dataset.storage]\nstore_frames = true\n"))
    render_dataset(cfg, tmp / "ds", progress=False, variant=_variant())
    np.save(tmp / "img.npy", np.random.default_rng(0).random((24, 24, 3)).astype(np.float32))
    from msps_render.scene.sample import SceneConfig, sample_scene

    (tmp / "scene.json").write_text(sample_scene(SceneConfig(), np.random.default_rng(0)).to_json())
    return tmp


@pytest.mark.parametrize("cmd", ["render-scene", "preview", "eval", "predict", "sample-scene"])
def test_read_only_outputs_are_one_line(cmd, framed, tmp_path):
    ro = readonly_dir(tmp_path)
    args = {"render-scene": ["render-scene", framed / "scene.json", "--out", ro],
            "preview": ["preview", framed / "ds", "--out", ro / "sheet.png"],
            "eval": ["eval", "--data", framed / "ds", "--out", ro, "--method", "lambertian"],
            "predict": ["predict", framed / "img.npy", "--out", ro / "pred", "--method", "lambertian"],
            "sample-scene": ["sample-scene", "--out", ro / "s.json"]}[cmd]
    line = one_line_error(cli(*args))
    assert str(ro) in line


def test_random_bytes_checkpoint_message_ends_on_a_word(tmp_path):
    torch = pytest.importorskip("torch")
    from msps_render.models.checkpoint import load_checkpoint

    ck = tmp_path / "junk.pt"
    ck.write_bytes(np.random.default_rng(1).bytes(4096))
    with pytest.raises(InputError) as ei:
        load_checkpoint(ck)
    msg = str(ei.value)
    assert msg.startswith(f"{ck}: not a loadable checkpoint (") and msg.endswith(")")
    inner = msg[msg.index("(") + 1:-1]
    try:
        torch.load(ck, weights_only=True)
    except Exception as e:
        full = str(e).strip().splitlines()[0]
    if inner.endswith("..."):
        kept = inner[:-3]
        assert full.startswith(kept) and full[len(kept)] in " ,;:.", (kept, full)
    else:
        assert inner == full


def test_corrupted_chunk_through_patchdataset_names_the_file(tmp_path, reference):
    pytest.importorskip("torch")
    from msps_render.data import PatchDataset
    from msps_render.testing import corrupt_patch_chunk

    out = tmp_path / "ds"
    shutil.copytree(reference[1], out)
    shard = out / "shards" / "shard-00001.h5"
    corrupt_patch_chunk(shard, 0)
    ds = PatchDataset(out)
    idx = int(ds.offsets[1])
    with pytest.raises(InputError, match=r"shard-00001\.h5: unreadable shard"):
        ds[idx]


@pytest.mark.parametrize("M", [np.zeros((3, 3)), np.array([[0.5, 0.5, 0], [0.5, 0.5, 0], [0, 0, 1.0]])],
                         ids=["zero", "singular"])
def test_verify_flags_unusable_crosstalk(M, tmp_path, reference):
    out = tmp_path / "ds"
    shutil.copytree(reference[1], out)
    shard = out / "shards" / "shard-00002.h5"
    with h5py.File(shard, "r+") as h:
        h[K.FRAME_CROSSTALK][...] = M.astype(np.float32)
    m = json.loads((out / "dataset.json").read_text())
    m["shards"]["shard-00002.h5"]["file_sha256"] = file_digest(shard)  # only the values are wrong
    (out / "dataset.json").write_text(json.dumps(m))
    r = cli("verify", out)
    assert r.returncode == 1 and "shard-00002.h5" in r.stderr and "crosstalk" in r.stderr, r.stderr


# ----------------------------------------------------------------------------- chaos
@pytest.mark.slow
def test_chaos_kills_and_interrupts_then_resume_equals_uninterrupted(tmp_path):
    """SIGKILL / SIGINT at >= 5 random moments of a 2-worker run, then --resume: same arrays as one clean run."""
    n = 60
    cfg_path = tiny(tmp_path, n)
    ref = tmp_path / "ref"
    render_dataset(load_config(cfg_path), ref, workers=1, progress=False, variant=_variant())
    out = tmp_path / "chaos"
    rng = random.Random(1234)
    hits = 0
    for k in range(7):
        proc = _start_render(cfg_path, out, 2, *(["--resume"] if out.exists() else []))
        time.sleep(rng.uniform(1.5, 6.0))
        if proc.poll() is not None:
            break
        sig = rng.choice([signal.SIGKILL, signal.SIGINT])
        kids = _children(proc.pid)
        if sig == signal.SIGINT:  # Ctrl-C reaches the whole group; kill -9 the driver alone
            _signal_group(proc, sig)
        else:
            proc.send_signal(sig)
        err = proc.communicate(timeout=60)[1]
        hits += 1
        assert proc.returncode in (-9, 130), err
        deadline = time.time() + 5
        while time.time() < deadline and [c for c in kids if _alive(c)]:
            time.sleep(0.1)
        assert not [c for c in kids if _alive(c)]
    assert hits >= 5, "the run finished before 5 interruptions; make it longer"
    r = cli("render", cfg_path, "--out", out, "--workers", "2", "--quiet", "--resume")
    assert r.returncode == 0, r.stderr
    assert read_manifest(out)["complete"]
    assert digests(out) == digests(ref)
    assert not list((out / "shards").glob(".*.tmp"))


def test_worker_killed_mid_run_is_one_line_and_keeps_finished_shards(tmp_path):
    """A worker dying under the driver (OOM killer, kill -9): exit 1 naming the shard, no hang, no temporaries."""
    cfg = tiny(tmp_path, LONG_RUN)
    out = tmp_path / "ds"
    proc = _start_render(cfg, out, 2)
    _wait_for_shards(out, 1, proc)
    workers = [k for k in _children(proc.pid) if "resource_tracker" not in Path(f"/proc/{k}/cmdline").read_text()]
    os.kill(workers[0], signal.SIGKILL)
    err = proc.communicate(timeout=60)[1]
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert proc.returncode == 1 and len(lines) == 1, err
    assert f"pid {workers[0]}" in lines[0] and "SIGKILL" in lines[0] and "--resume" in lines[0]
    m = read_manifest(out)
    assert sorted(p.name for p in (out / "shards").iterdir()) == sorted(m["shards"]) and m["shards"]


def _interrupt_at_import(module: str, argv: list[str]) -> subprocess.CompletedProcess:
    """Run `msps ARGV` in a child that sends itself SIGINT when `module` is first imported (an import
    hook: deterministic, unlike a timed signal)."""
    script = textwrap.dedent(f"""
        import importlib.abc, os, signal, sys
        # a harness started in the background (`cmd &` without job control) passes SIGINT ignored,
        # and Python then installs no KeyboardInterrupt handler: restore the terminal's default
        signal.signal(signal.SIGINT, signal.default_int_handler)
        class Hook(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path, target=None):
                if name == {module!r}:
                    os.kill(os.getpid(), signal.SIGINT)
                return None
        sys.meta_path.insert(0, Hook())
        sys.argv = {["msps", *argv]!r}
        from msps_render.cli import app
        app(prog_name="msps")
    """)
    return subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)


def _assert_interrupted_while_starting(r: subprocess.CompletedProcess) -> None:
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 128 + signal.SIGINT, r.stderr[-2000:]
    assert lines == ["msps: interrupted while starting; nothing was written"], r.stderr[-2000:]


def test_ctrl_c_while_the_commands_import_is_one_line_and_130():
    """A Ctrl-C that lands while `msps` is still importing its commands (over a second on a loaded machine)
    ends with one line and 128 + SIGINT, not a KeyboardInterrupt traceback through half-imported modules."""
    _assert_interrupted_while_starting(_interrupt_at_import("msps_render.cli.workflows", ["--help"]))


def test_ctrl_c_while_render_imports_mitsuba_is_one_line_and_130(tmp_path):
    """The same inside `msps render` while Mitsuba/drjit load (seconds): without the guard the interrupt
    inside drjit's extension import surfaced as a NameError traceback and exit 1."""
    out = tmp_path / "out"
    _assert_interrupted_while_starting(_interrupt_at_import("drjit", ["render", "demo", "--out", str(out), "--quiet"]))
    assert not out.exists()


def test_shard_without_its_compression_filter_says_hdf5plugin(tmp_path):
    """A zstd shard read where the filter plugins are not loaded: the line says what to import (HDF5's own
    words are about a plugin directory)."""
    from msps_render.dataset.reader import shard_errors
    from msps_render.errors import InputError

    p = tmp_path / "shard-00000.h5"
    with pytest.raises(InputError, match=r"shard-00000\.h5: cannot decode .*hdf5plugin"):
        with shard_errors(p):
            raise OSError("Can't synchronously read data (can't open directory (/usr/local/lib/plugin). "
                          "Please verify its existence)")


def test_ctrl_c_inside_a_drjit_custom_op_is_still_an_interrupt():
    """A Ctrl-C that lands inside `mi.render` arrives as drjit's RuntimeError caused by the
    KeyboardInterrupt: the render stops as interrupted (130, shards kept), not with a traceback."""
    import signal

    from msps_render.pipeline.run import _stopped_by, _Terminated

    def wrapped(inner):
        try:
            try:
                raise inner
            except BaseException as k:
                raise RuntimeError("drjit.custom(<_RenderOp>): error while performing a custom operation") from k
        except RuntimeError as e:
            return e

    assert _stopped_by(wrapped(KeyboardInterrupt())) == signal.SIGINT
    assert _stopped_by(wrapped(_Terminated())) == signal.SIGTERM
    assert _stopped_by(wrapped(ValueError("a real error"))) is None
