"""Material library: catalogue, MERL discovery, sampling (distinct, seeded, mixed), clear errors."""
from __future__ import annotations

import logging

import numpy as np
import pytest

from msps_render.brdf import analytic, library, merl
from msps_render.scene import materials
from msps_render.errors import InputError


@pytest.fixture
def no_merl_env(monkeypatch, tmp_path):
    monkeypatch.delenv("MSPS_MERL_DIR", raising=False)
    monkeypatch.setenv("MSPS_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("MSPS_BRDF_DIR", str(library.REPO_BRDF_DIR))  # the built-in nbrdf weights stay
    monkeypatch.setattr(library, "REPO_BRDF_DIR", tmp_path / "repo-brdf")  # no files dropped by a user


@pytest.fixture(scope="module")
def merl_dir(tmp_path_factory):
    """Two files named like real MERL materials (Lambertian content: only the names matter here)."""
    d = tmp_path_factory.mktemp("merl")
    for name, albedo in (("white-paint", 0.8), ("blue-fabric", 0.3)):
        merl.write_merl(d / f"{name}.binary", analytic.make_table("lambert", {"albedo": [albedo] * 3}))
    return d


def test_default_catalogue_lists_merl_generated_and_analytic():
    cat = library.load_catalogue()
    merl_names = [e.name for e in cat.by_source("merl")]
    assert len(merl_names) == 100 and "blue-metallic-paint" in merl_names
    assert all(e.target == f"{e.name}.binary" for e in cat.by_source("merl"))
    gen = cat.by_source("generated")
    assert len(gen) >= 8 and {e.target for e in gen} <= set(analytic.MODELS)
    for e in gen:  # every generated entry's params are valid for its model
        analytic.evaluate(e.target, e.params, np.array([[0.0, 0.0, 1.0]]), np.array([[0.0, 0.6, 0.8]]))
    assert {e.target for e in cat.by_source("analytic")} == {"diffuse", "plastic", "roughplastic",
                                                             "roughconductor", "principled"}


def test_without_measured_materials_there_is_no_silent_fallback(no_merl_env, monkeypatch, tmp_path):
    """No MERL files and no built-in weights: an error, not generated stand-ins."""
    monkeypatch.setenv("MSPS_BRDF_DIR", str(tmp_path / "empty"))
    with pytest.raises(InputError, match="no measured materials available"):
        materials.sample_materials(np.random.default_rng(0), 4, merl_fraction=1.0)


def test_generated_tables_only_when_asked_and_named(no_merl_env, caplog):
    with caplog.at_level(logging.INFO, logger="msps_render.scene.materials"):
        mats = materials.sample_materials(np.random.default_rng(0), 4, merl_fraction=1.0, measured="generated")
    assert len(mats) == 4 and all(m.kind == "merl" for m in mats)
    assert all(m.name.startswith("generated:") for m in mats)
    assert len({m.name for m in mats}) == 4
    assert "materials: generated:" in caplog.text
    path = library.resolve_table(mats[0])
    assert path.is_file() and path.stat().st_size == merl.FILE_BYTES
    assert library.resolve_table(mats[0]) == path  # cached, same file


def test_real_merl_files_are_found_and_preferred(no_merl_env, merl_dir):
    mats = materials.sample_materials(np.random.default_rng(1), 2, merl_fraction=1.0, merl_dir=str(merl_dir),
                                    measured="merl")
    assert sorted(m.name for m in mats) == ["merl:blue-fabric", "merl:white-paint"]
    for m in mats:
        assert library.resolve_table(m) == (merl_dir / f"{m.name[5:]}.binary").resolve()
    # asking for more measured materials than files: the rest are analytic, still distinct
    mats = materials.sample_materials(np.random.default_rng(1), 5, merl_fraction=1.0, merl_dir=str(merl_dir),
                                    measured="merl")
    assert sum(m.kind == "merl" for m in mats) == 2 and len({m.name for m in mats}) == 5


def test_env_var_merl_dir_and_catalogue_ids(no_merl_env, merl_dir, monkeypatch):
    monkeypatch.setenv("MSPS_MERL_DIR", str(merl_dir))
    mats = materials.sample_materials(np.random.default_rng(2), 1, merl_fraction=1.0, measured="merl")
    assert mats[0].name.startswith("merl:")
    from msps_render.scene.spec import MaterialSpec

    by_id = MaterialSpec(name="merl:white-paint", kind="merl", params={"table": "merl:white-paint"})
    assert library.resolve_table(by_id) == (merl_dir / "white-paint.binary").resolve()


def test_missing_merl_dir_is_a_clear_error(no_merl_env, tmp_path, monkeypatch):
    missing = tmp_path / "nowhere"
    with pytest.raises(InputError) as e:
        materials.sample_materials(np.random.default_rng(0), 2, merl_fraction=0.5, merl_dir=str(missing))
    msg = str(e.value)
    assert msg.startswith(str(missing)) and "does not exist" in msg and "searched:" in msg
    assert str(library.REPO_BRDF_DIR / "merl") in msg and "\n" not in msg
    empty = tmp_path / "empty"
    empty.mkdir()
    monkeypatch.setenv("MSPS_MERL_DIR", str(empty))
    with pytest.raises(InputError, match="no MERL .binary files of the catalogue found; searched: .*empty"):
        materials.sample_materials(np.random.default_rng(0), 2, merl_fraction=0.5)
    from msps_render.scene.spec import MaterialSpec

    with pytest.raises(InputError, match="MERL file not found; searched"):
        library.resolve_table(MaterialSpec(name="x", kind="merl", params={"table": "merl:steel"}))
    with pytest.raises(InputError, match="not found"):
        library.resolve_table(MaterialSpec(name="x", kind="merl", params={"table": str(tmp_path / "a.binary")}))


def test_sampling_is_seeded_distinct_and_mixed(no_merl_env):
    a = materials.sample_materials(np.random.default_rng(42), 3, merl_fraction=0.5)
    b = materials.sample_materials(np.random.default_rng(42), 3, merl_fraction=0.5)
    assert a == b
    kinds = []
    for seed in range(200):
        mats = materials.sample_materials(np.random.default_rng(seed), 3, merl_fraction=0.5)
        assert len(mats) == 3 and len({m.name for m in mats}) == 3
        kinds += [m.kind == "merl" for m in mats]
    assert 0.4 < np.mean(kinds) < 0.6
    none = materials.sample_materials(np.random.default_rng(0), 3, merl_fraction=0.0, families=["diffuse", "plastic"])
    assert all(m.kind in ("diffuse", "plastic") for m in none)


def test_scene_sampler_uses_the_library(no_merl_env):
    from msps_render.scene.sample import MaterialsConfig, SceneConfig, sample_scene

    cfg = SceneConfig(materials=MaterialsConfig(merl_fraction=0.6, min_count=2, max_count=3))
    spec = sample_scene(cfg, np.random.default_rng(3))
    assert len(spec.materials) >= 2 and spec.split.n_parts == len(spec.materials)
    assert len({m.name for m in spec.materials}) == len(spec.materials)
    again = type(spec).from_json(spec.to_json())
    assert again == spec  # merl materials stay JSON-serialisable


@pytest.mark.parametrize("text,expect", [
    ('[[material]]\nname = "a"\nsource = "merl"\n', "needs name"),
    ('[[material]]\nname = "a"\nsource = "bogus:x"\n', "unknown source kind 'bogus'"),
    ('[[material]]\nname = "a"\nsource = "generated:phong"\n', "unknown model 'phong'"),
    ('[[material]]\nname = "a"\nsource = "analytic:velvet"\n', "unknown family 'velvet'"),
    ('[[material]]\nname = "a"\nsource = "analytic:diffuse"\n[[material]]\nname = "a"\nsource = "analytic:plastic"\n',
     "duplicate material name 'a'"),
    ('[[material]]\nname = "a"\nsource = "analytic:diffuse"\ncolour = 1\n', "unknown key 'material.0.colour'"),
    ("materials = 3\n", "unknown key 'materials' (did you mean 'material'?)"),
    ("version = 1\n", "lists no [[material]]"),
    ("[[material]\n", "not valid TOML"),
])
def test_bad_catalogue_is_a_clear_error(tmp_path, text, expect):
    p = tmp_path / f"cat{abs(hash(text))}.toml"
    p.write_text(text)
    with pytest.raises(InputError) as e:
        library.load_catalogue(p)
    assert str(e.value).startswith(str(p)) and expect in str(e.value)
