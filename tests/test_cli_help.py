"""Honest CLI output (issue 13): --version, -h everywhere, help texts that say what happens."""
from __future__ import annotations

import numpy as np
from typer.testing import CliRunner

import msps_render
from msps_render.cli import app

runner = CliRunner()


def test_version_and_short_help():
    for flag in ("--version", "-V"):
        r = runner.invoke(app, [flag])
        assert r.exit_code == 0 and r.output.strip() == f"msps {msps_render.__version__}"
    r = runner.invoke(app, ["-h"])
    assert r.exit_code == 0 and "export" in r.output and "compose" in r.output
    for cmd in ("render", "predict", "export", "compose", "sample-scene", "eval"):
        r = runner.invoke(app, [cmd, "-h"])
        assert r.exit_code == 0 and "Usage" in r.output, (cmd, r.output)


def test_help_texts_keep_brackets_and_say_how_png_is_read():
    r = runner.invoke(app, ["sample-scene", "-h"], terminal_width=200)
    assert "TOML with a [scene] table" in r.output  # rich markup used to swallow "[scene]"
    r = runner.invoke(app, ["predict", "-h"], terminal_width=200)
    assert "sRGB-encoded" in r.output and "alpha dropped" in r.output


def test_predict_drops_alpha(tmp_path):
    from msps_render.models.predict import read_inputs

    from msps_render.export.pngio import write_png
    from PIL import Image

    rgba = np.zeros((8, 8, 4), np.uint8)
    rgba[2:6, 2:6] = (200, 100, 50, 255)
    Image.fromarray(rgba, "RGBA").save(tmp_path / "a.png")
    write_png(tmp_path / "b.png", np.ascontiguousarray(rgba[..., :3]))
    img, mask = read_inputs(tmp_path / "a.png", None)
    ref, _ = read_inputs(tmp_path / "b.png", None)
    assert img.shape == (8, 8, 3) and np.array_equal(img, ref) and mask.sum() == 16
