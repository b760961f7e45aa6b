"""Dataset pipeline: determinism, resume after SIGKILL, verify, loader round trip, bad input."""
from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from msps_render.dataset import schema as K  # the shard's HDF5 keys
from msps_render.errors import InputError
from msps_render.pipeline.config import load_config
from msps_render.dataset.manifest import read_manifest
from msps_render.pipeline.run import render_dataset
from msps_render.dataset.verify import verify_dataset
from msps_render.dataset import read_digests

pytestmark = pytest.mark.usefixtures("force_llvm")  # LLVM even where CUDA is preferred (conftest.py)

TINY = """
[dataset]
name = "tiny"
seed = 5
n_shards = {n_shards}
frames_per_shard = 2
[dataset.patches]
size = 16
stride = 8
min_coverage = 0.5
[dataset.storage]
store_frames = {store_frames}
[scene.camera]
width = 40
height = 40
[scene.integrator]
spp = 4
max_depth = 3
"""


def tiny_config(tmp_path: Path, n_shards=3, store_frames=False, name="tiny.toml") -> Path:
    p = tmp_path / name
    p.write_text(TINY.format(n_shards=n_shards, store_frames=str(store_frames).lower()))
    return p


def digests(root: Path) -> dict:
    return {p.name: read_digests(p) for p in sorted((root / "shards").glob("shard-*.h5"))}


def file_shas(root: Path) -> dict:
    m = read_manifest(root)
    return {k: v["file_sha256"] for k, v in m["shards"].items()}


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """One uninterrupted single-worker run that other tests compare against."""
    tmp = tmp_path_factory.mktemp("ref")
    cfg = load_config(tiny_config(tmp, n_shards=4))
    out = tmp / "ref"
    render_dataset(cfg, out, workers=1, progress=False, variant=_variant())
    return cfg, out


def _variant():
    from msps_render.render.variant import resolve_variant

    v = resolve_variant("rgb")
    if not v.startswith("llvm"):
        pytest.skip("LLVM variant unavailable: pipeline tests would be too slow")
    return v


def test_reference_dataset_is_complete_and_verifies(reference):
    cfg, out = reference
    m = read_manifest(out)
    assert m["complete"] and len(m["shards"]) == 4 and m["n_patches"] > 20
    assert verify_dataset(out) == {}
    with h5py.File(out / "shards" / "shard-00000.h5", "r") as h:
        assert h.attrs["complete"] and h.attrs["format_version"] == 1
        assert h.attrs["config_hash"] and h.attrs["variant"].startswith("llvm")
        assert h[K.PATCH_IMAGE].shape[1:] == (16, 16, 3)
        plist = h[K.PATCH_IMAGE].id.get_create_plist()  # the default filter: zstd (32015) + fletcher32 (3)
        assert {plist.get_filter(i)[0] for i in range(plist.get_nfilters())} >= {32015, 3}
        ld = h[K.FRAME_LIGHT_DIRS][0]
        np.testing.assert_allclose(np.linalg.norm(ld, axis=1), 1, atol=1e-6)
        spec = json.loads(h[K.FRAME_SCENE_JSON].asstr()[0])
        assert spec["lights"][0]["slant_deg"] == pytest.approx(30)


def test_two_workers_and_dask_give_identical_shards(reference, tmp_path):
    cfg, ref = reference
    render_dataset(cfg, tmp_path / "two", workers=2, progress=False, variant=_variant())
    assert digests(tmp_path / "two") == digests(ref)
    assert file_shas(tmp_path / "two") == file_shas(ref)  # byte-identical files
    pytest.importorskip("dask.distributed")
    render_dataset(cfg, tmp_path / "dask", workers=2, scheduler="dask-local", progress=False, variant=_variant())
    assert digests(tmp_path / "dask") == digests(ref)


