"""Built-in measured materials (Neural-BRDF fits of MERL): weights, baking, precedence, held-out split."""
from __future__ import annotations

import numpy as np
import pytest

from msps_render.brdf import analytic, library, merl, nbrdf
from msps_render.scene import materials
from msps_render.errors import InputError

# brdf/nbrdf/README.md: (material, theta_h, theta_d, phi_d) -> RGB (1/sr)
REFERENCE = [
    ("blue-acrylic", 0.00, 0.00, 1.57, (16.4243, 13.5585, 13.6116)),
    ("blue-acrylic", 0.05, 0.30, 1.57, (0.0246878, 0.034526, 0.0611476)),
    ("blue-acrylic", 0.30, 0.50, 1.00, (0.00465074, 0.0126693, 0.0359559)),
    ("blue-acrylic", 0.80, 1.00, 2.00, (0.0033894, 0.0100063, 0.0283524)),
    ("gold-paint", 0.00, 0.00, 1.57, (0.350799, 0.246771, 0.134453)),
    ("gold-paint", 0.05, 0.30, 1.57, (0.295017, 0.210661, 0.113564)),
    ("gold-paint", 0.30, 0.50, 1.00, (0.0895255, 0.0571019, 0.0239505)),
    ("gold-paint", 0.80, 1.00, 2.00, (0.0633079, 0.0380797, 0.0172916)),
]


