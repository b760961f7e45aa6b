"""Kernel reuse across scenes (issue 12): scenes of one structure compile no new drjit kernels
after the first, and directional-light shadows stay exact with the fixed scene bound."""
from __future__ import annotations

import numpy as np
import pytest

from msps_render.brdf import analytic
from msps_render.scene.geometry import sample_blobby_coeffs
from msps_render.scene.lights import direction_from_slant_tilt, three_lights
from msps_render.scene.materials import lambertian
from msps_render.scene.sample import sample_split
from msps_render.scene.shapes import random_rotation
from msps_render.scene.spec import (CameraSpec, IntegratorSpec, LightSpec, MaterialSpec, SceneSpec,
                                    ShapeSpec)

pytest.importorskip("mitsuba")


@pytest.fixture(scope="module")
def merl_tables(tmp_path_factory) -> list[str]:
    """Two generated MERL tables: one without a sampling lobe (weight 0), one shiny (weight > 0)."""
    cache = tmp_path_factory.getbasetemp() / "msps-cache" / "brdf"
    return [str(analytic.generated_table("lambert", {"albedo": [0.7, 0.5, 0.3]}, cache)),
            str(analytic.generated_table("ggx", {"kd": [0.05, 0.1, 0.2], "ks": [1.0, 1.0, 1.0],
                                                 "alpha": 0.08, "f0": 0.04}, cache))]


def _scene(k: int, tables: list[str]) -> SceneSpec:
    """Scene k of one structure (blobby shape split in 3 parts: merl, roughplastic, principled;
    three directional lights): everything else (shape and so bounding box, rotation, table,
    lobe, BSDF parameters, metallic zero or not, light directions, seed) differs with k."""
    rng = np.random.default_rng(100 + k)
    shape = ShapeSpec(kind="blobby", name=f"blob{k}", sh_coeffs=sample_blobby_coeffs(rng, 3, 0.35),
                      subdivisions=3, rotation=random_rotation(rng), radius=float(rng.uniform(0.6, 0.95)))
    merl = MaterialSpec(name="m", kind="merl", params={
        "table": tables[k % 2], "lobe_alpha": float(rng.uniform(0.05, 0.5)),
        "lobe_weight": float(rng.choice([0.0, rng.uniform(0.1, 0.8)]))})
    rough = MaterialSpec(name="r", kind="roughplastic", params={
        "diffuse_reflectance": tuple(float(x) for x in rng.uniform(0.1, 0.9, 3)),
        "alpha": float(rng.uniform(0.05, 0.4)), "int_ior": float(rng.uniform(1.4, 1.7))})
    princ = MaterialSpec(name="p", kind="principled", params={
        "base_color": tuple(float(x) for x in rng.uniform(0.1, 0.9, 3)), "roughness": float(rng.uniform(0.2, 0.9)),
        "metallic": 0.0 if k % 2 else float(rng.uniform(0.1, 1.0)), "specular": float(rng.uniform(0.2, 0.8))})
    lights = three_lights(30.0, (0.0, 120.0, 240.0), irradiance=2.0, rng=rng, jitter_deg=10.0)
    return SceneSpec(shape=shape, split=sample_split(rng, 3, "field"), materials=(merl, rough, princ),
                     lights=lights, camera=CameraSpec(width=32, height=32),
                     integrator=IntegratorSpec(kind="path", spp=4, max_depth=4, seed=k))


def test_scenes_of_one_structure_compile_no_new_kernels(rgb_variant, merl_tables):
    """After the first frame no new kernel hash appears and every launch is an in-memory cache hit.

    Checking hashes (not only LLVM compiles) keeps the test independent of drjit's disk
    cache, which would hide a recompilation of any kernel an earlier run compiled.
    """
    from msps_render.render import render_frame
    from msps_render.render.kernels import KernelLog

    log = KernelLog()
    try:
        per_frame = []
        for k in range(6):
            f = render_frame(_scene(k, merl_tables), variant=rgb_variant)
            assert f.mask.any() and np.isfinite(f.image).all() and f.image[f.mask].max() > 0
            per_frame.append(log.frame_counts())
    finally:
        log.close()
    assert per_frame[0]["new_hashes"] > 0
    later = per_frame[1:]
    assert all(c["new_hashes"] == 0 for c in later), later
    assert all(c["compiled"] == 0 and c["disk_loads"] == 0 for c in later), later
    assert all(c["launches"] > 0 for c in later)


def test_scene_bound_is_fixed(rgb_variant, merl_tables):
    """Every scene's bounding box is the helper's [-SCENE_BOUND, SCENE_BOUND]^3, whatever the object."""
    import mitsuba as mi

    from msps_render.render.scene_dict import SCENE_BOUND, build_scene_dict

    for k in range(2):
        spec = _scene(k, merl_tables)
        bbox = mi.load_dict(build_scene_dict(spec, mi)).bbox()
        np.testing.assert_allclose(np.array(bbox.min), -SCENE_BOUND)
        np.testing.assert_allclose(np.array(bbox.max), SCENE_BOUND)


