"""The import stack and the registries: the training side loads no scene/render module and
no Mitsuba; the renderer loads no torch; every kind has one registry and unknown names fail."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from msps_render.errors import InputError


def _loaded(code: str) -> list[str]:
    out = subprocess.run([sys.executable, "-c", code + "\nimport sys; print(' '.join(sorted(sys.modules)))"],
                         capture_output=True, text=True, check=True)
    return out.stdout.split()


def test_training_side_imports_no_scene_render_or_mitsuba():
    mods = _loaded("import msps_render.data, msps_render.models.train, msps_render.models.evaluate, "
                   "msps_render.models.predict, msps_render.cli")
    bad = [m for m in mods if m.startswith(("msps_render.scene", "msps_render.render", "msps_render.pipeline",
                                             "mitsuba", "drjit"))]
    assert not bad, bad
    assert "torch" in mods


def test_renderer_imports_no_torch():
    mods = _loaded("import msps_render.render, msps_render.pipeline.run, msps_render.scene.sample")
    assert "torch" not in mods and "mitsuba" not in mods  # Mitsuba only once a frame is rendered


def test_material_kinds_have_one_translator_each():
    from msps_render.brdf.families import FAMILIES, MATERIAL_KINDS, MEASURED_KIND
    from msps_render.render.materials import BSDFS

    assert set(BSDFS) | {MEASURED_KIND} == set(MATERIAL_KINDS)
    assert all(f.bsdf in BSDFS for f in FAMILIES.values())


def test_unknown_primitive_is_an_error_not_a_vase():
    from msps_render.scene.primitives import PRIMITIVES, sample_primitive_params
    from msps_render.scene.sample import ShapeConfig
    from msps_render.scene.spec import ShapeSpec

    rng = np.random.default_rng(0)
    for name in PRIMITIVES:
        assert sample_primitive_params(name, rng)
    with pytest.raises(InputError, match="unknown primitive 'cone'"):
        sample_primitive_params("cone", rng)
    with pytest.raises(ValueError, match="unknown primitive 'tours'.*did you mean 'torus'"):
        ShapeSpec(kind="primitive", name="tours")
    with pytest.raises(ValueError, match="unknown primitive 'cone'"):
        ShapeConfig(source="primitive", primitives=["cone"])


def test_image_formats_registry(tmp_path):
    from msps_render.io.images import FORMATS, read_image
    from msps_render.scene.envmap import load_envmap

    assert {".exr", ".hdr", ".png", ".npy"} <= set(FORMATS)
    (tmp_path / "a.bmp").write_bytes(b"x")
    with pytest.raises(InputError, match=r"unsupported image format '\.bmp' \(use \.exr, \.hdr"):
        read_image(tmp_path / "a.bmp")
    (tmp_path / "a.png").write_bytes(b"x")
    with pytest.raises(InputError, match=r"unsupported environment map format '\.png' \(use \.exr or \.hdr\)"):
        load_envmap(str(tmp_path / "a.png"))
