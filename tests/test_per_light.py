"""Per-light images stored in shards (`dataset.storage.store_per_light`, issue 23 item 4).

Tolerances:
* stored per-light and environment images are float16 (image_dtype): rounding to nearest keeps
  |x16 - x| <= 2^-11 |x| (10 stored mantissa bits) in the normal range and <= 2^-25 below it
  (subnormal spacing 2^-24).  The renderer makes the image as the float32 sum of the same
  components, so |sum(stored) - image| <= 2^-11 * sum(components) + 4 * 2^-25 (+ float32 rounding
  of that sum, 1e-6 relative, far below).
* a re-render uses the frame's stored scene, seed and variant: it reproduces the components to
  float32 rounding (`per_light_max_rel_deviation` <= 1e-5, measured 0), so an export from stored
  components differs from one re-rendered by the float16 rounding above plus each file's own
  quantisation: half a step of its integer code on its exposure (STEP16 / png_scale, STEP8 / ...).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import cli, one_line_error, render_tiny
from msps_render.dataset import schema as K

TINY = """
[dataset]
name = "tiny-per-light"
seed = 4
n_shards = 1
frames_per_shard = 2
[dataset.patches]
size = 16
stride = 8
[dataset.storage]
store_frames = true
store_per_light = {per_light}
[scene.environment]
enabled = true
[scene.camera]
width = 32
height = 32
[scene.integrator]
spp = 4
max_depth = 3
[sweep]
key = "environment.ratio"
values = [0.0, 0.3]
"""
F16 = 2.0 ** -11  # float16 relative rounding (to nearest)
F16_TINY = 2.0 ** -25  # half the float16 subnormal spacing
STEP16 = 0.51 / 65535  # half a 16-bit step (+ float64 rounding slack)
STEP8 = 0.51 / 255


def _render(tmp: Path, per_light: bool) -> Path:
    return render_tiny(TINY.format(per_light=str(per_light).lower()), tmp, f"ds-{per_light}")


@pytest.fixture(scope="module")
def stored(tmp_path_factory) -> Path:
    return _render(tmp_path_factory.mktemp("pl"), True)


@pytest.fixture(scope="module")
def old(tmp_path_factory) -> Path:
    """The same dataset without per-light images: what shards before store_per_light look like."""
    return _render(tmp_path_factory.mktemp("old"), False)


def _shards(root: Path) -> list[Path]:
    return sorted((root / "shards").glob("shard-*.h5"))


def test_option_needs_whole_frames(tmp_path):
    from msps_render.errors import InputError
    from msps_render.pipeline.config import load_config

    p = tmp_path / "c.toml"
    p.write_text(TINY.format(per_light="true").replace("store_frames = true", "store_frames = false"))
    with pytest.raises(InputError, match="store_per_light needs store_frames"):
        load_config(p)


def test_per_light_images_sum_to_the_stored_image(stored):
    import h5py

    from msps_render.dataset import iter_whole_frames, verify_dataset

    assert verify_dataset(stored) == {}  # checksums of the new arrays recorded and matching
    n_env = 0
    for path in _shards(stored):
        with h5py.File(path, "r") as h:
            per, env = h[K.FRAME_PER_LIGHT], h.get(K.FRAME_ENV_IMAGE)
            assert per.dtype == np.float16 and per.shape == (2, 3, 32, 32, 3)
            ratio = h[K.FRAME_ENV_RATIO][()]
            # the environment image is stored where some frame has an environment light
            assert (env is not None) == bool((ratio > 0).any())
        for fr in iter_whole_frames(path, per_light=True):
            assert fr.per_light.shape == (3, 32, 32, 3)
            parts = list(fr.per_light) + ([fr.env_image] if fr.env_image is not None else [])
            total = np.sum(parts, axis=0)
            tol = F16 * total + len(parts) * F16_TINY + 1e-6 * fr.image
            assert (np.abs(total - fr.image) <= tol).all(), float((np.abs(total - fr.image) - tol).max())
            if fr.env_ratio > 0:
                n_env += 1
                assert fr.env_image is not None and fr.env_image[fr.mask].min() >= 0
                assert fr.env_image.max() > 0  # the environment light is not lost
            elif fr.env_image is not None:
                assert not fr.env_image.any()  # frames without one store zeros
        assert all(f.per_light is None for f in iter_whole_frames(path))  # read only when asked
    assert n_env == 2


def _decoded16(d: Path, name: str, scale: float) -> np.ndarray:
    from msps_render.io.png16 import from_unorm, read_png

    return from_unorm(read_png(d / name)) / scale


def test_exports_from_stored_per_light_equal_rerender_of_old_shards(stored, old, tmp_path):
    from msps_render.export import export_dataset
    from msps_render.io.images import read_image
    from msps_render.io.png16 import read_png

    for fmt in ("diligent", "psfcn", "png16", "exr"):
        a = export_dataset(stored, fmt, tmp_path / f"{fmt}-stored")  # no --rerender needed
        b = export_dataset(old, fmt, tmp_path / f"{fmt}-old", rerender=True)
        assert a["per_light"]["source"].startswith("stored") and b["per_light"]["source"].startswith("re-rendered")
        assert "clean" in a["per_light"]["contents"] and "environment" in a["per_light"]["contents"]
        assert a["n_frames"] == b["n_frames"] == 4
        for fa, fb in zip(a["frames"], b["frames"]):
            assert fb["per_light_max_rel_deviation"] <= 1e-5  # the re-render reproduces the render
            assert fa["per_light_max_rel_deviation"] <= F16 * 1.01  # stored: float16 rounding only
            assert fa["environment_image"] == fb["environment_image"] == (fa["env_ratio"] > 0)
            da, db = tmp_path / f"{fmt}-stored" / fa["dir"], tmp_path / f"{fmt}-old" / fb["dir"]
            if fmt == "diligent":
                names = ["001.png", "002.png", "003.png"]
                sa, sb = fa["png_scale"], fb["png_scale"]
            elif fmt == "psfcn":
                names = ["l_000.png", "l_001.png", "l_002.png"]
                sa, sb = fa["png_scale"], fb["png_scale"]
            elif fmt == "png16":
                names = ["light0.png", "light1.png", "light2.png"]
                sa, sb = fa["png_scale"], fb["png_scale"]
            else:
                names = ["light0.exr", "light1.exr", "light2.exr"]
            if fa["environment_image"]:
                names.append("environment.exr" if fmt == "exr" else "environment.png")
            for name in names:
                if fmt == "exr":
                    x, y = read_image(da / name), read_image(db / name)
                    assert (np.abs(x - y) <= F16 * np.abs(y) + F16_TINY).all(), name
                    continue
                if name == "environment.png" and fmt != "png16":
                    sa, sb = fa["env_png_scale"], fb["env_png_scale"]
                if fmt == "psfcn":
                    from msps_render.io.png16 import from_unorm

                    x, y = from_unorm(read_png(da / name)) / sa, from_unorm(read_png(db / name)) / sb
                    step = STEP8
                else:
                    x, y = _decoded16(da, name, sa), _decoded16(db, name, sb)
                    step = STEP16
                # float16 rounding of the value (and of the exposure it set) + half a code step in each file
                tol = 2 * F16 * np.maximum(x, y) + step / sa + step / sb
                assert (np.abs(x - y) <= tol).all(), (fmt, name, float((np.abs(x - y) - tol).max()))
        idx = json.loads((tmp_path / f"{fmt}-stored" / "export.json").read_text())
        assert idx["per_light"]["files"]


def test_old_shards_export_with_rerender_and_refuse_without(old, tmp_path):
    from msps_render.dataset import iter_whole_frames
    from msps_render.export import export_dataset

    assert all(f.per_light is None for p in _shards(old) for f in iter_whole_frames(p, per_light=True))
    r = cli("export", old, "--format", "psfcn", "--out", tmp_path / "x")
    line = one_line_error(r)
    assert "shard-00000.h5" in line and "--rerender" in line and "store_per_light" in line
    assert not (tmp_path / "x").exists()
    idx = export_dataset(old, "png16", tmp_path / "png")  # per-frame images need no per-light images
    assert idx["per_light"] is None
    assert not list((tmp_path / "png").glob("*/light0.png"))
    idx = export_dataset(old, "diligent", tmp_path / "dl", rerender=True)
    assert idx["n_frames"] == 4 and all(f["per_light_max_rel_deviation"] <= 1e-5 for f in idx["frames"])
    # the environment light is written (and said), not dropped
    env = [f for f in idx["frames"] if f["env_ratio"] > 0]
    assert env and all((tmp_path / "dl" / f["dir"] / "environment.png").is_file() for f in env)