def test_kill_and_resume_equals_uninterrupted(reference, tmp_path):
    cfg, ref = reference
    cfg_path = tiny_config(tmp_path, n_shards=4)
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "msps_render.cli", "render", str(cfg_path), "--out", str(out), "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.time() + 120
    while time.time() < deadline:  # wait until at least one shard is done, then kill mid-run
        m = read_manifest(out) if (out / "dataset.json").is_file() else None
        if m and len(m["shards"]) >= 1:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    m = read_manifest(out)
    assert m is not None and not m["complete"], "the run finished before it could be killed"
    r = subprocess.run(cmd + ["--resume"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert read_manifest(out)["complete"]
    assert digests(out) == digests(ref)
    assert not list((out / "shards").glob(".*.tmp"))


def test_same_config_refused_without_resume_and_other_config_without_force(reference, tmp_path):
    cfg, ref = reference
    out = tmp_path / "copy"
    shutil.copytree(ref, out)
    with pytest.raises(InputError, match="already holds this dataset"):
        render_dataset(cfg, out, progress=False)
    m = render_dataset(cfg, out, resume=True, progress=False)  # nothing left to do
    assert m["last_run"]["shards_rendered"] == 0
    other = load_config(tiny_config(tmp_path, n_shards=4), ["lights.slant_deg=25"])
    with pytest.raises(InputError, match="different config"):
        render_dataset(other, out, resume=True, progress=False)
    r = subprocess.run([sys.executable, "-m", "msps_render.cli", "render", str(tiny_config(tmp_path, 4)),
                        "--out", str(out), "--set", "lights.slant_deg=25"], capture_output=True, text=True)
    assert r.returncode == 1 and "different config" in r.stderr and "--force" in r.stderr


def _corrupt_copy(ref: Path, tmp: Path, name: str) -> Path:
    out = tmp / name
    shutil.copytree(ref, out)
    return out


def test_verify_catches_corruption(reference, tmp_path):
    _, ref = reference
    shard = "shard-00001.h5"
    # 1. a flipped byte in the middle of the file
    d = _corrupt_copy(ref, tmp_path, "flip")
    p = d / "shards" / shard
    b = bytearray(p.read_bytes())
    b[len(b) // 2] ^= 0xFF
    p.write_bytes(bytes(b))
    assert shard in verify_dataset(d)
    # 2. truncated
    d = _corrupt_copy(ref, tmp_path, "trunc")
    p = d / "shards" / shard
    p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 3])
    assert any("unreadable" in s or "checksum" in s for s in verify_dataset(d)[shard])
    # 3. no complete flag
    d = _corrupt_copy(ref, tmp_path, "flag")
    with h5py.File(d / "shards" / shard, "r+") as h:
        h.attrs["complete"] = False
    assert any("not complete" in s for s in verify_dataset(d)[shard])
    # 4. a NaN patch
    d = _corrupt_copy(ref, tmp_path, "nan")
    with h5py.File(d / "shards" / shard, "r+") as h:
        img = h[K.PATCH_IMAGE][()]
        img[0, 3, 3, 1] = np.nan
        h[K.PATCH_IMAGE][...] = img
    assert any("NaN" in s for s in verify_dataset(d)[shard])
    # the CLI exits 1 naming the shard
    r = subprocess.run([sys.executable, "-m", "msps_render.cli", "verify", str(d)], capture_output=True, text=True)
    assert r.returncode == 1 and shard in r.stderr
    r = subprocess.run([sys.executable, "-m", "msps_render.cli", "verify", str(ref)], capture_output=True, text=True)
    assert r.returncode == 0


def test_dataset_patches_equal_rendered_frame_crops(tmp_path):
    torch = pytest.importorskip("torch")
    from msps_render.data import PatchDataset, ShardBatchSampler, iter_frames
    from msps_render.render import render_frame
    from msps_render.scene.spec import SceneSpec

    cfg = load_config(tiny_config(tmp_path, n_shards=2, store_frames=True))
    out = tmp_path / "ds"
    render_dataset(cfg, out, progress=False, variant=_variant())
    ds = PatchDataset(out)
    assert len(ds) == read_manifest(out)["n_patches"]
    frames = list(iter_frames(out))
    with h5py.File(out / "shards" / "shard-00000.h5", "r") as h:
        spec = SceneSpec.from_json(h[K.FRAME_SCENE_JSON].asstr()[1])
        fi, yx = h[K.PATCH_FRAME_INDEX][()], h[K.PATCH_YX][()]
    frame = render_frame(spec, variant=_variant())  # re-render from the stored SceneSpec
    np.testing.assert_array_equal(frame.image, frames[1].image)  # deterministic
    P = 16
    for j in np.nonzero(fi == 1)[0]:
        item = ds[int(j)]
        y, x = yx[j]
        crop = frame.image[y:y + P, x:x + P].transpose(2, 0, 1)
        # float16 storage: relative error <= 2^-11 (+ tiny absolute for subnormals)
        np.testing.assert_allclose(item["image"].numpy(), crop, rtol=2 ** -11, atol=1e-7)
        ncrop = frame.normal[y:y + P, x:x + P].transpose(2, 0, 1)
        np.testing.assert_allclose(item["normal"].numpy(), ncrop, atol=2 ** -11)
        assert np.array_equal(item["mask"][0].numpy().astype(bool), frame.mask[y:y + P, x:x + P])
        np.testing.assert_allclose(item["light_dirs"].numpy(), frame.light_dirs, atol=1e-6)
    # batched loading through a DataLoader with the shard-aware sampler sees every patch once
    loader = torch.utils.data.DataLoader(ds, batch_sampler=ShardBatchSampler(ds, 8, seed=1))
    seen = torch.cat([b["index"] for b in loader])
    assert sorted(seen.tolist()) == list(range(len(ds)))
    b = next(iter(loader))
    assert b["image"].shape[1:] == (3, P, P) and b["mask"].shape[1:] == (1, P, P)
    cached = PatchDataset(out, cache=True)
    assert torch.equal(cached[5]["image"], ds[5]["image"])
    from msps_render.data import make_loader

    fast = list(make_loader(ds, 8, seed=2))
    assert sorted(torch.cat([b["index"] for b in fast]).tolist()) == list(range(len(ds)))
    b0 = fast[0]
    for r in range(len(b0["index"])):  # batched fetch equals per-item fetch
        assert torch.equal(b0["image"][r], ds[int(b0["index"][r])]["image"])
    # several dataset directories read as one: patches of the first, then of the second
    both = PatchDataset([out, out])
    assert len(both) == 2 * len(ds)
    assert torch.equal(both[len(ds) + 3]["image"], ds[3]["image"])
    with pytest.raises(InputError, match="no dataset.json"):
        PatchDataset([out, tmp_path])


def test_bad_config_inputs(tmp_path):
    p = tiny_config(tmp_path)
    with pytest.raises(InputError, match=r"unknown key 'scene.lights.slnt_deg' \(did you mean 'slant_deg'\?\)"):
        load_config(p, ["scene.lights.slnt_deg=30"])
    with pytest.raises(InputError, match="slant_deg"):
        load_config(p, ["lights.slant_deg=95"])
    with pytest.raises(InputError, match="n_shards"):
        load_config(p, ["dataset.n_shards=0"])
    with pytest.raises(InputError, match="config file not found"):
        load_config(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[dataset\n")
    with pytest.raises(InputError, match="bad.toml: not valid TOML"):
        load_config(bad)


def test_full_disk_leaves_no_partial_shard(tmp_path, monkeypatch):
    from msps_render.dataset import writer

    cfg = load_config(tiny_config(tmp_path, n_shards=1))
    real = writer.create_array
    calls = {"n": 0}

    def failing(g, name, data, compression, chunks=None):
        calls["n"] += 1
        if calls["n"] == 3:
            raise OSError(28, "No space left on device")
        return real(g, name, data, compression, chunks)

    monkeypatch.setattr(writer, "create_array", failing)
    out = tmp_path / "full"
    with pytest.raises(OSError, match="No space left"):
        render_dataset(cfg, out, progress=False, variant=_variant())
    # neither a final shard nor a temp file nor an empty manifest: the failed first run leaves nothing
    assert not out.exists()


def test_sweep_conditions_share_scenes(tmp_path):
    p = tiny_config(tmp_path, n_shards=1)
    p.write_text(p.read_text() + '\n[sweep]\nkey = "lights.slant_deg"\nvalues = [20.0, 40.0]\n')
    cfg = load_config(p)
    out = tmp_path / "sweep"
    m = render_dataset(cfg, out, progress=False, variant=_variant())
    assert m["conditions"] == ["slant_deg=20.0", "slant_deg=40.0"] and len(m["shards"]) == 2
    objs = []
    for name in sorted(m["shards"]):
        with h5py.File(out / "shards" / name, "r") as h:
            objs.append([json.loads(s)["shape"] for s in h[K.FRAME_SCENE_JSON].asstr()[()]])
            slant = h[K.FRAME_SLANT_DEG][()]
        assert np.allclose(slant, 20.0 if name.endswith("0.h5") else 40.0)
    assert objs[0] == objs[1]  # same objects under both conditions


def test_sensor_noise_has_its_own_stream(tmp_path):
    """The recorded image is re-created from the stored scene and its frame's sensor stream alone
    (no replay of the scene sampler's draws), so sampler changes never move the sensor noise."""
    from msps_render.data import iter_frames
    from msps_render.pipeline.plan import plan, sensor_rng
    from msps_render.render import render_frame
    from msps_render.render.sensor import apply_sensor
    from msps_render.scene.spec import SceneSpec

    cfg = load_config(tiny_config(tmp_path, n_shards=1, store_frames=True), ["sensor.enabled=true"])
    out = tmp_path / "ds"
    render_dataset(cfg, out, progress=False, variant=_variant())
    task = plan(cfg)[0]
    with h5py.File(out / "shards" / "shard-00000.h5", "r") as h:
        spec = SceneSpec.from_json(h[K.FRAME_SCENE_JSON].asstr()[1])
    stored = list(iter_frames(out))[1].image
    clean = render_frame(spec, variant=_variant())
    again = apply_sensor(clean, cfg.sensor, sensor_rng(task, 1)).image
    np.testing.assert_array_equal(again.astype(stored.dtype), stored)  # as stored (float16 or float32)
    other = apply_sensor(clean, cfg.sensor, sensor_rng(task, 0)).image  # another frame's stream
    assert not np.array_equal(other, again)


def test_local_workers_share_the_cores(monkeypatch):
    """Without a thread count, each of N local workers gets cores / N drjit threads (not all cores
    each: 2 workers x 2 threads on 2 cores was 1.23x slower on the full paper corpus)."""
    import os

    from msps_render.pipeline.run import worker_threads

    monkeypatch.delenv("MSPS_THREADS", raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: 8)
    assert worker_threads(None, 2) == 4 and worker_threads(None, 3) == 2 and worker_threads(None, 16) == 1
    assert worker_threads(None, 1) is None  # one worker: drjit's default (all cores)
    assert worker_threads(3, 2) == 3  # given: kept
    monkeypatch.setenv("MSPS_THREADS", "2")
    assert worker_threads(None, 2) is None  # the environment decides (render.variant.activate reads it)


@pytest.mark.parametrize("var, value", [("MSPS_THREADS", "abc"), ("MSPS_THREADS", "0"), ("MSPS_THREADS", "-2"),
                                        ("MSPS_PROGRESS_EVERY", "abc"), ("MSPS_PROGRESS_EVERY", "-1"),
                                        ("MSPS_PROGRESS_EVERY", "nan")])
def test_a_bad_setting_in_the_environment_is_one_line_before_any_work(var, value, tmp_path):
    """MSPS_THREADS that is not a whole number >= 1, MSPS_PROGRESS_EVERY that is not seconds >= 0: one line
    naming it, exit 1, no --out created.  Was a traceback: MSPS_THREADS's from int() or drjit, raised in a
    worker after dataset.json was written; MSPS_PROGRESS_EVERY's at import, breaking every command."""
    from cli_helpers import cli, one_line_error

    why = {"MSPS_THREADS": "a whole number >= 1 (render threads)", "MSPS_PROGRESS_EVERY": "a number of seconds >= 0"}
    for args in (("render", "demo", "--out", tmp_path / "ds", "--quiet", "--workers", "2"),
                 ("train", "cpu", "--data", tmp_path / "ds", "--val", tmp_path / "ds", "--out", tmp_path / "run")):
        line = one_line_error(cli(*args, env_extra={var: value}))
        assert line == f"error: {var}: must be {why[var]}, got {value!r}", line
    assert list(tmp_path.iterdir()) == []
