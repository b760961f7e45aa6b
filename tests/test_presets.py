"""Every preset in scenes/ validates, and the paper presets say what the paper says."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from msps_render.errors import InputError
from msps_render.pipeline.config import PRESET_DIR, load_config

PRESETS = sorted(p.stem for p in Path(PRESET_DIR).glob("*.toml"))


def test_presets_exist():
    assert {"demo", "paper-train", "paper-val", "paper-test"} <= set(PRESETS)


@pytest.mark.parametrize("name", PRESETS)
def test_preset_validates(name):
    cfg = load_config(name)
    assert cfg.dataset.patches.size <= cfg.scene.camera.width


def test_paper_presets_match_the_paper():
    tr, va = load_config("paper-train"), load_config("paper-val")
    for c in (tr, va):
        assert c.scene.lights.slant_deg == 30 and c.scene.lights.tilts_deg == [0, 120, 240]
        np.testing.assert_allclose(c.scene.lights.crosstalk, np.full((3, 3), 0.04) + 0.88 * np.eye(3))
        assert c.dataset.patches.size == 40 and not c.scene.environment.enabled
        assert c.scene.materials.min_count >= 2
    assert tr.scene.shape.n_shapes == 9 and va.scene.shape.n_shapes == 1
    assert tr.scene.shape.pool_seed != va.scene.shape.pool_seed  # validation shape unseen in training
    assert load_config("paper-test").dataset.storage.store_frames


TEST_MESH_DIR = "$MSPS_TEST_DATA/meshes"
UNSEEN = ("unseen-test", "unseen-test-grey", "unseen-robust-env", "unseen-robust-slant",
          "unseen-test-colour", "unseen-test-texture", "unseen-test-smooth", "unseen-test-patches",
          "unseen-rig-crosstalk", "unseen-rig-jitter", "diligent-rig")
ANALYTIC_UNSEEN = ("unseen-test-colour", "unseen-test-texture", "unseen-test-smooth", "unseen-test-patches",
                   "unseen-rig-crosstalk", "unseen-rig-jitter")


@pytest.mark.parametrize("name", [p for p in PRESETS if p not in UNSEEN])
def test_no_training_or_validation_preset_sees_test_objects(name):
    """The test meshes and the held-out measured materials (brdf/split.toml) stay out of every
    corpus that is not an unseen-object test set; the test sets draw only held-out materials."""
    cfg = load_config(name)
    assert not any("MSPS_TEST_DATA" in m or "shared/data" in m for m in cfg.scene.shape.meshes)
    # test sets of unseen shapes may draw the held-out materials; every other corpus must not
    assert cfg.scene.materials.holdout == ("test" if name == "paper-test" else "train")
    env = cfg.scene.environment
    assert not (env.enabled and ("MSPS_TEST_DATA" in env.source or "shared/data" in env.source))  # test-only map


def test_unseen_presets_find_the_test_assets_from_one_setting(monkeypatch, tmp_path):
    """The unseen-* presets name $MSPS_TEST_DATA/meshes/... (and envmaps/): unset, one line names the
    variable and what to set it to; set, they work from any working directory."""
    from msps_render.scene.envmap import load_envmap

    cfg = load_config("unseen-robust-env")
    monkeypatch.delenv("MSPS_TEST_DATA", raising=False)
    with pytest.raises(InputError, match=r"^\$MSPS_TEST_DATA/meshes/ajc_spot\.obj: environment variable MSPS_TEST_DATA "
                                         r"is not set .*export MSPS_TEST_DATA=FOLDER holding meshes/ and envmaps/"):
        cfg.scene.shape.mesh_paths()
    with pytest.raises(InputError, match=r"^\$MSPS_TEST_DATA/envmaps/venice_sunset_1k\.exr: environment variable"):
        load_envmap(cfg.scene.environment.source)
    monkeypatch.setenv("MSPS_TEST_DATA", str(tmp_path))
    with pytest.raises(InputError, match=rf"^{tmp_path}/meshes/ajc_spot\.obj: no mesh file matches this path/pattern "
                                         r"\(from '\$MSPS_TEST_DATA/meshes/ajc_spot\.obj' in the config\)"):
        cfg.scene.shape.mesh_paths()
    shared = Path(__file__).resolve().parents[2] / "shared" / "data"
    if (shared / "meshes").is_dir():
        monkeypatch.setenv("MSPS_TEST_DATA", str(shared))
        monkeypatch.chdir(tmp_path)  # not the checkout: nothing is read relative to the working directory
        assert [Path(p).name for p in cfg.scene.shape.mesh_paths()] == [
            "ajc_spot.obj", "ajc_cow.obj", "ajc_teapot.obj", "ajc_suzanne.obj", "ajc_beetle.obj", "ajc_fandisk.obj",
            "scivi_feline.obj"]
        assert load_envmap(cfg.scene.environment.source).shape == (512, 1024, 3)


@pytest.mark.parametrize("name", UNSEEN)
def test_unseen_presets_use_test_meshes_and_held_out_materials(name):
    cfg = load_config(name)
    assert cfg.scene.shape.source == "mesh" and cfg.scene.shape.mesh_order == "cycle"
    assert len(cfg.scene.shape.meshes) == 7 and all(TEST_MESH_DIR in m for m in cfg.scene.shape.meshes)
    assert cfg.scene.camera.width == cfg.scene.camera.height == 256
    assert cfg.dataset.storage.store_frames
    n_frames = cfg.dataset.n_shards * cfg.dataset.frames_per_shard
    assert n_frames % 7 == 0  # every mesh gets the same number of frames
    if name == "unseen-test-grey":
        assert cfg.scene.materials.families == ["grey"] and cfg.scene.materials.merl_fraction == 0
        assert cfg.scene.materials.min_count == cfg.scene.materials.max_count == 1
    elif name in ANALYTIC_UNSEEN:  # colour tests: one full-gamut Lambertian material (no measured ones)
        assert cfg.scene.materials.families == ["diffuse"] and cfg.scene.materials.merl_fraction == 0
        assert cfg.scene.materials.albedo == "full" and cfg.scene.materials.max_count == 1
        assert cfg.dataset.seed == load_config("unseen-test-grey").dataset.seed  # the grey test's poses
        if name in ("unseen-test-smooth", "unseen-test-patches"):  # one texture kind each (issue 20's targets)
            assert cfg.scene.materials.texture.kinds == [name.rsplit("-", 1)[1]]
            assert cfg.scene.materials.texture.fraction == 1.0
    else:
        assert cfg.scene.materials.holdout == "test" and cfg.scene.materials.merl_fraction == 1.0


def test_training_presets_are_measured_detailed_and_at_test_scale():
    tr, va, rb = load_config("train"), load_config("val"), load_config("train-robust")
    for c in (tr, va, rb):
        assert c.scene.shape.source == "procedural" and c.scene.materials.merl_fraction >= 0.5
        assert c.scene.camera.width == 256 and c.dataset.patches.size == 40
    assert rb.scene.environment.enabled and rb.sensor is not None and rb.scene.lights.slant_range_deg
    ac = load_config("train-achromatic")  # grey-heavy supplement, same robust conditions
    assert len({tr.dataset.seed, va.dataset.seed, rb.dataset.seed, ac.dataset.seed}) == 4
    assert ac.scene.shape.source == "procedural" and ac.scene.camera.width == 256
    assert ac.scene.materials.families == ["grey"] and ac.scene.materials.merl_fraction <= 0.25
    assert ac.scene.lights == rb.scene.lights and ac.scene.environment == rb.scene.environment


def test_mesh_cycle_gives_every_mesh_the_same_frames(tmp_path):
    """mesh_order = "cycle": frame k of a condition gets mesh k mod N, whatever the rng draws."""
    from msps_render.scene.sample import SceneConfig, sample_scene

    meshes = []
    for i in range(3):
        p = tmp_path / f"m{i}.obj"
        p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
        meshes.append(str(p))
    cfg = SceneConfig.model_validate({"shape": {"source": "mesh", "meshes": meshes, "mesh_order": "cycle"}})
    names = [sample_scene(cfg, np.random.default_rng(k), frame_index=k).shape.name for k in range(9)]
    assert names == ["m0", "m1", "m2"] * 3
    rnd = SceneConfig.model_validate({"shape": {"source": "mesh", "meshes": meshes}})
    drawn = [sample_scene(rnd, np.random.default_rng(k), frame_index=k).shape.name for k in range(30)]
    assert set(drawn) == {"m0", "m1", "m2"} and drawn[:9] != names
