"""SceneSpec as data: sampling determinism, validation, JSON round trip, shapes, parts."""
from __future__ import annotations

import json

import numpy as np
import pytest

from msps_render.errors import InputError
from msps_render.scene import shapes as S
from msps_render.scene.lights import direction_from_slant_tilt, slant_tilt_from_direction, three_lights
from msps_render.scene.sample import SceneConfig, load_scene_config, sample_scene
from msps_render.scene.spec import LightSpec, SceneSpec, ShapeSpec, SplitSpec


def test_same_seed_same_spec_and_json_round_trip():
    cfg = SceneConfig()
    a = sample_scene(cfg, np.random.default_rng(7), seed=7)
    b = sample_scene(cfg, np.random.default_rng(7), seed=7)
    c = sample_scene(cfg, np.random.default_rng(8), seed=8)
    assert a == b and a.to_json() == b.to_json()
    assert a != c
    assert SceneSpec.from_json(a.to_json()) == a
    assert "light 0" in a.summary()


def test_every_sampled_object_has_two_or_more_materials_on_coherent_parts():
    cfg = SceneConfig()
    for seed in range(5):
        spec = sample_scene(cfg, np.random.default_rng(seed))
        assert len(spec.materials) >= 2
        mesh = S.build_mesh(spec.shape)
        parts = S.face_parts(mesh, spec.split)
        counts = np.bincount(parts, minlength=spec.split.n_parts)
        assert (counts > 0.05 * len(parts)).sum() >= 2  # at least two sizeable parts


def test_paper_light_geometry():
    lights = three_lights(30.0)
    for l, tilt in zip(lights, (0, 120, 240)):
        s, t = slant_tilt_from_direction(l.direction)
        assert s == pytest.approx(30.0, abs=1e-9) and t == pytest.approx(tilt, abs=1e-9)
    M = np.array([l.rgb for l in lights]).T
    np.testing.assert_allclose(M, np.full((3, 3), 0.04) + 0.88 * np.eye(3))
    np.testing.assert_allclose(direction_from_slant_tilt(30, 0), [0.5, 0, np.sqrt(3) / 2])


@pytest.mark.parametrize("slant", [0.0, 90.0, -5.0, 120.0])
def test_slant_out_of_range_is_rejected(slant):
    with pytest.raises(InputError, match="slant"):
        direction_from_slant_tilt(slant, 0)
    with pytest.raises(Exception, match="slant_deg"):
        SceneConfig.model_validate({"lights": {"slant_deg": slant}})


def test_unknown_config_key_is_named(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text("[scene.lights]\nslnt_deg = 30\n")
    with pytest.raises(InputError) as e:
        load_scene_config(p)
    assert "bad.toml" in str(e.value) and "slnt_deg" in str(e.value)
    with pytest.raises(InputError, match="unknown key 'shape.colour'"):
        SceneSpec.from_json(json.dumps({"shape": {"kind": "sphere", "colour": 1}, "materials": [],
                                        "lights": []}), "x.json")


def test_blobby_shape_is_star_shaped_and_smooth():
    rng = np.random.default_rng(3)
    coeffs = S.sample_blobby_coeffs(rng, lmax=4, amplitude=0.3)
    v, f = S.blobby_mesh(coeffs, subdivisions=4)
    r = np.linalg.norm(v, axis=1)
    assert r.min() > 0.3  # radial function positive => no self-intersection
    m = S.build_mesh(ShapeSpec(kind="blobby", sh_coeffs=coeffs, subdivisions=4))
    assert np.linalg.norm(m.vertices, axis=1).max() == pytest.approx(1.0, abs=1e-5)
    # smooth: adjacent vertex normals differ by a few degrees at most
    e = np.concatenate([m.faces[:, [0, 1]], m.faces[:, [1, 2]]])
    cos = (m.normals[e[:, 0]] * m.normals[e[:, 1]]).sum(1)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 15
    # outward normals
    assert ((m.normals * m.vertices).sum(1) > 0).mean() > 0.99


def test_split_kinds_cover_all_parts():
    m = S.build_mesh(ShapeSpec(kind="blobby", subdivisions=4))
    rng = np.random.default_rng(0)
    for kind in ("field", "planes"):
        split = S.sample_split(rng, 3, kind)
        parts = S.face_parts(m, split)
        assert set(np.unique(parts)) <= {0, 1, 2} and len(np.unique(parts)) >= 2
    assert (S.face_parts(m, SplitSpec()) == 0).all()


def test_scene_validation_errors():
    light = LightSpec(direction=(0, 0, 1))
    with pytest.raises(Exception, match="at least one material"):
        SceneSpec(shape=ShapeSpec(kind="sphere"), materials=(), lights=(light,))
    with pytest.raises(Exception, match="finite non-zero"):
        LightSpec(direction=(0, 0, 0))
    with pytest.raises(Exception, match="point light needs a distance"):
        LightSpec(kind="point", direction=(0, 0, 1))


@pytest.mark.parametrize("name", list(S.PRIMITIVES))
def test_primitives_build_outward_and_normalised(name):
    params = S.sample_primitive_params(name, np.random.default_rng(0))
    m = S.build_mesh(ShapeSpec(kind="primitive", name=name, params=params))
    assert np.linalg.norm(m.vertices, axis=1).max() == pytest.approx(1.0, abs=1e-5)
    # outward: vertex normals agree with the face winding's normals on average
    fn = np.cross(m.vertices[m.faces[:, 1]] - m.vertices[m.faces[:, 0]],
                  m.vertices[m.faces[:, 2]] - m.vertices[m.faces[:, 0]])
    agree = (fn * m.normals[m.faces].mean(1)).sum(1) > 0
    assert agree.mean() > 0.99
    # and point away from the centroid for most of the surface (all four are nearly star-shaped)
    assert ((m.normals * (m.vertices - m.vertices.mean(0))).sum(1) > 0).mean() > 0.6


def test_unknown_primitive_is_rejected():
    with pytest.raises(Exception, match="unknown primitive 'donut'"):
        ShapeSpec(kind="primitive", name="donut")


def test_real_sh_basis_equals_scipy_spherical_harmonics():
    """The recurrence in `geometry.real_sh_basis` is scipy's complex Y_lm made real (Condon-Shortley
    phase included), to float rounding, including the poles and up to l = 8."""
    from scipy.special import sph_harm_y

    from msps_render.scene.geometry import real_sh_basis

    rng = np.random.default_rng(0)
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:3] = [[0, 0, 1], [0, 0, -1], [1, 0, 0]]
    theta, phi = np.arccos(np.clip(d[:, 2], -1, 1)), np.arctan2(d[:, 1], d[:, 0])
    for lmax, lmin in ((1, 1), (4, 1), (8, 0)):
        cols = []
        for l in range(lmin, lmax + 1):
            for m in range(-l, l + 1):
                Y = sph_harm_y(l, abs(m), theta, phi)
                cols.append(Y.real if m == 0 else np.sqrt(2) * (-1) ** m * (Y.imag if m < 0 else Y.real))
        np.testing.assert_allclose(real_sh_basis(d, lmax, lmin), np.stack(cols, 1), rtol=0, atol=1e-12)
