"""Procedural shape families: determinism, valid closed outward meshes, sharp creases,
real concavities, clear config errors, and a tiny render per family."""
from __future__ import annotations

import numpy as np
import pytest

from msps_render.errors import InputError
from msps_render.scene import families as FM
from msps_render.scene.sample import SceneConfig, load_scene_config, sample_scene
from msps_render.scene.shapes import build_mesh
from msps_render.scene.spec import SceneSpec, ShapeSpec

FAMILIES = list(FM.SHAPE_FAMILIES)


def spec(name: str, seed: int, **kw) -> ShapeSpec:
    return ShapeSpec(kind="procedural", name=name, params={"seed": float(seed), "version": float(FM.FAMILY_VERSIONS[name])}, **kw)


def fresh(name: str, seed: int):
    FM._generate.cache_clear()
    return FM.procedural_mesh(name, {"seed": seed})


def directed_edges(f: np.ndarray) -> np.ndarray:
    return np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])


def weld(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Faces re-indexed onto unique positions (undoes crease splitting)."""
    _, inv = np.unique(np.round(v.astype(np.float64), 6), axis=0, return_inverse=True)
    return inv.reshape(-1)[f]


def face_normals(v, f):
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]).astype(np.float64)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def test_registry_and_unknown_family_errors(tmp_path):
    assert set(FAMILIES) == {"detailed", "creased", "concave", "thin", "composite"}
    with pytest.raises(Exception) as e:
        SceneConfig.model_validate({"shape": {"source": "procedural", "families": ["creasd"]}})
    msg = str(e.value)
    assert "unknown shape family 'creasd'" in msg and "did you mean 'creased'" in msg
    assert all(f in msg for f in FAMILIES)
    with pytest.raises(Exception, match="unknown shape family 'spot'"):
        ShapeSpec(kind="procedural", name="spot", params={"seed": 1.0})
    with pytest.raises(Exception, match="needs params.seed"):
        ShapeSpec(kind="procedural", name="thin")
    with pytest.raises(InputError, match="version 99"):
        build_mesh(ShapeSpec(kind="procedural", name="thin", params={"seed": 1.0, "version": 99.0}))
    p = tmp_path / "bad.toml"
    p.write_text('[scene.shape]\nsource = "procedural"\nfamilies = ["thin", "blobbyy"]\n')
    with pytest.raises(InputError, match="bad.toml.*unknown shape family 'blobbyy'"):
        load_scene_config(p)
    p.write_text('[scene.shape]\nsource = "procedural"\nfamilies = ["creased", "thin"]\n')
    assert load_scene_config(p).shape.families == ["creased", "thin"]


def test_mesh_is_a_deterministic_function_of_the_spec():
    cfg = SceneConfig.model_validate({"shape": {"source": "procedural"}})
    a = sample_scene(cfg, np.random.default_rng(5))
    assert a == sample_scene(cfg, np.random.default_rng(5))
    stored = SceneSpec.from_json(a.to_json())  # what a shard keeps
    m1 = build_mesh(a.shape)
    FM._generate.cache_clear()
    m2 = build_mesh(stored.shape)
    for x, y in zip((m1.vertices, m1.faces, m1.normals), (m2.vertices, m2.faces, m2.normals)):
        np.testing.assert_array_equal(x, y)
    for name in FAMILIES:
        v1, f1 = fresh(name, 11)
        v2, f2 = fresh(name, 11)
        v3, _ = fresh(name, 12)
        np.testing.assert_array_equal(v1, v2)
        np.testing.assert_array_equal(f1, f2)
        assert v1.shape != v3.shape or not np.array_equal(v1, v3)


def test_mixed_draws_every_family_and_a_pool_repeats_shapes():
    cfg = SceneConfig.model_validate({"shape": {"source": "procedural", "families": ["mixed"]}})
    rng = np.random.default_rng(0)
    names = {sample_scene(cfg, rng).shape.name for _ in range(40)}
    assert names == set(FAMILIES)
    pool = SceneConfig.model_validate({"shape": {"source": "procedural", "n_shapes": 3}})
    rng = np.random.default_rng(1)
    shapes = {(s.name, s.params["seed"]) for s in (sample_scene(pool, rng).shape for _ in range(20))}
    assert len(shapes) <= 3


@pytest.mark.parametrize("name", FAMILIES)
def test_every_family_builds_closed_outward_valid_meshes(name):
    for seed in range(4):
        v, f = fresh(name, seed)
        assert np.isfinite(v).all() and len(f) <= 200_000
        area = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
        assert (area > 1e-10).all()
        # closed + consistently wound: every directed edge once, and its reverse once
        e = directed_edges(f)
        key = e[:, 0] * len(v) + e[:, 1]
        assert len(np.unique(key)) == len(key)
        assert np.isin(e[:, 1] * len(v) + e[:, 0], key).all()
        lab = FM.components(f, len(v))
        for c in np.unique(lab):
            assert FM.signed_volume(v, f[lab == c]) > 0, f"{name} seed {seed} component {c} wound inward"
        m = build_mesh(spec(name, seed, radius=0.9))
        assert np.isfinite(m.vertices).all() and np.isfinite(m.normals).all()
        np.testing.assert_allclose(np.linalg.norm(m.normals, axis=1), 1.0, atol=1e-5)
        assert np.linalg.norm(m.vertices, axis=1).max() == pytest.approx(0.9, abs=1e-5)
        # vertex normals agree with the faces they shade (outward)
        fn = face_normals(m.vertices, m.faces)
        assert (np.einsum("ij,ij->i", fn, m.normals[m.faces].mean(1)) > 0).mean() > 0.99


def test_creased_family_keeps_sharp_edges_sharp():
    n_sharp = 0
    for seed in range(6):
        m = build_mesh(spec("creased", seed))
        wf = weld(m.vertices, m.faces)
        fn = face_normals(m.vertices, m.faces)
        e = directed_edges(wf)
        corner = np.concatenate([m.faces[:, [0, 1]], m.faces[:, [1, 2]], m.faces[:, [2, 0]]])
        face = np.tile(np.arange(len(wf)), 3)
        # pair each directed edge with its reverse (the neighbouring face)
        key = e[:, 0] * (wf.max() + 1) + e[:, 1]
        rkey = e[:, 1] * (wf.max() + 1) + e[:, 0]
        order = np.argsort(key)
        j = order[np.searchsorted(key[order], rkey)]
        assert (key[j] == rkey).all()
        dihedral = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", fn[face], fn[face[j]]), -1, 1)))
        sharp = np.flatnonzero(dihedral > 60)
        assert len(sharp), f"seed {seed}: no edge sharper than 60 degrees"
        n_sharp += len(sharp)
        # at both ends of a sharp edge the two faces use different vertex normals, each close to
        # its own face's normal (not averaged across the crease)
        for i in sharp:
            for end in (0, 1):
                n_here = m.normals[corner[i, end]]
                n_there = m.normals[corner[j[i], 1 - end]]
                ang = np.degrees(np.arccos(np.clip(np.dot(n_here, n_there), -1, 1)))
                assert ang > 0.5 * dihedral[i]
                assert np.dot(n_here, fn[face[i]]) > np.cos(np.radians(45))
    assert n_sharp > 10


def test_smooth_families_stay_smooth():
    """Crease splitting must not facet finely tessellated smooth surfaces."""
    for name in ("detailed", "thin"):
        m = build_mesh(spec(name, 3))
        v, _ = FM.procedural_mesh(name, {"seed": 3})
        assert len(m.vertices) < 1.1 * len(v)


def test_concave_family_is_clearly_non_convex():
    from scipy.spatial import ConvexHull

    ratios = []
    for seed in range(8):
        v, f = fresh("concave", seed)
        ratios.append(FM.signed_volume(v, f) / ConvexHull(v).volume)
        assert 0 < ratios[-1] < 0.92, f"seed {seed}: volume / hull volume = {ratios[-1]:.2f}"
    assert np.median(ratios) < 0.75, ratios


def test_crease_normals_on_a_box_and_a_sphere():
    v, f = FM._box((1.0, 2.0, 3.0))
    nv, nf, n = FM.crease_normals(v, f)
    assert len(nv) == 24  # each cube corner split in three
    fn = face_normals(nv, nf)
    np.testing.assert_allclose(n[nf], np.repeat(fn[:, None], 3, 1), atol=1e-12)
    d, sf = FM._sphere(3)
    sv, sff, sn = FM.crease_normals(d, sf)
    assert len(sv) == len(d)  # nothing to split
    np.testing.assert_array_equal(sv[sff], d[sf])
    np.testing.assert_allclose(sn[sff], FM._vnormals(d, sf)[sf], atol=1e-12)


@pytest.mark.parametrize("name", FAMILIES)
def test_each_family_renders(name, rgb_variant):
    from msps_render.render import render_frame

    cfg = SceneConfig.model_validate({"shape": {"source": "procedural", "families": [name]},
                                      "camera": {"width": 32, "height": 32}, "integrator": {"spp": 2}})
    s = sample_scene(cfg, np.random.default_rng(3))
    fr = render_frame(s, variant=rgb_variant)
    assert np.isfinite(fr.image).all() and fr.image[fr.mask].sum() > 0
    n = fr.normal[fr.mask]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-4)
    assert (n[:, 2] >= -1e-6).all()  # facing the camera
    # the mask covers the object: project area-weighted surface samples to pixels
    m = build_mesh(s.shape)
    rng = np.random.default_rng(0)
    a, b, c = (m.vertices[m.faces[:, k]].astype(np.float64) for k in range(3))
    area = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    idx = rng.choice(len(area), 20000, p=area / area.sum())
    u, w = rng.random((2, 20000, 1))
    flip = (u + w) > 1
    u, w = np.where(flip, 1 - u, u), np.where(flip, 1 - w, w)
    p = a[idx] + u * (b[idx] - a[idx]) + w * (c[idx] - a[idx])
    ext, W = s.camera.extent, s.camera.width
    col = np.clip(((p[:, 0] / ext + 1) / 2 * W).astype(int), 0, W - 1)
    row = np.clip(((1 - p[:, 1] / ext) / 2 * W).astype(int), 0, W - 1)
    foot = np.zeros_like(fr.mask)
    foot[row, col] = True
    assert (fr.mask & foot).sum() >= 0.8 * fr.mask.sum() and fr.mask.sum() >= 0.6 * foot.sum()
    assert not (fr.mask & ~foot).any()
