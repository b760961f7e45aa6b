"""Narrow-band rigs in spectral mode (msps_render.scene.rig_layouts.spectral_rig): N Gaussian LEDs x an M-channel camera of
Gaussian filters, one shot (multiplexed) or one per LED (sequential).

The closed form: an orthographic Lambertian sphere of grey albedo rho under directional LED n reads, in
channel m, I[m] = rho/pi * sum_n C[m, n] * max(0, n . l_n) with
C[m, n] = E_n * int e_n(l) S_m(l) dl / sum_m' int e_n(l) S_m'(l) dl   (E_n the LED's irradiance),
the spectral module's column normalisation.  Here the integrals are computed in closed form (a product
of two Gaussians), independently of the renderer's 1 nm tables, and the grey albedo is spectrally flat
in Mitsuba's upsampling (checked: rgb 0.5/0.8/1.0 give exactly that constant at every wavelength).

Tolerance, 1 % on the median of render / closed form over interior pixels: the per-pixel spread of
that ratio at 16 spp is measured in the test (about 1 %: pixel-footprint sampling of the shading, and
wavelength sampling -- 4 stratified wavelengths per sample drawn from each LED's own bands, so only
channels that share an LED's wavelengths add noise); with ~1500 pixels per channel the median's
standard error is 1.25 * spread / sqrt(n), about 0.05 %, and the test asserts it stays under 0.2 %,
so 1 % keeps a margin of 5x at least (measured worst channel: 0.08 % off).

One exception, measured: in a sequential capture a channel that sees only a NEIGHBOUR's leak (2-7 % of
that LED's signal) gets few of the LED's wavelength samples (they are drawn in proportion to the sum
of the bands, which the LED's own channel dominates), so its per-pixel spread is ~50 % and the
distribution is skewed (its median sits ~15 % low while its mean is unbiased).  Those channels are
checked on the mean over the interior instead: the mean's standard error spread / sqrt(n) is measured
0.4-1.1 % for leaks of 2-9 % (checked to 5 %) and 1.1-2.0 % for leaks of 0.5-1.2 % (checked to 10 %);
the test asserts s.e. < tolerance / 4, so each check is >= 4 sigma, and still catches a transposed or
mis-normalised C (the leaks differ by 2-18x between neighbours here: the filters sit off the LEDs).
In the multiplexed shot every channel carries its own LED, so all six are held to 1 %.  Using the pixel-centre normal
for a box-filtered pixel biases the median by < 0.05 % (second order in the pixel size, interior
pixels).  1 % still catches what would be wrong: a FWHM read as sigma (the LED-filter overlaps
change by 20-60 %), channels or lights out of order (100 %), a light in the wrong shot, a lost
d^2 or normalisation (factor >= 2).
"""
from __future__ import annotations

import functools

import numpy as np
import pytest
from scipy.ndimage import binary_erosion

from msps_render.errors import InputError
from msps_render.rig import Rig, lambertian_shots, rig_of_spec, rig_sensitivities
from msps_render.scene.rig_layouts import RigConfig
from msps_render.scene.materials import lambertian
from msps_render.scene.sample import SceneConfig, sample_scene

PEAKS = (440.0, 490.0, 540.0, 590.0, 640.0, 690.0)
LED_FWHM = 25.0
FILTERS = tuple((c + d, 35.0) for c, d in zip(PEAKS, (0, 5, -5, 10, 0, -10)))  # a little off the LEDs
IRRADIANCE = 3.0
RHO = 0.7
RES, SPP = 64, 16


def rig_table(capture="multiplexed", **kw) -> dict:
    return {"layout": "ring", "n_lights": 6, "slant_deg": 40.0, "capture": capture, "irradiance": IRRADIANCE,
            "led_peaks_nm": list(PEAKS), "led_fwhm_nm": LED_FWHM, "filters": [list(f) for f in FILTERS], **kw}


def scene_config(rig: dict, mode="spectral", **kw) -> SceneConfig:
    return SceneConfig.model_validate({"mode": mode, "shape": {"source": "sphere"},
                                       "camera": {"width": RES, "height": RES},
                                       "integrator": {"kind": "direct", "spp": SPP}, "rig": rig, **kw})


def sphere_spec(capture: str):
    """A grey Lambertian sphere under the narrow-band rig (same lights and seed for every capture)."""
    spec = sample_scene(scene_config(rig_table(capture)), np.random.default_rng(3))
    return spec.model_copy(update={"materials": (lambertian((RHO,) * 3),)})


