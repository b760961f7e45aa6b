"""Honest CLI output (issue 13): --version, -h everywhere, help texts that say what happens."""
from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

import msps_render
from msps_render.cli import app

runner = CliRunner()
pytestmark = pytest.mark.usefixtures("force_llvm")  # LLVM even where CUDA is preferred (conftest.py)


def test_version_and_short_help():
    for flag in ("--version", "-V"):
        r = runner.invoke(app, [flag])
        assert r.exit_code == 0 and r.output.strip() == f"msps {msps_render.__version__}"
    r = runner.invoke(app, ["-h"])
    assert r.exit_code == 0 and "export" in r.output and "compose" in r.output
    for cmd in ("render", "predict", "export", "compose", "sample-scene", "eval"):
        r = runner.invoke(app, [cmd, "-h"])
        assert r.exit_code == 0 and "Usage" in r.output, (cmd, r.output)


def test_one_version_everywhere():
    """The version is written twice (pyproject for the wheel's metadata, __version__ for `msps -V`):
    they must agree."""
    import tomllib
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    declared = tomllib.loads((root / "pyproject.toml").read_text())["project"]["version"]
    assert declared == msps_render.__version__


def test_help_texts_keep_brackets_and_say_how_png_is_read():
    r = runner.invoke(app, ["sample-scene", "-h"], terminal_width=200)
    assert "TOML with a [scene] table" in r.output  # rich markup used to swallow "[scene]"
    r = runner.invoke(app, ["predict", "-h"], terminal_width=200)
    assert "sRGB-encoded" in r.output and "alpha dropped" in r.output


def test_predict_drops_alpha(tmp_path):
    from msps_render.models.predict import read_inputs

    from msps_render.io.png16 import write_png
    from PIL import Image

    rgba = np.zeros((8, 8, 4), np.uint8)
    rgba[2:6, 2:6] = (200, 100, 50, 255)
    Image.fromarray(rgba, "RGBA").save(tmp_path / "a.png")
    write_png(tmp_path / "b.png", np.ascontiguousarray(rgba[..., :3]))
    img, mask = read_inputs(tmp_path / "a.png", None, linear=False)  # Pillow's is untagged, ours tagged
    ref, _ = read_inputs(tmp_path / "b.png", None, linear=False)  # linear: decode both the same way
    assert img.shape == (8, 8, 3) and np.array_equal(img, ref) and mask.sum() == 16


def test_render_scene_writes_per_light_pngs_and_part_map_and_says_what_it_does(tmp_path):
    from msps_render.render.variant import resolve_variant

    if not resolve_variant("rgb").startswith("llvm"):
        import pytest

        pytest.skip("LLVM variant unavailable")
    from cli_helpers import cli
    from msps_render.io.png16 import read_png
    from msps_render.io.images import read_image
    from msps_render.scene.sample import SceneConfig, sample_scene

    cfg = SceneConfig.model_validate({"camera": {"width": 32, "height": 32}, "integrator": {"spp": 4}})
    spec = sample_scene(cfg, np.random.default_rng(2), seed=2)
    (tmp_path / "s.json").write_text(spec.to_json())
    r = cli("render-scene", tmp_path / "s.json", "--out", tmp_path / "o", "--per-light")
    assert r.returncode == 0, r.stderr
    assert "rendering" in r.stdout and "32x32, 4 spp, 3 emitter(s)" in r.stdout and " s -> " in r.stdout
    mask = read_png(tmp_path / "o" / "mask.png") > 0
    part = read_png(tmp_path / "o" / "part.png")
    assert part.shape == (32, 32, 3) and (part[~mask] == 0).all() and (part[mask].max(-1) > 0).all()
    per = [read_png(tmp_path / "o" / f"light{k}.png").astype(float) for k in range(3)]
    exr = [read_image(tmp_path / "o" / f"light{k}.exr") for k in range(3)]
    for k in range(3):  # one shared exposure: light k's PNG is brightest where its EXR is
        assert per[k].shape == (32, 32, 3)
        assert np.corrcoef(per[k][mask].sum(-1), exr[k][mask].sum(-1))[0, 1] > 0.9


@pytest.mark.parametrize("args, option", [
    (["render", "demo", "--out", "{t}/d", "--threads", "-1"], "--threads"),  # was a drjit TypeError traceback
    (["render", "demo", "--out", "{t}/d", "--workers", "0"], "--workers"),  # was: rendered in-process
    (["render", "demo", "--out", "{t}/d", "--seed", "-1"], "--seed"),
    (["render", "demo", "--out", "{t}/d", "--recycle-after", "-1"], "--recycle-after"),
    (["sample-scene", "--seed", "-1", "--out", "{t}/s.json"], "--seed"),  # was a numpy ValueError traceback
    (["render-scene", "{t}/s.json", "--out", "{t}/r", "--threads", "0"], "--threads"),
    (["config", "show", "demo", "--threads", "0"], "--threads"),
    (["train", "cpu", "--data", "{t}", "--val", "{t}", "--out", "{t}/run", "--threads", "0"], "--threads"),
    (["eval", "--data", "{t}", "--out", "{t}/e", "--max-patches", "0"], "--max-patches"),
])
def test_counts_out_of_range_are_refused_before_any_work(args, option, tmp_path):
    """Counts and seeds below their range: a usage error naming the option (exit 2), nothing written."""
    r = runner.invoke(app, [a.format(t=tmp_path) for a in args])
    assert r.exit_code == 2, r.output
    assert "Invalid value" in r.output and option in r.output and "Traceback" not in r.output, r.output
    assert list(tmp_path.iterdir()) == []
