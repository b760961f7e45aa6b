"""`msps config show` (plan exact, estimates checked against a real tiny render) and
`msps config schema` (docs/config.md generated from the models, kept in sync)."""
from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from cli_helpers import cli, one_line_error
from msps_render.pipeline.config import config_hash, load_config, validate_config

ROOT = Path(__file__).resolve().parents[1]

TINY = """
[dataset]
name = "tiny"
seed = 5
n_shards = 2
frames_per_shard = 3

[dataset.patches]
size = 16
stride = 8
min_coverage = 0.5

[scene.shape]
source = "blobby"
subdivisions = 3

[scene.camera]
width = 32
height = 32

[scene.integrator]
spp = 4
max_depth = 2
"""

SWEEP = """
[sweep]
key = "lights.slant_deg"
values = [20.0, 40.0, 60.0]
"""


def write(tmp_path: Path, text: str, name: str = "tiny.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


# ------------------------------------------------------------------ the plan (no Mitsuba)
def test_plan_numbers_exact_with_sweep(tmp_path):
    from msps_render.pipeline.describe import describe

    cfg = load_config(write(tmp_path, TINY + SWEEP))
    d = describe(cfg, probe=0)
    assert d.estimate is None
    assert (d.n_conditions, d.n_shards, d.frames_per_shard, d.n_frames) == (3, 6, 3, 18)
    assert [(c.name, c.value, c.shards, c.frames) for c in d.conditions] == [
        ("slant_deg=20.0", 20.0, 2, 6), ("slant_deg=40.0", 40.0, 2, 6), ("slant_deg=60.0", 60.0, 2, 6)]
    assert d.resolution == (32, 32) and d.spp == 4 and d.patch_size == 16


def test_show_cli_prints_every_key_as_toml_that_reads_back(tmp_path):
    cfg_path = write(tmp_path, TINY + SWEEP)
    r = cli("config", "show", cfg_path, "--probe", "0", "--set", "camera.width=48")
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert "# shards: 6 (3 condition(s) x 2), frames: 18 (3 per shard)" in out
    assert "#   slant_deg=40.0: 2 shards, 6 frames" in out
    assert "estimates: none (nothing rendered)" in out
    # every key, defaults included: a default the file never mentions is printed
    assert "jitter_deg = 0.0" in out and "width = 48" in out and "# distance = (unset)" in out
    back = validate_config(tomllib.loads(out))  # the printed TOML is the resolved config
    assert config_hash(back) == config_hash(load_config(cfg_path, ["camera.width=48"]))


def test_show_renders_nothing_unless_probe_asked_and_says_so(tmp_path):
    """The default is the plan alone (no Mitsuba frame, no temp dir); --probe N renders N frames and
    the heading says so."""
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    cfg_path = write(tmp_path, TINY)
    r = cli("config", "show", cfg_path, env_extra={"TMPDIR": str(tmpdir)})
    assert r.returncode == 0, r.stderr
    assert "# ---- plan (nothing rendered) ----" in r.stdout and "probe frame" not in r.stdout
    assert "estimates: none (nothing rendered); `--probe N` renders N frames" in r.stdout
    from msps_render.render.variant import resolve_variant

    if not resolve_variant("rgb").startswith("llvm"):
        pytest.skip("LLVM variant unavailable: the probe would be too slow")
    r = cli("config", "show", cfg_path, "--probe", "1", "--masks", "1", env_extra={"TMPDIR": str(tmpdir)})
    assert r.returncode == 0, r.stderr
    assert "# ---- plan, with estimates from 1 probe frame(s) rendered now (temp dir, deleted) ----" in r.stdout
    assert "nothing rendered" not in r.stdout and "# render time: ~" in r.stdout
    assert list(tmpdir.iterdir()) == []  # the probe's temp dir is gone


def test_show_json_and_help(tmp_path):
    import json

    from typer.testing import CliRunner

    from msps_render.cli import app

    runner = CliRunner()
    r = runner.invoke(app, ["config", "show", str(write(tmp_path, TINY + SWEEP)), "--probe", "0", "--json"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.output)
    assert (d["n_shards"], d["n_frames"], d["estimate"]) == (6, 18, None)
    for args in (["config", "-h"], ["config", "show", "-h"], ["config", "schema", "-h"]):
        r = runner.invoke(app, args)
        assert r.exit_code == 0 and "Usage" in r.output, (args, r.output)


def test_show_bad_input_one_line_and_nothing_written(tmp_path):
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    env = {"TMPDIR": str(tmpdir)}
    cfg_path = write(tmp_path, TINY)
    line = one_line_error(cli("config", "show", cfg_path, "--set", "lights.slnt_deg=20", env_extra=env))
    assert "lights.slnt_deg" in line and "slant_deg" in line  # names the key, suggests the right one
    line = one_line_error(cli("config", "show", tmp_path / "missing.toml", env_extra=env))
    assert "missing.toml" in line
    bad = write(tmp_path, TINY.replace("width = 32", "width = 12"), "bad.toml")  # patch 16 > 12 px frame
    line = one_line_error(cli("config", "show", bad, "--probe", "0", env_extra=env))
    assert "bad.toml" in line and "patch size" in line
    assert list(tmpdir.iterdir()) == []


def test_bad_set_value_blames_the_set_not_the_file(tmp_path):
    """A value given on the command line that fails validation names that --set (a bad value in the file
    still names the file): the user looks where the mistake is."""
    cfg_path = write(tmp_path, TINY)
    line = one_line_error(cli("config", "show", cfg_path, "--set", "dataset.n_shards=abc"))
    assert line.startswith("error: --set dataset.n_shards=abc: dataset.n_shards: Input should be a valid integer"), line
    assert str(cfg_path) not in line
    line = one_line_error(cli("render", "demo", "--out", tmp_path / "out", "--set", "lights.slant_deg=abc"))
    assert "--set lights.slant_deg=abc: scene.lights.slant_deg:" in line and "demo.toml" not in line, line
    assert not (tmp_path / "out").exists()
    bad = write(tmp_path, TINY.replace("n_shards = 2", 'n_shards = "two"'), "bad.toml")
    line = one_line_error(cli("config", "show", bad, "--set", "camera.width=48"))
    assert "bad.toml: dataset.n_shards:" in line and "--set" not in line, line
    from msps_render.errors import InputError
    from msps_render.models.presets import load_model_config
    with pytest.raises(InputError, match=r"^--set train\.lr=abc: train\.lr: Input should be a valid number"):
        load_model_config("cpu", ["train.lr=abc"])  # the model presets follow the same rule


# ------------------------------------------------------------------ estimates vs a real render
@pytest.fixture(scope="module")
def tiny_render(tmp_path_factory):
    from msps_render.pipeline.run import render_dataset

    d = tmp_path_factory.mktemp("cfgshow")
    cfg_path = write(d, TINY)
    cfg = load_config(cfg_path)
    m = render_dataset(cfg, d / "data", progress=False)
    disk = sum(p.stat().st_size for p in (d / "data" / "shards").glob("*.h5"))
    return cfg_path, m["n_patches"], m["n_frames"], disk


def test_estimates_against_real_render(tiny_render, tmp_path, monkeypatch):
    import tempfile

    from msps_render.pipeline.describe import describe

    cfg_path, real_patches, real_frames, real_disk = tiny_render
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # the probe's temp dir goes here
    cfg = load_config(cfg_path)

    # masks of every frame: the patch count is exact (same seeds, same mask as the render)
    full = describe(cfg, probe=1, masks=6)
    e = full.estimate
    assert full.n_frames == real_frames == 6
    assert e.exact and e.mask_frames == 6 and e.patches == real_patches
    assert sum(e.patches_per_frame) == real_patches
    # disk: patches are exact here, so what is left is the compression factor and frame-record
    # size measured on 1 of 6 frames, and HDF5 metadata measured on a 1-frame shard (its chunk
    # index grows with the patch count: at this tiny size metadata is ~60% of a shard and the
    # estimate came out 7% low); 20% leaves room for that without hiding a wrong model
    # (forgetting the metadata or the compression would be off by > 50%)
    assert abs(e.disk_bytes - real_disk) <= 0.20 * real_disk, (e.disk_bytes, real_disk)
    assert e.probe_frames == 1 and e.seconds_per_frame > 0 and e.startup_seconds >= 0
    assert e.render_seconds == pytest.approx(e.startup_seconds + 6 * e.seconds_per_frame)

    # 2 of 6 frames counted: the estimate states a margin (2 standard errors) and the real
    # count lies inside it (deterministic: the seeds are fixed)
    part = describe(cfg, probe=1, masks=2).estimate
    assert not part.exact and part.mask_frames == 2 and part.patches_margin is not None
    assert part.patches_per_frame == e.patches_per_frame[:2]  # frames 0-1 of shard-00000, in plan order
    assert abs(part.patches - real_patches) <= part.patches_margin, (part.patches, part.patches_margin, real_patches)
    assert list(tmp_path.iterdir()) == []  # the probe shard was deleted


def test_failed_probe_leaves_no_temporaries(tmp_path, monkeypatch):
    import tempfile

    from msps_render.errors import InputError
    from msps_render.pipeline import describe as D

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))

    def broken(path):
        assert Path(path).is_file()  # the probe shard exists when it fails ...
        raise InputError(path, "simulated failure")

    monkeypatch.setattr(D, "storage_bytes", broken)
    (tmp_path / "cfg").mkdir()
    cfg = load_config(write(tmp_path / "cfg", TINY))
    with pytest.raises(InputError, match="simulated failure"):
        D.describe(cfg, probe=1, masks=1)
    assert [p.name for p in tmp_path.iterdir()] == ["cfg"]  # ... and is gone with its directory


