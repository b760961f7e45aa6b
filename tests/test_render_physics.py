"""Closed-form physics checks of the render stage.

Tolerances:
- Radiance: an orthographic Lambertian sphere lit by one directional light has
  L = rho/pi * E * max(0, n.l) exactly; the render differs only by the box
  filter averaging n.l over the pixel footprint (second order in the pixel/
  radius ratio, < 0.1% for radius 60 px away from the rim) and by pixel-sample
  noise at 64 spp (~0.2%). 1% mean relative error therefore has >5x margin.
- Normals: the analytic sphere's shading normal at the pixel centre is exact up
  to float32 ray/sphere intersection error (~1e-3 deg).
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import binary_erosion

from msps_render.render import render_frame
from msps_render.testing import ASYMMETRIC_CROSSTALK, analytic_sphere_normals
from msps_render.scene.lights import direction_from_slant_tilt, three_lights
from msps_render.scene.materials import lambertian
from msps_render.scene.spec import CameraSpec, IntegratorSpec, LightSpec, SceneSpec, ShapeSpec

RHO = 0.6
E = 2.0


def sphere_scene(lights, spp=64, kind="direct", res=128, radius=0.95, shape="sphere"):
    return SceneSpec(shape=ShapeSpec(kind=shape, radius=radius, subdivisions=6),
                     materials=(lambertian((RHO, RHO, RHO)),), lights=tuple(lights),
                     camera=CameraSpec(width=res, height=res),
                     integrator=IntegratorSpec(kind=kind, spp=spp, max_depth=4))


def angular_error_deg(a, b):
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1, 1)))


@pytest.mark.parametrize("slant,tilt", [(30, 0), (30, 120), (45, 250), (0.001, 0), (60, 300)])
def test_lambertian_sphere_radiance_matches_closed_form(rgb_variant, slant, tilt):
    l = direction_from_slant_tilt(slant, tilt)
    spec = sphere_scene([LightSpec(direction=tuple(l), rgb=(E, E, E))])
    f = render_frame(spec, variant=rgb_variant)
    n_true, disk = analytic_sphere_normals(128, 128, spec.camera.extent, spec.shape.radius)
    expected = RHO / np.pi * E * np.clip(n_true @ l, 0, None)
    inner = binary_erosion(disk, iterations=2) & (expected > 0.05 * RHO / np.pi * E)
    rel = np.abs(f.image[..., 0][inner] - expected[inner]) / expected[inner]
    assert inner.sum() > 3000
    assert rel.mean() < 0.01, f"mean relative error {rel.mean():.4f}"
    # all three channels equal for a white light and grey albedo
    assert np.allclose(f.image[..., 0], f.image[..., 2], rtol=1e-5, atol=1e-6)
    # unlit side is black (no environment, convex object)
    dark = binary_erosion(disk, iterations=2) & (n_true @ l < -0.05)
    if dark.any():
        assert f.image[dark].max() == 0.0


def test_path_equals_direct_on_convex_lambertian(rgb_variant):
    """A convex object has no interreflection: path tracing must not add energy."""
    l = direction_from_slant_tilt(30, 0)
    a = render_frame(sphere_scene([LightSpec(direction=tuple(l), rgb=(E, E, E))], kind="direct"), rgb_variant)
    b = render_frame(sphere_scene([LightSpec(direction=tuple(l), rgb=(E, E, E))], kind="path"), rgb_variant)
    m = binary_erosion(a.mask, iterations=2)
    assert abs(a.image[m].mean() / b.image[m].mean() - 1) < 0.005


def test_three_coloured_lights_sum_without_selection_noise(rgb_variant):
    """Three coloured lights at once equal the sum of the closed forms per light (<1%).

    The closed form is built from the crosstalk matrix itself (channel i of light k = E M[i, k]),
    not from the lights' RGB, and the matrix is asymmetric: a transpose anywhere from
    `three_lights` to the film changes channels by several percent."""
    M = ASYMMETRIC_CROSSTALK
    tilts = (0, 120, 240)
    lights = three_lights(30.0, tilts, M, irradiance=E)
    f = render_frame(sphere_scene(lights, spp=32), rgb_variant, per_light=True)
    n_true, disk = analytic_sphere_normals(128, 128, 1.05, 0.95)
    expected = sum(RHO / np.pi * np.clip(n_true @ direction_from_slant_tilt(30.0, t), 0, None)[..., None]
                   * E * M[:, k] for k, t in enumerate(tilts))
    inner = binary_erosion(disk, iterations=2) & (expected.min(-1) > 0.05)
    rel = np.abs(f.image[inner] - expected[inner]) / expected[inner]
    assert rel.mean() < 0.01
    assert f.per_light.shape == (3, 128, 128, 3)
    np.testing.assert_allclose(f.per_light.sum(0), f.image, rtol=1e-6, atol=1e-7)
    # grey surface: light k's own image splits over the channels exactly as column k of M
    for k in range(3):
        lit = inner & (f.per_light[k].sum(-1) > 0.05)
        share = f.per_light[k][lit].sum(0) / f.per_light[k][lit].sum()
        np.testing.assert_allclose(share, M[:, k], atol=1e-5)


def test_sphere_ground_truth_normals_and_mask(rgb_variant):
    f = render_frame(sphere_scene([LightSpec(direction=(0, 0, 1))], spp=4), rgb_variant)
    n_true, disk = analytic_sphere_normals(128, 128, 1.05, 0.95)
    inside = binary_erosion(disk, iterations=1)
    err = angular_error_deg(f.normal[inside], n_true[inside])
    assert err.mean() < 0.2 and err.max() < 1.0, (err.mean(), err.max())
    # mask equals the analytic disk except on boundary pixels
    boundary = disk ^ binary_erosion(disk)
    boundary |= binary_erosion(~disk) ^ ~disk
    assert np.array_equal(f.mask & ~boundary, disk & ~boundary)
    assert np.allclose(np.linalg.norm(f.normal[f.mask], axis=-1), 1, atol=1e-5)
    assert (f.normal[~f.mask] == 0).all()
    # depth: orthographic camera at z=5 sees the sphere surface at 5 - z
    z = np.sqrt(np.clip(0.95 ** 2 - 0.95 ** 2 * (n_true[..., 0] ** 2 + n_true[..., 1] ** 2), 0, None))
    assert np.abs(f.depth[inside] - (5.0 - z[inside])).max() < 1e-3



@pytest.mark.parametrize("width,height", [(96, 64), (64, 96)])
def test_non_square_frame_normals_match_the_analytic_helper(rgb_variant, width, height):
    """Mitsuba's orthographic camera keeps x in +-extent and scales y by H/W; the analytic helper
    must agree (same error bounds as the square frame above), so tests of non-square frames are sound."""
    spec = sphere_scene([LightSpec(direction=(0, 0, 1))], spp=4).model_copy(
        update={"camera": CameraSpec(width=width, height=height)})
    f = render_frame(spec, rgb_variant)
    n_true, disk = analytic_sphere_normals(width, height, spec.camera.extent, spec.shape.radius)
    boundary = (disk ^ binary_erosion(disk)) | (binary_erosion(~disk) ^ ~disk)
    assert np.array_equal(f.mask & ~boundary, disk & ~boundary)
    inside = binary_erosion(disk, iterations=1)
    assert inside.sum() > 0.5 * np.pi * (0.95 / 1.05 * min(width, height) / 2) ** 2
    err = angular_error_deg(f.normal[inside], n_true[inside])
    assert err.mean() < 0.2 and err.max() < 1.0, (err.mean(), err.max())

def test_mesh_sphere_normals_close_to_analytic(rgb_variant):
    """The blobby path with zero displacement is an icosphere: interpolated normals ~ exact."""
    f = render_frame(sphere_scene([LightSpec(direction=(0, 0, 1))], spp=4, shape="blobby"), rgb_variant)
    n_true, disk = analytic_sphere_normals(128, 128, 1.05, 0.95)
    inside = binary_erosion(disk, iterations=2) & f.mask
    # compare to the exact normal of the point actually hit (x, y known; z on the sphere)
    err = angular_error_deg(f.normal[inside], n_true[inside])
    assert err.mean() < 0.5, err.mean()


@pytest.mark.parametrize("tilt,axis,sign", [(0, 1, +1), (180, 1, -1), (90, 0, -1), (270, 0, +1)])
def test_image_axes(rgb_variant, tilt, axis, sign):
    """Tilt 0 lights +x = image right; tilt 90 lights +y = image top (row 0)."""
    l = direction_from_slant_tilt(60, tilt)
    f = render_frame(sphere_scene([LightSpec(direction=tuple(l), rgb=(E, E, E))], spp=4), rgb_variant)
    half = f.image.shape[axis] // 2
    lum = f.image[..., 0]
    first, second = (lum[:, :half], lum[:, half:]) if axis == 1 else (lum[:half], lum[half:])
    # axis 1 (columns): second half = right; axis 0 (rows): first half = top
    brighter_second = second.sum() > first.sum() * 2
    assert brighter_second == (sign > 0)
    nx = f.normal[..., 0]
    ny = f.normal[..., 1]
    assert nx[:, half:][f.mask[:, half:]].mean() > 0.3 and nx[:, :half][f.mask[:, :half]].mean() < -0.3
    assert ny[:half][f.mask[:half]].mean() > 0.3 and ny[half:][f.mask[half:]].mean() < -0.3


def test_point_light_inverse_square(rgb_variant):
    """A point light of intensity I at distance d gives irradiance I/d^2 at the sphere centre."""
    d, I = 40.0, 2.0 * 40.0 ** 2
    spec = sphere_scene([LightSpec(kind="point", direction=(0, 0, 1), distance=d, rgb=(I, I, I))], spp=16)
    f = render_frame(spec, rgb_variant)
    c = f.image[60:68, 60:68, 0].mean()
    # surface point is at z = 0.95, so the distance is d - 0.95; n.l ~ 1 at the centre
    expected = RHO / np.pi * I / (d - 0.95) ** 2 * f.normal[60:68, 60:68, 2].mean()
    assert abs(c / expected - 1) < 0.005


def test_perspective_camera_sees_sphere_with_camera_facing_normals(rgb_variant):
    spec = sphere_scene([LightSpec(direction=(0, 0, 1), rgb=(E, E, E))], spp=4).model_copy(
        update={"camera": CameraSpec(kind="perspective", fov_deg=30, distance=5.0, width=64, height=64)})
    f = render_frame(spec, rgb_variant)
    # a sphere of radius 0.95 at distance 5 subtends asin(0.95/5) = 10.95 deg of the 15 deg half-fov
    r_px = np.tan(np.arcsin(0.95 / 5)) / np.tan(np.radians(15)) * 32
    assert abs(f.mask.sum() / (np.pi * r_px ** 2) - 1) < 0.05

    assert (f.normal[f.mask][:, 2] > 0).all()
    assert abs(f.depth[32, 32] - (5 - 0.95)) < 0.01

