"""Render stage end to end: determinism, user meshes, env maps, bad input, CLI, variant fallback."""
from __future__ import annotations

import subprocess
import sys
import warnings

import numpy as np
import pytest

from msps_render.errors import InputError
from msps_render.render import render_frame
from msps_render.render import variant as V
from msps_render.scene import shapes as S
from msps_render.scene.envmap import load_envmap, procedural_sky
from msps_render.scene.lights import three_lights
from msps_render.scene.materials import lambertian
from msps_render.scene.sample import SceneConfig, sample_scene
from msps_render.scene.spec import CameraSpec, EnvSpec, IntegratorSpec, LightSpec, SceneSpec, ShapeSpec


def small(spec: SceneSpec, res=48, spp=8) -> SceneSpec:
    return spec.model_copy(update={"camera": CameraSpec(width=res, height=res),
                                   "integrator": spec.integrator.model_copy(update={"spp": spp})})


def test_same_seed_same_image(rgb_variant):
    cfg = SceneConfig()
    a = small(sample_scene(cfg, np.random.default_rng(11)))
    b = small(sample_scene(cfg, np.random.default_rng(11)))
    fa, fb = render_frame(a, rgb_variant, threads=2), render_frame(b, rgb_variant, threads=2)
    assert np.array_equal(fa.image, fb.image) and np.array_equal(fa.normal, fb.normal)
    assert fa.mask.any() and np.isfinite(fa.image).all() and (fa.image >= 0).all()
    assert set(np.unique(fa.part[fa.mask])) <= set(range(len(a.materials)))


def test_every_analytic_family_renders(rgb_variant):
    from msps_render.scene.materials import FAMILIES, sample_analytic

    rng = np.random.default_rng(0)
    mats = tuple(sample_analytic(f, rng) for f in FAMILIES)
    spec = SceneSpec(shape=ShapeSpec(kind="blobby", subdivisions=4),
                     split=S.sample_split(rng, len(mats), "planes"), materials=mats, lights=three_lights(),
                     camera=CameraSpec(width=48, height=48), integrator=IntegratorSpec(spp=4))
    f = render_frame(spec, rgb_variant)
    assert np.isfinite(f.image).all() and f.image[f.mask].mean() > 0.01


@pytest.mark.parametrize("name", ["ajc_spot.obj", "ajc_cow.obj", "ajc_teapot.obj"])
def test_user_mesh_is_normalised_and_renders(rgb_variant, shared_data, name):
    spec = SceneSpec(shape=ShapeSpec(kind="mesh", path=str(shared_data / "meshes" / name)),
                     materials=(lambertian(),), lights=(LightSpec(direction=(0, 0, 1), rgb=(1, 1, 1)),),
                     camera=CameraSpec(width=64, height=64), integrator=IntegratorSpec(kind="direct", spp=4))
    m = S.build_mesh(spec.shape)
    assert np.linalg.norm(m.vertices, axis=1).max() == pytest.approx(1.0, abs=1e-5)
    f = render_frame(spec, rgb_variant)
    assert 0.05 < f.mask.mean() < 0.9
    # Head-on light: a correctly oriented (outward) surface is lit almost everywhere it is seen,
    # with radiance rho/pi * n_z (one-sided BSDFs render inward-wound meshes black).
    lit = f.image[..., 0][f.mask] > 0
    assert lit.mean() > 0.95, lit.mean()
    expected = 0.8 / np.pi * f.normal[..., 2][f.mask]
    ok = expected > 0.05
    assert np.median(np.abs(f.image[..., 0][f.mask][ok] - expected[ok]) / expected[ok]) < 0.05


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".stl", ".glb"])
def test_mesh_formats_via_trimesh(tmp_path, suffix):
    import trimesh

    p = tmp_path / f"box{suffix}"
    trimesh.creation.box().export(p)
    m = S.build_mesh(ShapeSpec(kind="mesh", path=str(p)))
    assert len(m.faces) == 12 and np.allclose(np.linalg.norm(m.normals, axis=1), 1, atol=1e-5)


def test_degenerate_faces_removed():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]], float)
    f = np.array([[0, 1, 2], [0, 1, 3], [1, 1, 2]])  # second is collinear, third repeats an index
    assert S.clean_faces(v, f).tolist() == [[0, 1, 2]]


def test_bad_meshes(tmp_path):
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99999\n\x00\x01")
    empty = tmp_path / "empty.obj"
    empty.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    for p, msg in ((garbage, "cannot parse|no faces"), (empty, "no faces"), (nan, "NaN")):
        with pytest.raises(InputError, match=msg) as e:
            S.build_mesh(ShapeSpec(kind="mesh", path=str(p)))
        assert p.name in str(e.value) and "\n" not in str(e.value)