@pytest.fixture
def cache(monkeypatch, tmp_path):
    monkeypatch.setenv("MSPS_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("MSPS_MERL_DIR", raising=False)
    return tmp_path / "cache"


def test_eighty_materials_ship_and_all_are_in_the_catalogue():
    names = nbrdf.builtin_names()
    assert len(names) == 80
    cat = {e.name for e in library.load_catalogue().by_source("merl")}
    assert set(names) <= cat


@pytest.mark.parametrize("name,th,td,pd,rgb", REFERENCE)
def test_network_matches_reference_values(name, th, td, pd, rgb):
    """The README's values are float32 network outputs: agreement to 1e-4 relative (float32 rounding)."""
    w = nbrdf.read_weights(nbrdf.weights_path(name))
    np.testing.assert_allclose(nbrdf.evaluate(w, th, td, pd), rgb, rtol=1e-4)


@pytest.mark.parametrize("name", ["blue-acrylic", "gold-paint"])
def test_baked_table_matches_reference_values(cache, name):
    """A lookup in the baked table is the network at the bin centre: it differs from the reference
    point only by MERL's binning (theta_d bins are 1 deg wide, theta_h bins sqrt-spaced), measured
    <= 3.2 % on these points; 5 % leaves room without hiding a wrong axis or channel (those give
    factors, not percent)."""
    path = nbrdf.baked_table(nbrdf.weights_path(name))
    assert path.stat().st_size == merl.BAKED_FILE_BYTES and path.parent == cache / "brdf"  # float32 (issue 21)
    table = merl.read_table(path)
    assert table.n_negative == 0 and table.n_nonfinite == 0
    for n, th, td, pd, rgb in REFERENCE:
        if n != name:
            continue
        wi, wo = nbrdf.rusinkiewicz_dirs(th, td, pd)
        np.testing.assert_allclose(merl.lookup(table, wi, wo), rgb, rtol=0.05)
    # exact at a bin centre: the table stores the network's float32 value there
    th, td, pd = merl.bin_centres()
    i = (40, 30, 77)
    w = nbrdf.read_weights(nbrdf.weights_path(name))
    # rtol 1e-5: the bake evaluates the float32 network in large batches, this one point alone; BLAS
    # sums the products in another order for another batch shape (measured up to 1.25e-6, ~10 float32
    # ulps); a wrong bin, axis or channel gives errors of order 1, not 1e-5
    np.testing.assert_allclose(table.rgb[(slice(None), *i)], nbrdf.evaluate(w, th[i], td[i], pd[i]), rtol=1e-5)
    assert nbrdf.baked_table(nbrdf.weights_path(name)) == path  # cached: same file, not rebuilt


def test_auto_prefers_real_merl_file_of_same_name(cache, tmp_path):
    d = tmp_path / "merl"
    merl.write_merl(d / "white-paint.binary", analytic.make_table("lambert", {"albedo": [0.5] * 3}))
    pool = materials.measured_pool(library.load_catalogue(), "auto", merl_dir=d)
    names = {m.name for m in pool}
    assert "merl:white-paint" in names and "nbrdf:white-paint" not in names
    assert "nbrdf:gold-paint" in names and len(pool) == 80
    assert {m.name for m in materials.measured_pool(library.load_catalogue(), "merl", merl_dir=d)} == \
        {"merl:white-paint"}
    only_nbrdf = materials.measured_pool(library.load_catalogue(), "nbrdf", merl_dir=d)
    assert len(only_nbrdf) == 80 and all(m.name.startswith("nbrdf:") for m in only_nbrdf)


def test_the_kept_pool_follows_the_files_in_the_folder(cache, tmp_path):
    """`measured_pool` keeps its pool between frames while the files listed are the same: a MERL file
    added (or removed) mid-run changes the next frame's pool, as when it was rebuilt every frame."""
    d = tmp_path / "merl"
    d.mkdir()
    cat = library.load_catalogue()
    before = materials.measured_pool(cat, "auto", merl_dir=d)
    assert "nbrdf:white-paint" in {m.name for m in before}
    assert materials.measured_pool(cat, "auto", merl_dir=d) == before  # kept: the same specs
    merl.write_merl(d / "white-paint.binary", analytic.make_table("lambert", {"albedo": [0.5] * 3}))
    added = {m.name for m in materials.measured_pool(cat, "auto", merl_dir=d)}
    assert "merl:white-paint" in added and "nbrdf:white-paint" not in added
    (d / "white-paint.binary").unlink()
    assert materials.measured_pool(cat, "auto", merl_dir=d) == before


def test_holdout_split_keeps_test_materials_out_of_training(cache):
    test = library.held_out()
    assert len(test) == 16 and test <= set(nbrdf.builtin_names())
    seen_train, seen_test = set(), set()
    for s in range(40):
        for m in materials.sample_materials(np.random.default_rng(s), 3, merl_fraction=1.0, holdout="train"):
            seen_train.add(m.name.split(":", 1)[1])
        for m in materials.sample_materials(np.random.default_rng(s), 3, merl_fraction=1.0, holdout="test"):
            seen_test.add(m.name.split(":", 1)[1])
    assert not (seen_train & test) and len(seen_train) > 30
    assert seen_test <= test and len(seen_test) > 8


def test_resolve_nbrdf_material_bakes(cache):
    from msps_render.scene.spec import MaterialSpec

    m = MaterialSpec(name="nbrdf:gold-paint", kind="merl", params={"table": "nbrdf:gold-paint"})
    p = library.resolve_table(m)
    assert p.is_file() and p.name.startswith("nbrdf-gold-paint-")
    with pytest.raises(InputError, match="no built-in Neural-BRDF weights 'no-such.h5'"):
        library.resolve_table(MaterialSpec(name="nbrdf:x", kind="merl", params={"table": "nbrdf:no-such"}))


@pytest.mark.parametrize("content,msg", [
    (b"\x00" * 100, "cannot read as HDF5"),
    (None, "not a Neural-BRDF weights file"),
])
def test_bad_weights_files_are_one_clear_error(tmp_path, content, msg):
    p = tmp_path / "bad.h5"
    if content is None:
        import h5py

        with h5py.File(p, "w") as f:
            f["x"] = np.zeros(3)
    else:
        p.write_bytes(content)
    with pytest.raises(InputError, match=msg) as e:
        nbrdf.read_weights(p)
    assert str(p) in str(e.value)


def test_missing_split_file_is_a_clear_error(tmp_path):
    with pytest.raises(InputError, match="split file not found") as e:
        materials.sample_materials(np.random.default_rng(0), 2, merl_fraction=1.0, split_file=tmp_path / "nope.toml")
    assert "nope.toml" in str(e.value)


def test_nbrdf_material_renders(cache, rgb_variant):
    """A scene with a built-in measured material renders finite, non-zero radiance."""
    from msps_render import render_frame, sample_scene
    from msps_render.scene.sample import SceneConfig

    cfg = SceneConfig.model_validate({"materials": {"merl_fraction": 1.0, "min_count": 2, "max_count": 2},
                                      "camera": {"width": 32, "height": 32}, "integrator": {"spp": 4}})
    spec = sample_scene(cfg, np.random.default_rng(5))
    assert all(m.name.startswith("nbrdf:") for m in spec.materials)
    f = render_frame(spec, variant=rgb_variant)
    assert np.all(np.isfinite(f.image)) and f.image[f.mask > 0].mean() > 0.01
