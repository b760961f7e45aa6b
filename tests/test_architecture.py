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
                   "msps_render.models.predict")
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


def test_architecture_doc_names_only_what_exists():
    """docs/architecture.md cites files, functions and registries: each must exist in the code."""
    import ast
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    text = (root / "docs" / "architecture.md").read_text()
    defined: set[str] = set()
    source = ""
    for py in (root / "msps_render").rglob("*.py"):
        source += py.read_text()
        for node in ast.walk(ast.parse(py.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
                defined.add(node.name)
            elif isinstance(node, (ast.Assign, ast.AnnAssign)):
                for t in node.targets if isinstance(node, ast.Assign) else [node.target]:
                    if isinstance(t, ast.Name):
                        defined.add(t.id)
    missing = []
    for code in re.findall(r"`([^`]+)`", text):
        for path in re.findall(r"msps_render/[\w/]*(?:\.py|/)", code):
            if not (root / path).exists():
                missing.append(path)
        for file in re.findall(r"^(\w+\.py)$", code):
            if not list((root / "msps_render").rglob(file)):
                missing.append(file)
        call = re.match(r"^(?:[\w.]+\.)?(\w+)\(", code)  # `name(...)`, `module.name(...)`
        if call and call.group(1) not in defined and not re.search(rf"\.{call.group(1)}\(", source):
            missing.append(call.group(1))  # neither ours nor a library call the code makes
        if re.fullmatch(r"[A-Z][A-Z_]+|[A-Z][a-z]+[A-Z]\w*", code) and code not in defined and not re.search(rf"\b{code}\b", source):
            missing.append(code)  # registries, types, environment variables
        if (re.fullmatch(r"[a-z]+(?:_[a-z0-9]+)+", code) and code not in defined
                and not re.search(rf"\b{code}\b", source)):
            missing.append(code)  # bare function names
    assert not missing, f"docs/architecture.md names what the code does not have: {sorted(set(missing))}"


def test_import_graph_has_no_cycles():
    import importlib.util
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "scripts" / "import_graph.py"
    spec = importlib.util.spec_from_file_location("import_graph", script)
    graph = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(graph)
    m = graph.measure()
    assert m["module_cycles"] == [] and m["room_cycles"] == [], m["module_cycles"] + m["room_cycles"]