# ------------------------------------------------------------------ schema
def test_docs_config_md_in_sync():
    from msps_render.cli.config import config_reference

    text = config_reference()
    assert (ROOT / "docs" / "config.md").read_text() == text, \
        "docs/config.md is out of date: run `msps config schema --out docs/config.md`"


def _leaves(model, prefix=""):
    from msps_render.config_doc import _model_of

    for name, f in model.model_fields.items():
        sub = _model_of(f.annotation)
        if sub is not None:
            yield from _leaves(sub, f"{prefix}{name}.")
        else:
            yield f"{prefix}{name}", f


def test_reference_lists_every_key_with_type_and_default():
    from msps_render.cli.config import config_reference
    from msps_render.pipeline.config import DatasetConfig

    text = config_reference()
    rows = {ln.split("|")[1].strip().strip("`"): ln for ln in text.splitlines() if ln.startswith("| `")}
    leaves = dict(_leaves(DatasetConfig))
    assert len(leaves) > 60
    for key in leaves:
        assert key in rows, key
    assert "| `scene.lights.slant_deg` | float | `30.0` | > 0, < 90 | angle between" in text
    # the main keys say what they mean (and their unit)
    main = [k for k in leaves if k.startswith(("dataset.", "scene.camera.", "scene.lights.", "scene.shape.",
                                              "scene.integrator.", "scene.environment.", "scene.materials."))]
    missing = [k for k in main if not leaves[k].description]
    assert missing == []


def test_schema_cli_writes_the_reference(tmp_path):
    r = cli("config", "schema", "--out", tmp_path / "config.md")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "config.md").read_text() == (ROOT / "docs" / "config.md").read_text()
    line = one_line_error(cli("config", "schema", "--out", tmp_path))
    assert str(tmp_path) in line