def _slab_and_cube(path) -> tuple[np.ndarray, float]:
    """A flat slab (top face at z = 0, finely subdivided so its inner vertex normals are exactly +z)
    with a cube floating above it; written to `path`. Returns (bbox centre, scale) of the
    normalisation `build_mesh` applies (radius 0.95, as `shapes.normalise`)."""
    import trimesh

    slab = trimesh.creation.box(extents=(1.6, 1.6, 0.2))
    slab.apply_translation((0.0, 0.0, -0.1))
    for _ in range(4):
        slab = slab.subdivide()
    cube = trimesh.creation.box(extents=(0.3, 0.3, 0.3))
    cube.apply_translation((0.3, 0.0, 0.35))
    mesh = trimesh.util.concatenate([slab, cube])
    mesh.export(path)
    v = np.asarray(mesh.vertices)
    c = 0.5 * (v.min(0) + v.max(0))
    return c, 0.95 / float(np.linalg.norm(v - c, axis=1).max())


def test_directional_shadow_is_exact_with_the_fixed_bound(rgb_variant, tmp_path):
    """Closed form: a cube above a Lambertian slab, one directional light at slant 45 deg.

    On the slab's top (z = 0) the shadow is the cube swept along -l: x in
    [x0 - t1 lx, x1 - t0 lx], y in [y0, y1] with t in [(z0)/lz, (z1)/lz]; the camera
    sees it left of the cube.  Inside it (1.5 px margin) the direct integrator must
    give exactly 0; on the lit top it must give rho/pi E cos(45 deg).
    """
    from msps_render.render import render_frame

    c, s = _slab_and_cube(tmp_path / "slab.obj")
    l = direction_from_slant_tilt(45.0, 0.0)
    rho, E, res = 0.6, 2.0, 96
    spec = SceneSpec(shape=ShapeSpec(kind="mesh", name="slab", path=str(tmp_path / "slab.obj"), radius=0.95),
                     materials=(lambertian((rho, rho, rho)),), lights=(LightSpec(direction=tuple(l), rgb=(E, E, E)),),
                     camera=CameraSpec(width=res, height=res), integrator=IntegratorSpec(kind="direct", spp=16))
    f = render_frame(spec, variant=rgb_variant)
    ext = spec.camera.extent
    xs = ((np.arange(res) + 0.5) / res * 2 - 1) * ext
    ys = (1 - (np.arange(res) + 0.5) / res * 2) * ext
    X, Y = np.meshgrid(xs, ys)
    x, y = X / s + c[0], Y / s + c[1]  # pixel centres in the mesh's own coordinates
    px = 2 * ext / res / s  # one pixel in those coordinates
    t0, t1 = 0.2 / l[2], 0.5 / l[2]
    shadow = ((x > 0.15 - t1 * l[0] + 1.5 * px) & (x < 0.15 - 1.5 * px)  # left of the cube's footprint
              & (np.abs(y) < 0.15 - 1.5 * px))
    inner = 0.8 - 0.1 - 1.5 * px  # the slab's outermost cells (0.1 wide) have tilted vertex normals
    top = f.mask & (f.normal[..., 2] > 0.9999) & (np.abs(x) < inner) & (np.abs(y) < inner)
    swept = ((x > 0.15 - t1 * l[0] - 1.5 * px) & (x < 0.45 - t0 * l[0] + 1.5 * px)
             & (np.abs(y) < 0.15 + 1.5 * px))
    cube = (np.abs(x - 0.3) < 0.15 + 1.5 * px) & (np.abs(y) < 0.15 + 1.5 * px)
    lit = top & ~swept & ~cube
    assert (shadow & top).sum() > 30 and lit.sum() > 1000
    assert f.image[shadow & top].max() == 0.0
    expected = rho / np.pi * E * l[2]
    rel = np.abs(f.image[lit][:, 0] - expected) / expected
    assert rel.max() < 1e-3, rel.max()


def test_smooth_plastic_ior_takes_few_values():
    """Mitsuba's `plastic` bakes int_ior into the kernel: the family draws it on a 0.1 grid, so a
    long run compiles at most 4 plastic variants per material mix instead of one per scene."""
    import numpy as np

    from msps_render.brdf.families import FAMILIES

    rng = np.random.default_rng(0)
    iors = {FAMILIES["plastic"].sample(rng)["int_ior"] for _ in range(400)}
    assert iors == {1.4, 1.5, 1.6, 1.7}
