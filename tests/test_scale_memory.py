"""Issue 21, memory: a bounded per-process table cache (pixels unchanged) and the float32 disk cache."""
from __future__ import annotations

import numpy as np
import pytest

from msps_render.brdf import merl, nbrdf
from msps_render.errors import InputError

MIB = 1 << 20
TABLE_MIB = 3 * merl.N_BINS * 4 / MIB  # 16.7 MiB: one table on the device


def _lobe_table(k: int) -> np.ndarray:
    """A distinct, non-trivial table per k: a diffuse base plus a theta_h lobe of its own width/colour,
    so a scene rendered with another material's table gives other pixels."""
    ih = np.arange(merl.RES_THETA_H, dtype=np.float64)[:, None, None]
    id_ = np.arange(merl.RES_THETA_D, dtype=np.float64)[None, :, None]
    rgb = np.empty((3, *merl.DIMS))
    for c in range(3):
        base = 0.05 + 0.08 * ((k + c) % 4)
        rgb[c] = base + (2.0 + k) * np.exp(-ih / (2.0 + 3 * k + c)) * (1.0 - id_ / 180.0)
    return rgb


@pytest.fixture
def cache(monkeypatch, tmp_path):
    monkeypatch.setenv("MSPS_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("MSPS_MERL_DIR", raising=False)
    return tmp_path / "cache" / "brdf"


@pytest.fixture
def table_cache(monkeypatch):
    """`table_cache(k)`: set MSPS_TABLE_CACHE=k and start from an empty table cache (restored after)."""
    from msps_render.render import merl_bsdf

    def set_size(k: int):
        monkeypatch.setenv(merl_bsdf.TABLE_CACHE_ENV, str(k))
        merl_bsdf.device_table.cache_clear()
        return merl_bsdf.device_table

    yield set_size
    merl_bsdf.device_table.cache_clear()


def _rss_mib() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def test_table_cache_holds_at_most_k_tables_and_frees_evicted_ones(tmp_path, rgb_variant, table_cache):
    """Six tables through a cache of 2: it keeps 2 and the process keeps ~2 tables' memory; the same six
    through a cache of 16 keep all six (~100 MiB more), so the RSS measure does see retained tables."""
    import drjit as dr

    from msps_render.render.memory import release_frame_memory

    paths = [str(merl.write_baked(tmp_path / f"t{k}.npy", _lobe_table(k))) for k in range(7)]
    table_cache(1)(paths.pop(), rgb_variant)  # warm-up: scipy import, first drjit arrays (~40 MiB once)
    growth = {}
    for k in (2, 16):
        dt = table_cache(k)
        release_frame_memory()
        before = _rss_mib()
        for p in paths:
            data, _, _ = dt(p, rgb_variant)
            dr.eval(dr.sum(data))  # read every entry, as renders do: mapped pages become resident
            del data
        release_frame_memory()
        growth[k] = _rss_mib() - before
        info = dt.cache_info()
        assert info.currsize == min(k, 6) and info.maxsize == k and info.misses == 6
        dt.cache_clear()
    # k=2: two tables (33 MiB) kept; 2.8 tables' allowance for allocator slack, well below the 4 more
    # tables (67 MiB) an eviction that leaked would add.  k=16: >= 5.5 of the 6 tables stay resident.
    assert growth[2] <= 2.8 * TABLE_MIB, growth
    assert growth[16] >= 5.5 * TABLE_MIB, growth


def test_table_cache_hits_and_lru_order(tmp_path, rgb_variant, table_cache):
    paths = [str(merl.write_baked(tmp_path / f"t{k}.npy", _lobe_table(k))) for k in range(3)]
    dt = table_cache(2)
    a = dt(paths[0], rgb_variant)
    dt(paths[1], rgb_variant)
    assert dt(paths[0], rgb_variant) is a  # hit: the same array, not a reload
    dt(paths[2], rgb_variant)  # evicts paths[1], the least recently used
    assert dt(paths[0], rgb_variant) is a
    info = dt.cache_info()
    assert (info.hits, info.misses, info.currsize) == (2, 3, 2)


def test_bad_table_cache_size_is_one_line(monkeypatch, table_cache):
    from msps_render.render import merl_bsdf

    table_cache(4)
    for bad in ("0", "-3", "eight"):
        monkeypatch.setenv(merl_bsdf.TABLE_CACHE_ENV, bad)
        with pytest.raises(InputError, match=r"MSPS_TABLE_CACHE: must be a whole number >= 1"):
            merl_bsdf.table_cache_size()


def _measured_scenes(tmp_path, n_materials: int, n_scenes: int):
    """Small scenes (24x24, 4 spp) whose 3 materials are all measured, drawn from `n_materials`
    distinct tables (real MERL files in a folder named by the catalogue)."""
    from msps_render.scene.sample import MaterialsConfig, SceneConfig, sample_scene
    from msps_render.scene.spec import CameraSpec, IntegratorSpec

    d = tmp_path / "merl"
    names = [f"lobe-{k}" for k in range(n_materials)]
    for k, n in enumerate(names):
        merl.write_merl(d / f"{n}.binary", _lobe_table(k))
    cat = tmp_path / "catalogue.toml"
    cat.write_text("version = 1\n" + "".join(f'\n[[material]]\nname = "{n}"\nsource = "merl:{n}.binary"\n'
                                             for n in names))
    cfg = SceneConfig(materials=MaterialsConfig(min_count=3, max_count=3, merl_fraction=1.0, catalogue=str(cat),
                                                merl_dir=str(d), measured="merl"),
                      camera=CameraSpec(width=24, height=24), integrator=IntegratorSpec(spp=4, max_depth=3))
    return [sample_scene(cfg, np.random.default_rng(s), seed=s) for s in range(n_scenes)]


def test_pixels_identical_with_cache_of_one_and_a_large_cache(tmp_path, rgb_variant, table_cache):
    """Four tables, scenes of three measured materials each: with a cache of 1 every scene reloads
    evicted tables; the images, normals and masks must equal those of a cache that keeps all four,
    byte for byte (the reloaded table is the same float32 data)."""
    from msps_render.render import render_frame

    scenes = _measured_scenes(tmp_path, 4, 3)
    used = {m.params["table"] for s in scenes for m in s.materials}
    assert len(used) == 4  # the scene set uses more materials than the small cache holds
    out = {}
    for k in (1, 64):
        dt = table_cache(k)
        out[k] = [render_frame(s, variant=rgb_variant, threads=1) for s in scenes]
        out[f"misses{k}"] = dt.cache_info().misses
    assert out["misses64"] == 4 and out["misses1"] > 4  # k=1 really evicted and reloaded
    for a, b in zip(out[1], out[64]):
        for name in ("image", "normal", "mask"):
            x, y = getattr(a, name), getattr(b, name)
            assert x.tobytes() == y.tobytes(), name
        assert float(np.abs(a.image).max()) > 0  # something was rendered


# ------------------------------------------------------------------ disk cache
@pytest.fixture(scope="module")
def gold_paint():
    """(weights, the float64 table `make_table` bakes from them): baked once for the module."""
    w = nbrdf.read_weights(nbrdf.weights_path("gold-paint"))
    return w, nbrdf.make_table(w)


@pytest.mark.slow
def test_bake_row_by_row_is_bit_identical_to_the_whole_grid_bake(gold_paint):
    """`make_table` now evaluates one theta_h row at a time (peak ~10 MiB instead of ~430 MiB of
    activations): the same float32 products and sums per bin, so exactly the table msps <= issue 21
    baked from the whole bin grid at once (and wrote to the v1 caches)."""
    w, table = gold_paint
    whole = np.ascontiguousarray(np.moveaxis(nbrdf.evaluate(w, *merl.bin_centres()), -1, 0), dtype=np.float64)
    assert np.array_equal(table, whole)


@pytest.fixture
def bakes(monkeypatch, gold_paint):
    """Counts `nbrdf.make_table` calls (bakes), answering with the module's real bake instead of
    baking again (~1 s idle, up to a minute on the shared machine)."""
    calls = []

    def make_table(w):
        calls.append(w.path)
        assert w.digest == gold_paint[0].digest
        return gold_paint[1]

    monkeypatch.setattr(nbrdf, "make_table", make_table)
    return calls


def _v1_file(cache, gold_paint):
    """What msps <= issue 21 wrote: the float64 MERL table `nbrdf-<name>-<digest>-v1.binary`."""
    w, table = gold_paint
    return merl.write_merl(cache / f"nbrdf-gold-paint-{w.digest}-v1.binary", table)


def test_baked_table_is_float32_and_half_the_disk(cache, gold_paint, bakes):
    p = nbrdf.baked_table(nbrdf.weights_path("gold-paint"))
    assert len(bakes) == 1
    assert p.name == f"nbrdf-gold-paint-{gold_paint[0].digest}-v2.npy" and p.parent == cache
    assert p.stat().st_size == merl.BAKED_FILE_BYTES == 17_496_128  # vs merl.FILE_BYTES = 34,992,012
    t = merl.read_table(p)
    assert t.rgb.dtype == np.float32 and t.rgb.shape == (3, *merl.DIMS)
    # the network computes in float32: the float32 file holds exactly what was computed
    assert np.array_equal(t.rgb, gold_paint[1].astype(np.float32))
    assert np.array_equal(merl.map_baked(p), t.rgb.reshape(3, -1).T)  # the renderer's interleaved layout


def test_old_float64_cache_is_read_and_gives_the_same_table(cache, gold_paint, bakes):
    """A v1 cache entry is converted (not re-baked) into the v2 file, bit-identical to the float32 table
    the renderer loaded from v1 before; the v1 file is left untouched for older versions."""
    old = _v1_file(cache, gold_paint)
    before = merl.read_merl(old, dtype=np.float32).rgb  # what the renderer loaded from the old cache
    old_bytes = old.read_bytes()
    new = nbrdf.baked_table(nbrdf.weights_path("gold-paint"))
    assert bakes == [] and new.name.endswith("-v2.npy")
    assert np.array_equal(merl.read_table(new).rgb, before)
    assert np.array_equal(before, gold_paint[1].astype(np.float32))
    assert old.read_bytes() == old_bytes
    assert nbrdf.baked_table(nbrdf.weights_path("gold-paint")) == new and bakes == []  # now a plain hit


def test_damaged_old_cache_is_rebuilt_cleanly(cache, gold_paint, bakes):
    old = _v1_file(cache, gold_paint)
    with open(old, "r+b") as fh:
        fh.truncate(1000)
    new = nbrdf.baked_table(nbrdf.weights_path("gold-paint"))
    assert len(bakes) == 1  # baked afresh
    assert np.array_equal(merl.read_table(new).rgb, gold_paint[1].astype(np.float32))
    assert sorted(p.name for p in cache.iterdir()) == sorted([old.name, new.name])  # no temporaries left


def test_damaged_baked_table_is_one_line_naming_the_file(tmp_path):
    p = merl.write_baked(tmp_path / "t.npy", _lobe_table(0))
    with open(p, "r+b") as fh:
        fh.truncate(merl.BAKED_FILE_BYTES - 4)
    with pytest.raises(InputError, match=r"t\.npy: truncated baked table: 17496124 bytes, expected 17496128"):
        merl.read_table(p)
    q = tmp_path / "q.npy"
    np.save(q, np.zeros((3, 4), np.float32))
    with pytest.raises(InputError, match=r"q\.npy: not a baked BRDF table: float32 array of shape \(3, 4\)"):
        merl.read_table(q)