@functools.lru_cache(maxsize=None)
def rendered(capture: str, variant: str):
    from msps_render.render import render_frame

    spec = sphere_spec(capture)
    return spec, render_frame(spec, variant=variant)


def gaussian_overlap(c1, w1, c2, w2) -> float:
    """int exp(-(l-c1)^2/2s1^2) exp(-(l-c2)^2/2s2^2) dl over the real line (FWHM w = 2 sqrt(2 ln 2) s)."""
    k = 2.0 * np.sqrt(2.0 * np.log(2.0))
    s1, s2 = w1 / k, w2 / k
    v = s1 * s1 + s2 * s2
    return float(np.sqrt(2 * np.pi) * s1 * s2 / np.sqrt(v) * np.exp(-0.5 * (c1 - c2) ** 2 / v))


def closed_form_crosstalk() -> np.ndarray:
    """(M, N) C[m, n] = E_n * overlap(LED n, filter m) / sum_m' overlap(LED n, filter m')."""
    R = np.array([[gaussian_overlap(p, LED_FWHM, c, w) for p in PEAKS] for c, w in FILTERS])
    return IRRADIANCE * R / R.sum(axis=0, keepdims=True)


# ------------------------------------------------------------------ the channel-by-light matrix
def test_rig_crosstalk_is_the_closed_form_spectral_integral():
    spec = sphere_spec("multiplexed")
    rig = rig_of_spec(spec)
    C = closed_form_crosstalk()
    assert rig.crosstalk.shape == (6, 6) and rig.n_shots == 1
    # the renderer's 1 nm sums of Gaussians (sigma >= 10 nm) equal the integral to ~1e-12; the range cut
    # at centre +- 2 FWHM loses < 1e-6 of any band
    np.testing.assert_allclose(rig.crosstalk, C, rtol=1e-6, atol=1e-9 * IRRADIANCE)
    np.testing.assert_allclose(rig.crosstalk.sum(0), IRRADIANCE, rtol=1e-12)
    assert spec.rig.channel_names == tuple(f"{c:g}nm" for c, _ in FILTERS)
    assert [l.spectrum for l in spec.lights] == [f"led:{p:g}:{LED_FWHM:g}" for p in PEAKS]
    assert rig_sensitivities(spec.rig).shape[1] == 6
    # neighbours leak a few percent, others nothing: a real multiplexing problem, still separable
    off = C / np.diag(C)[None, :]
    assert 0.005 < off[1, 0] < 0.1 and off[3, 0] < 1e-6


# ------------------------------------------------------------------ rendering vs closed form
@pytest.mark.parametrize("capture", ["multiplexed", "sequential"])
def test_narrowband_sphere_matches_closed_form(spectral_variant, capture):
    spec, f = rendered(capture, spectral_variant)
    S = 1 if capture == "multiplexed" else 6
    assert f.shots.shape == (S, RES, RES, 6) and f.meta["lights"] == "one-pass"
    rig = Rig(rig_of_spec(spec).light_dirs, closed_form_crosstalk(), shots=spec.rig.shots)
    ref = lambertian_shots(rig, f.normal, RHO)  # (S, H, W, M) at pixel centres
    inner = binary_erosion(f.mask, iterations=3)
    main = leaks = 0
    for s in range(S):
        top = ref[s].max()
        for m in range(6):
            r = ref[s][..., m]
            if r.max() < 1e-3 * top:  # the channel does not see this shot's LEDs (C < 1e-3 of the brightest)
                assert np.abs(f.shots[s][..., m][inner]).max() < 1e-3 * top, (s, m)
                continue
            sel = inner & (r > 0.1 * r.max())  # away from the silhouette and each LED's terminator
            assert sel.sum() > 500
            ratio = f.shots[s][..., m][sel] / r[sel]
            if r.max() >= 0.2 * top:  # a channel that carries the shot's signal: 1 % on the median
                med = float(np.median(ratio))
                stderr = 1.2533 * ratio.std() / np.sqrt(sel.sum())
                print(f"shot {s} channel {m}: {sel.sum()} px, median ratio {med:.5f}, spread {ratio.std():.4f}, "
                      f"median s.e. {stderr:.5f}")
                assert stderr < 0.002, f"shot {s} channel {m}: too noisy for a 1 % check (s.e. {stderr:.4f})"
                assert abs(med - 1.0) < 0.01, f"shot {s} channel {m}: render / closed form = {med:.4f}"
                main += 1
            else:  # a neighbour's leak alone (sequential): 2-7 % of the LED's signal, see below
                mean = float(f.shots[s][..., m][sel].sum() / r[sel].sum())
                stderr = ratio.std() / np.sqrt(sel.sum())
                print(f"shot {s} channel {m} (leak {r.max() / top:.3f}): {sel.sum()} px, mean ratio {mean:.4f}, "
                      f"spread {ratio.std():.3f}, mean s.e. {stderr:.4f}")
                tol = 0.05 if r.max() >= 0.02 * top else 0.10  # a leak under 2 %: fewer samples land in it
                assert stderr < tol / 4, f"shot {s} channel {m}: too noisy for a {tol:.0%} check (s.e. {stderr:.4f})"
                assert abs(mean - 1.0) < tol, f"shot {s} channel {m}: leak render / closed form = {mean:.4f}"
                leaks += 1
    assert main == 6 and leaks == (0 if capture == "multiplexed" else 10)