def _write_exr(path, img):
    from msps_render.io.images import write_exr

    write_exr(path, img)


def test_bad_envmaps(tmp_path):
    img = np.ones((16, 32, 3), np.float32)
    img[3, 4, 1] = np.nan
    _write_exr(tmp_path / "nan.exr", img)
    img2 = np.ones((16, 32, 3), np.float32)
    img2[0, 0, 0] = -1
    _write_exr(tmp_path / "neg.exr", img2)
    (tmp_path / "junk.exr").write_bytes(b"not an exr")
    for name, msg in (("nan.exr", "NaN"), ("neg.exr", "negative"), ("junk.exr", "cannot read EXR")):
        with pytest.raises(InputError, match=msg) as e:
            load_envmap(str(tmp_path / name))
        assert name in str(e.value)


def test_real_envmaps_load(shared_data):
    exr = load_envmap(str(shared_data / "envmaps" / "venice_sunset_1k.exr"))
    hdr = load_envmap(str(shared_data / "envmaps" / "venice_sunset_1k.hdr"))
    assert exr.shape == hdr.shape == (512, 1024, 3)
    assert abs(float(exr.mean()) / float(hdr.mean()) - 1) < 0.02  # same map, half vs RGBE precision


def test_procedural_sky_is_hdr_and_deterministic():
    a, b = procedural_sky(3), procedural_sky(3)
    assert np.array_equal(a, b) and a.shape == (128, 256, 3)
    assert a.max() / np.median(a) > 20  # sun-like blobs give real dynamic range


def test_environment_adds_light_and_keeps_ground_truth(rgb_variant):
    base = SceneSpec(shape=ShapeSpec(kind="sphere"), materials=(lambertian(),), lights=three_lights(),
                     camera=CameraSpec(width=48, height=48), integrator=IntegratorSpec(spp=8))
    with_env = base.model_copy(update={"environment": EnvSpec(source="procedural", scale=0.05, seed=1)})
    a, b = render_frame(base, rgb_variant), render_frame(with_env, rgb_variant)
    assert np.array_equal(a.normal, b.normal) and np.array_equal(a.mask, b.mask)
    assert b.image[b.mask].sum() > a.image[a.mask].sum() * 1.01
    from scipy.ndimage import binary_dilation

    far = ~binary_dilation(b.mask, iterations=2)  # boundary pixels are partly covered: skip them
    assert b.env_image is not None and (b.image[far] == 0).all()  # emitters hidden from the camera


def test_variant_fallback_to_scalar(monkeypatch, scalar_variant):
    monkeypatch.delenv("MSPS_VARIANT", raising=False)
    monkeypatch.setattr(V, "probe_variant", lambda v, timeout=0: (False, "forced by test"))
    with pytest.warns(V.VariantFallbackWarning, match="falling back to scalar_rgb"):
        v = V.resolve_variant("rgb")
    assert v == "scalar_rgb"
    spec = SceneSpec(shape=ShapeSpec(kind="sphere"), materials=(lambertian(),), lights=three_lights(),
                     camera=CameraSpec(width=24, height=24), integrator=IntegratorSpec(kind="direct", spp=16))
    f = render_frame(spec, variant=v)
    assert f.variant == "scalar_rgb"
    from msps_render.testing import analytic_sphere_normals

    n, disk = analytic_sphere_normals(24, 24, 1.05, 1.0)
    from scipy.ndimage import binary_erosion

    inner = binary_erosion(disk, iterations=2)
    ang = np.degrees(np.arccos(np.clip((f.normal[inner] * n[inner]).sum(-1), -1, 1)))
    assert ang.max() < 0.1
    expected = sum(0.8 / np.pi * np.clip(n @ np.array(l.direction), 0, None)[..., None] * np.array(l.rgb)
                   for l in spec.lights)
    ok = inner & (expected.min(-1) > 0.02)
    assert np.mean(np.abs(f.image[ok] - expected[ok]) / expected[ok]) < 0.02


def test_forced_variant_env(monkeypatch):
    monkeypatch.setenv("MSPS_VARIANT", "scalar_rgb")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert V.resolve_variant("rgb") == "scalar_rgb"
    monkeypatch.setenv("MSPS_VARIANT", "no_such_variant")
    with pytest.raises(ValueError, match="not available"):
        V.resolve_variant("rgb")


# ---------------------------------------------------------------------- CLI
def run_cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "msps_render.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd)


