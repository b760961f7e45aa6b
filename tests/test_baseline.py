"""The Lambertian baseline: exact on closed-form and on Mitsuba-rendered Lambertian objects.

Both use an asymmetric crosstalk matrix (`testing.ASYMMETRIC_CROSSTALK`): with the paper's
symmetric one a transposed matrix in the solve or in the lights' RGB would pass unnoticed.
"""
from __future__ import annotations

import numpy as np
import pytest

from msps_render.models.baseline import lambertian_ps, unshadowed
from msps_render.models.metrics import angular_error_deg
from msps_render.scene.lights import three_lights
from msps_render.testing import ASYMMETRIC_CROSSTALK


def test_closed_form_lambertian_is_recovered_exactly():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(2000, 3))
    n[:, 2] = np.abs(n[:, 2]) + 0.5
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    lights = three_lights(30.0)
    L = np.array([l.direction for l in lights])
    M = ASYMMETRIC_CROSSTALK
    rho = 0.7
    c = rho * (np.clip(n @ L.T, 0, None) @ M.T)
    ok = (n @ L.T > 0).all(1)
    err = angular_error_deg(lambertian_ps(c, L, M), n)
    # float32 output: arccos near 1 turns ~6e-8 rounding into ~0.02 deg; anything model-related is larger
    assert err[ok].max() < 0.05


def test_baseline_on_rendered_lambertian_blob(rgb_variant):
    from msps_render.render import render_frame
    from msps_render.scene.materials import lambertian
    from msps_render.scene.shapes import sample_blobby_coeffs
    from msps_render.scene.spec import CameraSpec, IntegratorSpec, SceneSpec, ShapeSpec

    coeffs = sample_blobby_coeffs(np.random.default_rng(4), 3, 0.2)
    spec = SceneSpec(shape=ShapeSpec(kind="blobby", sh_coeffs=coeffs, subdivisions=6),
                     materials=(lambertian((0.6, 0.6, 0.6)),),
                     lights=three_lights(30.0, crosstalk=ASYMMETRIC_CROSSTALK, irradiance=3.0),
                     camera=CameraSpec(width=96, height=96), integrator=IntegratorSpec(kind="direct", spp=64))
    f = render_frame(spec, rgb_variant)
    np.testing.assert_allclose(f.crosstalk, ASYMMETRIC_CROSSTALK, atol=1e-12)  # column k = light k's RGB share
    n = lambertian_ps(f.image, f.light_dirs, f.crosstalk, f.mask)
    from scipy.ndimage import binary_erosion

    ok = unshadowed(f.normal, f.light_dirs, binary_erosion(f.mask, iterations=2), margin=0.05)
    assert ok.sum() > 2000
    err = angular_error_deg(n[ok], f.normal[ok])
    # direct lighting of a Lambertian surface: only pixel-footprint averaging separates the
    # image from the pixel-centre normal, so the error is a small fraction of a degree
    assert err.mean() < 1.0 and np.median(err) < 0.5, (err.mean(), np.median(err))