def test_sequential_capture_sums_to_the_multiplexed_one(spectral_variant):
    _, seq = rendered("sequential", spectral_variant)
    _, mux = rendered("multiplexed", spectral_variant)
    assert seq.shots.shape[0] == 6 and mux.shots.shape[0] == 1
    np.testing.assert_allclose(seq.shots.sum(axis=0), mux.shots[0], rtol=1e-5, atol=1e-7)
    np.testing.assert_array_equal(seq.normal, mux.normal)


def test_stored_spectral_rig_keeps_its_matrix_and_rgb_rigs_keep_their_json():
    spec = sphere_spec("multiplexed")
    from msps_render.scene.spec import SceneSpec

    back = SceneSpec.model_validate_json(spec.to_json())
    np.testing.assert_array_equal(rig_of_spec(back).crosstalk, rig_of_spec(spec).crosstalk)
    rgb = sample_scene(scene_config({"layout": "ring", "n_lights": 4}, mode="rgb"), np.random.default_rng(0))
    dumped = rgb.rig.model_dump()
    assert not {"filters", "camera", "crosstalk"} & set(dumped)
    cfg = RigConfig.model_validate({"layout": "ring", "n_lights": 4}).model_dump()
    assert not {"filters", "camera", "led_peaks_nm", "led_fwhm_nm", "spectra"} & set(cfg)


def test_measured_sensitivity_table_of_any_channel_count(tmp_path):
    """A CSV 'wavelength, s1..s4' is a four-channel camera; flat (white) lights by default."""
    rows = ["nm,a,b,c,d"] + [f"{w},{np.exp(-((w - 450) / 30) ** 2):.6f},{np.exp(-((w - 520) / 30) ** 2):.6f},"
                             f"{np.exp(-((w - 600) / 30) ** 2):.6f},{np.exp(-((w - 680) / 30) ** 2):.6f}"
                             for w in range(380, 781, 5)]
    path = tmp_path / "cam4.csv"
    path.write_text("\n".join(rows) + "\n")
    spec = sample_scene(scene_config({"layout": "ring", "n_lights": 4, "capture": "multiplexed",
                                      "camera": str(path)}), np.random.default_rng(0))
    C = rig_of_spec(spec).crosstalk
    assert C.shape == (4, 4) and spec.rig.channel_names == ("C0", "C1", "C2", "C3")
    assert [l.spectrum for l in spec.lights] == ["flat"] * 4
    np.testing.assert_allclose(C[:, 0], C[:, 1])  # the same white spectrum in every column
    np.testing.assert_allclose(C.sum(0), IRRADIANCE, rtol=1e-12)


# ------------------------------------------------------------------ the integrator's M channels
def test_m_channel_wavelength_sampling_integrates_the_bands(spectral_variant):
    import drjit as dr
    import mitsuba as mi

    from msps_render.render import multilight
    from msps_render.render.multilight import _sample_wavelengths, band_table
    from msps_render.spectral.spectra import GRID, filter_sensitivities, light_spectrum

    bands = filter_sensitivities(FILTERS) * light_spectrum("led:540:25").values[:, None]  # (G, 6)
    table = {k: mi.Float(v.reshape(-1)) for k, v in band_table(GRID, bands).items()}
    n = 100_000
    lam, w = _sample_wavelengths(mi, table, mi.Float((np.arange(n) + 0.5) / n))
    assert len(w) == 6
    est = np.stack([np.array(dr.sum(wi, axis=0)) for wi in w], -1)
    exact = np.trapezoid(bands, GRID, axis=0)
    big = exact > 1e-3 * exact.max()
    np.testing.assert_allclose(est.mean(0)[big], exact[big], rtol=2e-3)
    np.testing.assert_allclose(est.sum(1), exact.sum(), rtol=1e-4)
    integ = mi.load_dict(multilight.integrator_dict("direct", 2, ["light0"], channels=6))
    assert integ.aov_names() == [f"light0.C{i}" for i in range(6)]
    with pytest.raises(ValueError, match=r"expected \(N, 6\)"):
        integ.set_bands(GRID, {"light0": bands[:, :3]})