def test_cli_render_scene_writes_outputs(tmp_path, rgb_variant):
    spec = small(sample_scene(SceneConfig(), np.random.default_rng(1)), res=32, spp=4)
    sj = tmp_path / "scene.json"
    sj.write_text(spec.to_json())
    r = run_cli("render-scene", sj, "--out", tmp_path / "out")
    assert r.returncode == 0, r.stderr
    names = {p.name for p in (tmp_path / "out").iterdir()}
    assert {"image.exr", "normal.exr", "depth.exr", "image.png", "normal.png", "mask.png", "scene.json"} <= names
    from msps_render.io.images import read_image

    img = read_image(tmp_path / "out" / "image.exr")
    assert img.shape == (32, 32, 3) and img.max() > 0


def test_cli_bad_inputs_one_line_no_output(tmp_path, shared_data):
    bad_json = tmp_path / "bad.json"
    bad_json.write_text('{"shape": {"kind": "sphere"}, "materials": [], "lights": [], "wat": 1}')
    bad_mesh = tmp_path / "broken.obj"
    bad_mesh.write_text("this is not a mesh\n")
    spec = sample_scene(SceneConfig(), np.random.default_rng(1))
    mesh_scene = tmp_path / "mesh.json"
    mesh_scene.write_text(spec.model_copy(update={"shape": ShapeSpec(kind="mesh", path=str(bad_mesh))}).to_json())
    for scene, msg in ((bad_json, "unknown key 'wat'"), (mesh_scene, "broken.obj"),
                       (tmp_path / "missing.json", "scene file not found")):
        out = tmp_path / f"out-{scene.stem}"
        r = run_cli("render-scene", scene, "--out", out)
        assert r.returncode == 1
        lines = [l for l in r.stderr.strip().splitlines() if l]
        assert len(lines) == 1 and msg in lines[0], r.stderr
        assert not out.exists()


def test_inward_wound_mesh_is_reoriented(tmp_path):
    import trimesh

    box = trimesh.creation.icosphere(2)
    p = tmp_path / "inside_out.ply"
    trimesh.Trimesh(box.vertices, box.faces[:, ::-1], process=False).export(p)
    m = S.build_mesh(ShapeSpec(kind="mesh", path=str(p)))
    assert ((m.normals * m.vertices).sum(1) > 0).all()


@pytest.mark.parametrize("gpu,cuda_ok,llvm_ok,expect", [
    (False, True, True, "llvm_ad_rgb"),   # no NVIDIA driver: CUDA never probed
    (True, True, True, "cuda_ad_rgb"),    # a working GPU wins
    (True, False, True, "llvm_ad_rgb"),   # a GPU whose CUDA variant fails: LLVM, a warning saying why
    (True, False, False, "scalar_rgb"),   # nothing works: scalar with one warning
])
def test_variant_order_cuda_llvm_scalar(monkeypatch, gpu, cuda_ok, llvm_ok, expect):
    """CUDA when a working device is present, then LLVM, then scalar; MSPS_VARIANT still forces one."""
    monkeypatch.delenv("MSPS_VARIANT", raising=False)
    probed = []

    def probe(v, timeout=0):
        probed.append(v)
        return ({"cuda_ad_rgb": cuda_ok, "llvm_ad_rgb": llvm_ok}[v], "forced by test")

    monkeypatch.setattr(V, "probe_variant", probe)
    monkeypatch.setattr(V, "cuda_device_present", lambda: gpu)
    import warnings

    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        assert V.resolve_variant("rgb") == expect
    said = [str(w.message) for w in got if issubclass(w.category, V.VariantFallbackWarning)]
    if expect == "scalar_rgb":
        assert len(said) == 1 and "cuda_ad_rgb: forced by test; llvm_ad_rgb: forced" in said[0]
    elif gpu and not cuda_ok:  # the probe's own words, and what is used instead
        assert len(said) == 1 and "cuda_ad_rgb: forced by test" in said[0] and "using llvm_ad_rgb" in said[0]
    else:
        assert said == []
    assert ("cuda_ad_rgb" in probed) == gpu
    monkeypatch.setenv("MSPS_VARIANT", "scalar_rgb")
    assert V.resolve_variant("rgb") == "scalar_rgb"


def test_cuda_variant_renders_on_a_gpu():
    """On a machine with a working NVIDIA GPU the CUDA variant passes the probe (skips elsewhere)."""
    if not V.cuda_device_present():
        pytest.skip("no NVIDIA driver on this machine")
    ok, why = V.probe_variant("cuda_ad_rgb")
    assert ok, why
