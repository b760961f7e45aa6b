"""Spatially varying appearance (textures, measured blends), the albedo gamut and rig variation.

Tolerances:
- Textured Lambertian sphere: L_c = albedo_c(x)/pi * E * max(0, n.l) at every pixel, with
  albedo(x) the stored ground truth read back from the same mesh attributes the renderer
  shades with.  The render averages over the pixel footprint (box filter) while the truth is
  at the pixel centre: for a smooth field of feature size >= 0.3 object radii (~40 px here)
  the footprint average differs by second order, well under 0.1 %; pixel-sample noise at
  64 spp is ~0.2 %; so a 1 % mean relative error has > 3x margin.  A transposed channel,
  a texture evaluated in the rotated instead of the object frame, or a ground truth off by
  one vertex would each give errors of 10-100 %.
- Sharp patches: inside a cell the same closed form holds; at cell edges the footprint
  straddles two colours, so the test asserts the median (edges are a few % of pixels).
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import binary_erosion

from msps_render.errors import InputError
from msps_render.scene.spec import CameraSpec, IntegratorSpec, LightSpec, MaterialSpec, SceneSpec, ShapeSpec
from msps_render.scene.textures import TEXTURE_KINDS, TextureConfig, TextureSpec, texture_fields, texture_images

E = 2.0


def _sphere_points(n=4000, seed=0):
    p = np.random.default_rng(seed).normal(size=(n, 3))
    return p / np.linalg.norm(p, axis=1, keepdims=True)


def _tex(kind, seed=3, scale=0.3, colors=((0.8, 0.1, 0.1), (0.1, 0.7, 0.2), (0.1, 0.2, 0.9))):
    return TextureSpec(kind=kind, seed=seed, scale=scale, colors=colors)


@pytest.mark.parametrize("kind", [k for k in TEXTURE_KINDS if k != "image"])
def test_texture_fields_are_deterministic_bounded_and_vary(kind):
    p = _sphere_points()
    rgb, w = texture_fields(_tex(kind), p)
    rgb2, w2 = texture_fields(_tex(kind), p)
    assert rgb.shape == (len(p), 3) and w.shape == (len(p),)
    assert np.array_equal(rgb, rgb2) and np.array_equal(w, w2)
    assert rgb.min() >= 0 and rgb.max() <= 1 and w.min() >= 0 and w.max() <= 1
    assert rgb.std(axis=0).max() > 0.05, "a texture must vary across the surface"
    other, _ = texture_fields(_tex(kind, seed=4), p)
    assert not np.array_equal(rgb, other), "another seed is another texture"


@pytest.mark.parametrize("kind", ["patches", "stripes", "decals"])
def test_sharp_kinds_take_only_palette_colours(kind):
    t = _tex(kind)
    rgb, _ = texture_fields(t, _sphere_points())
    pal = np.asarray(t.colors, np.float32)
    d = np.abs(rgb[:, None, :] - pal[None]).max(-1).min(1)
    assert d.max() < 1e-6  # sharp edges: every point has exactly one palette colour


def test_image_texture_triplanar_and_uv(tmp_path):
    from msps_render.io.png16 import write_png

    img = np.zeros((8, 8, 3), np.uint16)
    img[:, :4] = (65535, 0, 0)
    img[:, 4:] = (0, 0, 65535)
    write_png(tmp_path / "tex.png", img)
    t = TextureSpec(kind="image", seed=1, scale=0.5, image=str(tmp_path / "tex.png"))
    p = _sphere_points()
    rgb, _ = texture_fields(t, p, p)
    assert rgb[:, 0].max() > 0.9 and rgb[:, 2].max() > 0.9  # both halves of the image are used
    uv = np.column_stack([np.full(10, 0.25), np.full(10, 0.5)])
    t_uv = t.model_copy(update={"mapping": "uv"})
    rgb_uv, _ = texture_fields(t_uv, p[:10], p[:10], uv)
    assert np.allclose(rgb_uv, [1.0, 0.0, 0.0], atol=1e-6)  # u = 0.25 is the red half
    with pytest.raises(InputError, match="without UVs"):
        texture_fields(t_uv, p[:10], p[:10], None)


def test_bad_texture_inputs_name_the_file(tmp_path):
    from msps_render.scene.textures import read_texture_image

    with pytest.raises(InputError, match="no images"):
        texture_images(tmp_path)
    bad = tmp_path / "garbage.png"
    bad.write_bytes(b"not a png at all")
    with pytest.raises(InputError) as e:
        read_texture_image(bad)
    assert "garbage.png" in str(e.value)
    with pytest.raises(ValueError, match="needs texture.folder"):
        TextureConfig(fraction=0.5, kinds=["image"])
    with pytest.raises(ValueError, match="unknown texture kind 'stripe'.*stripes"):
        TextureConfig(kinds=["stripe"])


def test_full_gamut_reaches_saturated_and_dark_colours_moderate_does_not():
    from msps_render.brdf.families import _albedo

    rng = np.random.default_rng(0)
    full = np.array([_albedo(rng, gamut="full") for _ in range(4000)])
    mod = np.array([_albedo(rng) for _ in range(4000)])
    ratio_full = full.min(1) / full.max(1)
    ratio_mod = mod.min(1) / mod.max(1)
    assert ratio_mod.min() >= 0.49  # the old distribution: every channel >= half the largest
    # documented: s = 0.9 u^0.6, so P(min/max < 0.25) = P(u > 0.738) = 0.26 and the floor is 0.1
    assert np.quantile(ratio_full, 0.2) < 0.25 and ratio_full.min() < 0.11
    assert full.max(1).min() < 0.1 and full.max() <= 0.95  # dark colours occur, never above 0.95
    hue = np.degrees(np.arctan2(np.sqrt(3) * (full[:, 1] - full[:, 2]),
                                2 * full[:, 0] - full[:, 1] - full[:, 2])) % 360
    counts = np.histogram(hue[ratio_full < 0.6], bins=6, range=(0, 360))[0]
    assert counts.min() > 0.5 * counts.mean()  # every hue sextant is covered


def test_mixed_gamut_is_a_third_each_achromatic_moderate_full():
    """`mixed` (train-colour-mixed): one third exactly grey, the rest split between the moderate
    distribution (ratio >= 0.49) and the full one (ratios down to 0.1).  Binomial sd over 6,000
    draws is 0.6 %, so +-3 % is > 4 sd."""
    from msps_render.brdf.families import _albedo

    rng = np.random.default_rng(3)
    mixed = np.array([_albedo(rng, gamut="mixed") for _ in range(6000)])
    ratio = mixed.min(1) / mixed.max(1)
    grey = ratio == 1.0
    assert abs(grey.mean() - 1 / 3) < 0.03
    # full draws with ratio 1 - s < 0.49: s = 0.9 u^0.6 > 0.51 <=> u > 0.388, P = 0.61
    assert abs((ratio < 0.49).mean() - 0.61 / 3) < 0.03
    assert ratio.min() < 0.11
    g = mixed[grey, 0]
    assert 0.15 <= g.min() < 0.17 and 0.88 < g.max() <= 0.9  # grey brightness uniform in [lo, hi]


def test_random_crosstalk_is_dominant_asymmetric_and_normalised():
    from msps_render.calibration import crosstalk_problem
    from msps_render.scene.lights import random_crosstalk

    rng = np.random.default_rng(1)
    Ms = [random_crosstalk(rng, (0.8, 0.95), 0.6) for _ in range(200)]
    for M in Ms:
        assert crosstalk_problem(M) is None
        assert np.allclose(M.sum(0), 1.0)
        assert (np.diag(M) >= 0.8 - 1e-12).all() and (np.diag(M) <= 0.95 + 1e-12).all()
    assert np.mean([np.abs(M - M.T).max() > 0.01 for M in Ms]) > 0.9  # asymmetric rigs occur
    sym = random_crosstalk(rng, (0.92, 0.92), 0.0)
    assert np.allclose(sym, np.full((3, 3), 0.04) + np.eye(3) * 0.88)  # asymmetry 0 = the paper's rig


def test_sensor_bits_and_response():
    from msps_render.render.sensor import SensorConfig, camera_response, sensor_response

    x = np.linspace(0, 1, 1001)[:, None, None].repeat(3, -1)
    for bits in (8, 10, 12, 16):
        cfg = SensorConfig(poisson=False, read_noise_e=0.0, bits=bits)
        y = sensor_response(x, cfg, 1.0, np.random.default_rng(0))
        assert len(np.unique(y)) == min(2 ** bits, 1001)
        assert np.abs(y - x).max() <= 0.5 / (2 ** bits - 1) + 1e-7
    g = SensorConfig(poisson=False, read_noise_e=0.0, bits=16, response="gamma", gamma=2.2)
    y = sensor_response(x, g, 1.0, np.random.default_rng(0))
    assert np.allclose(y[500, 0, 0], 0.5 ** (1 / 2.2), atol=1e-4)
    assert np.allclose(camera_response(np.array([0.5]), SensorConfig(response="srgb")), 0.7353569, atol=1e-6)


# ----------------------------------------------------------------- rendering
def _textured_sphere(kind, seed=5, scale=0.45, res=128, rotation=None):
    tex = TextureSpec(kind=kind, seed=seed, scale=scale,
                      colors=((0.85, 0.15, 0.1), (0.1, 0.6, 0.2), (0.2, 0.3, 0.9)), max_edge=0.02)
    mat = MaterialSpec(name="diffuse", kind="diffuse", params={"reflectance": (0.85, 0.15, 0.1)}, texture=tex)
    rot = rotation if rotation is not None else ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (-1.0, 0.0, 0.0))
    return SceneSpec(shape=ShapeSpec(kind="blobby", radius=0.95, subdivisions=5, rotation=rot),
                     materials=(mat,), lights=(LightSpec(direction=(0.0, 0.0, 1.0), rgb=(E, E, E)),),
                     camera=CameraSpec(width=res, height=res),
                     integrator=IntegratorSpec(kind="direct", spp=64, max_depth=2))


@pytest.mark.parametrize("kind", ["smooth", "patches"])
def test_textured_lambertian_matches_closed_form_with_stored_albedo(rgb_variant, kind):
    from msps_render.render import render_frame
    from msps_render.scene.shapes import build_mesh

    spec = _textured_sphere(kind)
    f = render_frame(spec, variant=rgb_variant)
    assert f.albedo is not None and f.albedo.shape == (128, 128, 3)
    cos = np.clip(f.normal[..., 2], 0, None)
    expected = f.albedo / np.pi * E * cos[..., None]
    inner = binary_erosion(f.mask, iterations=2) & (cos > 0.2)
    rel = np.abs(f.image[inner] - expected[inner]) / np.maximum(expected[inner], 1e-3)
    assert inner.sum() > 5000
    if kind == "smooth":
        assert rel.mean() < 0.01, f"mean relative error {rel.mean():.4f}"
    else:
        assert np.median(rel) < 0.005 and np.mean(rel < 0.02) > 0.85, (np.median(rel), np.mean(rel < 0.02))
    # the stored albedo is the texture, evaluated in the object's own frame
    mesh = build_mesh(spec.shape)
    R = np.asarray(spec.shape.rotation)
    front = mesh.vertices[:, 2] > 0.5
    rgb, _ = texture_fields(spec.materials[0].texture, mesh.vertices[front] @ R, mesh.normals[front] @ R)
    assert f.albedo[inner].std(0).max() > 0.05
    assert np.abs(np.sort(f.albedo[inner][:, 0]).mean() - rgb[:, 0].mean()) < 0.1
    assert (f.albedo[~f.mask] == 0).all() and (f.blend == 0).all()


def test_textured_frame_save_writes_albedo(rgb_variant, tmp_path):
    from msps_render.render import render_frame

    f = render_frame(_textured_sphere("stripes", res=64), variant=rgb_variant)
    written = {p.name for p in f.save(tmp_path)}
    assert {"albedo.exr", "albedo.png", "blend.exr"} <= written


def test_measured_blend_weight_ground_truth(rgb_variant):
    """A measured part textured with blend: weight 0/1 regions of a patches texture both occur,
    and where w = 0 the pixel equals the render of material A alone (weight truth is exact)."""
    from msps_render.brdf import nbrdf
    from msps_render.render import render_frame

    names = sorted(nbrdf.builtin_names())
    if len(names) < 2:
        pytest.skip("no built-in Neural-BRDF materials")
    a = MaterialSpec(name=f"nbrdf:{names[0]}", kind="merl", params={"table": f"nbrdf:{names[0]}"})
    b = MaterialSpec(name=f"nbrdf:{names[1]}", kind="merl", params={"table": f"nbrdf:{names[1]}"})
    tex = TextureSpec(kind="stripes", seed=2, scale=0.4, colors=((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)))
    base = _textured_sphere("smooth", res=96)
    spec = base.model_copy(update={"materials": (a.model_copy(update={"texture": tex, "blend": b}),)})
    f = render_frame(spec, variant=rgb_variant)
    inner = binary_erosion(f.mask, iterations=3)
    w = f.blend[inner]
    # stripes take w = 0 or 1; only the triangles a stripe edge crosses interpolate between them
    assert (w == 0).mean() > 0.2 and (w == 1).mean() > 0.2 and ((w == 0) | (w == 1)).mean() > 0.85
    only_a = render_frame(base.model_copy(update={"materials": (a,)}), variant=rgb_variant)
    zero = binary_erosion(f.blend == 0, iterations=2) & inner
    assert np.allclose(f.image[zero], only_a.image[zero], rtol=0.05, atol=1e-3)
    one = binary_erosion(f.blend == 1, iterations=2) & inner
    assert np.abs(f.image[one] - only_a.image[one]).mean() > 0.01  # material B shows where w = 1


# ----------------------------------------------------------------- command line
def _msps(*args):
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "msps_render.cli", *args], capture_output=True, text=True)


def _texture_sets(folder):
    return ["--set", "scene.materials.texture.fraction=1", "--set", 'scene.materials.texture.kinds=["image"]',
            "--set", f"scene.materials.texture.folder={folder}"]


def test_render_refuses_bad_textures_before_writing(tmp_path):
    from msps_render.io.png16 import write_png

    folder = tmp_path / "tex"
    folder.mkdir()
    out = tmp_path / "out"
    r = _msps("render", "demo", "--out", str(out), *_texture_sets(folder))
    assert r.returncode == 1 and not out.exists()
    assert r.stderr.strip().count("\n") == 0 and "texture folder holds no images" in r.stderr
    (folder / "broken.png").write_bytes(b"garbage")
    r = _msps("render", "demo", "--out", str(out), *_texture_sets(folder))
    assert r.returncode == 1 and not out.exists() and "broken.png" in r.stderr
    (folder / "broken.png").unlink()
    write_png(folder / "ok.png", np.full((4, 4, 3), 30000, np.uint16))
    mesh = tmp_path / "tet.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    r = _msps("render", "demo", "--out", str(out), *_texture_sets(folder), "--set", "scene.shape.source=mesh",
              "--set", f'scene.shape.meshes=["{mesh}"]', "--set", "scene.materials.texture.mapping=uv")
    assert r.returncode == 1 and not out.exists()
    assert "tet.obj" in r.stderr and "without UVs" in r.stderr


def test_uv_mapped_image_texture_on_a_mesh_with_uvs(rgb_variant, tmp_path):
    """spot has UVs: its albedo truth takes the texture's two colours where mapping = 'uv'."""
    from conftest import SHARED

    from msps_render.io.png16 import write_png
    from msps_render.render import render_frame
    from msps_render.scene.shapes import mesh_has_uv

    spot = SHARED / "meshes" / "ajc_spot.obj"
    if not spot.is_file():
        pytest.skip("../shared/data absent")
    assert mesh_has_uv(spot)
    img = np.zeros((64, 64, 3), np.uint8)
    img[:, :, 0] = 200
    img[(np.arange(64) // 4) % 4 == 0] = (0, 0, 200)  # blue bands, 4 texels wide: the UV layout shows
    write_png(tmp_path / "lines.png", img)
    tex = TextureSpec(kind="image", seed=0, scale=0.5, image=str(tmp_path / "lines.png"), mapping="uv")
    mat = MaterialSpec(name="diffuse", kind="diffuse", params={"reflectance": (0.5, 0.5, 0.5)}, texture=tex)
    spec = SceneSpec(shape=ShapeSpec(kind="mesh", name="spot", path=str(spot), radius=0.95),
                     materials=(mat,), lights=(LightSpec(direction=(0.0, 0.0, 1.0), rgb=(E, E, E)),),
                     camera=CameraSpec(width=96, height=96), integrator=IntegratorSpec(kind="direct", spp=8))
    f = render_frame(spec, variant=rgb_variant)
    a = f.albedo[f.mask]
    srgb200 = ((200 / 255 + 0.055) / 1.055) ** 2.4  # 8-bit texture images are sRGB-decoded
    assert np.abs(a.max(0)[[0, 2]] - srgb200).max() < 0.02  # both colours reach the surface ...
    assert (a[:, 0] > 0.5).mean() > 0.5  # ... mostly red, as the image is


def test_spectral_random_rig_draws_led_camera_pairs_per_frame():
    from msps_render.scene.sample import SceneConfig, sample_scene

    cfg = SceneConfig.model_validate({"mode": "spectral", "spectral": {"random_rig": {}}})
    specs = [sample_scene(cfg, np.random.default_rng(s)) for s in range(12)]
    cams = {s.camera_response for s in specs}
    assert cams == {"Nikon 5100 (NPL)", "Sigma SDMerill (NPL)"}
    Ms = np.array([s.crosstalk for s in specs])
    assert np.ptp(Ms[:, 0, 0]) > 0.01  # the effective crosstalk follows the drawn pair
    peaks = np.array([[float(l.spectrum.split(":")[1]) for l in s.lights] for s in specs])
    assert ((peaks[:, 0] >= 615) & (peaks[:, 0] <= 645)).all() and ((peaks[:, 2] >= 455) & (peaks[:, 2] <= 475)).all()
    fixed = SceneConfig.model_validate({"mode": "spectral"})
    assert sample_scene(fixed, np.random.default_rng(0)).crosstalk == sample_scene(fixed, np.random.default_rng(0)).crosstalk


def test_subdivision_splits_only_long_edges_without_cracks():
    """Long edges are split at shared midpoints: the surface (area, watertightness) is unchanged,
    no edge is left longer than max_edge, and a mesh that is already fine is left alone."""
    import trimesh

    from msps_render.render.textures import subdivide_to_edge
    from msps_render.scene.geometry import TriMesh

    box = trimesh.creation.box(extents=(1.0, 0.6, 0.3))  # 12 big faces, edges up to 1.17
    m = TriMesh(box.vertices.astype(np.float32), box.faces.astype(np.uint32),
                box.vertex_normals.astype(np.float32))
    m2 = subdivide_to_edge(m, 0.05)
    e = np.linalg.norm(m2.vertices[m2.faces[:, [1, 2, 0]]] - m2.vertices[m2.faces], axis=-1)
    assert e.max() <= 0.05 + 1e-6
    t2 = trimesh.Trimesh(m2.vertices, m2.faces, process=True)  # merges the shared midpoints
    assert t2.is_watertight and abs(t2.area - box.area) < 1e-5
    assert np.allclose(np.linalg.norm(m2.normals, axis=1), 1.0, atol=1e-5)
    fine = subdivide_to_edge(m2, 0.05)
    assert len(fine.faces) == len(m2.faces)  # nothing left to split
    capped = subdivide_to_edge(m, 0.001, max_faces=5000)
    assert len(capped.faces) <= 5000