# ------------------------------------------------------------------ bad input: one line naming the key
@pytest.mark.parametrize("mode,rig,needle", [
    ("spectral", {"filters": [[380.0, 20.0]]}, "filters[0] = [380, 20]: centre 380 nm +- 2 x FWHM 20 nm"),
    ("spectral", {"filters": [[700.0, 70.0]]}, "outside the renderer's spectral range 360-830 nm"),
    ("spectral", {"led_peaks_nm": [370.0] * 6}, "led_peaks_nm[0] = 370 with led_fwhm_nm 25"),
    ("spectral", {"led_peaks_nm": list(PEAKS[:5])}, "led_peaks_nm has 5 entries for 6 lights"),
    ("spectral", {"camera": "Nikon 5100 (NPL)"}, "as filters or as camera, not both"),
    ("spectral", {"spectra": ["flat"] * 6}, "as led_peaks_nm or as spectra, not both"),
    ("spectral", {"filters": [[540.0, 30.0]] * 3}, "capture shot 0 has 6 lights but the camera has 3 channel(s)"),
    ("spectral", {"spectra": ["laser"] * 6, "led_peaks_nm": None}, "unknown light spectrum 'laser'"),
])
def test_bad_spectral_rig_config_is_one_line(mode, rig, needle):
    from msps_render.config_io import validate

    with pytest.raises(InputError) as e:
        validate(SceneConfig, {"mode": mode, "rig": {**rig_table(), **rig}}, "narrow.toml")
    msg = str(e.value)
    assert needle in msg and "rig" in msg and "\n" not in msg, msg


@pytest.mark.parametrize("mode,rig,key,needle", [
    ("rgb", rig_table(), "scene.rig.filters", "is for scene mode 'spectral'"),
    ("rgb", {"layout": "ring", "n_lights": 6, "led_peaks_nm": list(PEAKS)}, "scene.rig.led_peaks_nm",
     "is for scene mode 'spectral'"),
    ("spectral", rig_table(channels="mono"), "scene.rig.channels", "for mode 'rgb'"),
    ("spectral", rig_table(colours="rgb-cycle"), "scene.rig.colours", "for mode 'rgb'"),
    ("spectral", rig_table(errors={"colour_error": 0.1}), "scene.rig.errors.colour_error", "intensity_error"),
    ("spectral", rig_table(led_peaks_nm=[440.0, 490.0, 540.0, 590.0, 640.0, 780.0], led_fwhm_nm=10.0),
     "scene.rig.led_peaks_nm", "light 5 ('led:780:10') gives no signal"),
])
def test_rig_that_does_not_fit_the_mode_is_one_line(mode, rig, key, needle):
    with pytest.raises(InputError) as e:
        sample_scene(scene_config(rig, mode=mode), np.random.default_rng(0))
    msg = str(e.value)
    assert msg.startswith(key) and needle in msg and "\n" not in msg, msg


def test_spectral_rig_refuses_textures():
    cfg = scene_config(rig_table(), materials={"texture": {"fraction": 1.0}})
    with pytest.raises(InputError, match="scene.materials.texture: textures need mode 'rgb'"):
        sample_scene(cfg, np.random.default_rng(0))


def test_lambertian_baseline_demultiplexes_one_narrowband_shot(spectral_variant):
    """Six lights from ONE six-channel image: least squares with the rig's C recovers the normals
    (grey albedo; pixels lit by all six LEDs).  Measured: median 0.49 deg -- the ~1.5 % per-pixel noise
    of each channel at 16 spp; a wrong C (transposed, unnormalised, channels out of order) gives tens
    of degrees.  Bound 1.5 deg."""
    from msps_render.models.baseline import lambertian_ps_rig

    spec, f = rendered("multiplexed", spectral_variant)
    out = lambertian_ps_rig(f.shots, f.rig, f.mask)
    n = out[0] if isinstance(out, tuple) else out
    lit = (f.normal @ f.rig.light_dirs.T > 0.05).all(-1) & binary_erosion(f.mask, iterations=2)
    err = np.degrees(np.arccos(np.clip((n * f.normal).sum(-1), -1, 1)))[lit]
    assert lit.sum() > 500
    assert np.median(err) < 1.5, f"median angular error {np.median(err):.3f} deg"
