"""The albedo colour read off a network's own normals (models/netcal.py), against closed forms.

On a Lambertian sphere c = diag(rho) A max(0, L n) exactly, so with the true normals the per-channel
ratio c_k / (A n)_k IS rho on every pixel all lights reach; with normals off by ~7 deg at random the
median still gives it to 0.2 %.  A network confuses colour with tilt: the stand-in predictor below
averages the truth with calibrated Lambertian PS (which explains every colour as a tilt), so its error
comes only from the colour -- one round of the loop must remove half of it, each further round half
of the rest (geometric: the stand-in keeps half of the colour it is shown).  Grey objects and objects
of two colours must pass through untouched (the gates).  Then `msps predict --netcal`,
`msps bench-real` and `msps eval` with the shipped network.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from cli_helpers import cli, render_tiny
from msps_render.models.baseline import lambertian_ps, unshadowed
from msps_render.models.metrics import angular_error_deg
from msps_render.models.netcal import NetcalSettings, calibrate, chroma_agreement, estimate_colour, pixel_ratios
from test_selfcal import COLOUR_SET, L, M, SATURATED, render, sphere, write_predict_inputs

A = M @ L
TRUE_RHO = SATURATED / SATURATED.mean()


def stand_in(mask: np.ndarray, truth: np.ndarray):
    """A 'network' whose only error is colour read as tilt: the mean of the truth and Lambertian PS."""
    def predict(image: np.ndarray) -> np.ndarray:
        q = 0.5 * truth + 0.5 * lambertian_ps(image, L, M, mask)
        q /= np.linalg.norm(q, axis=-1, keepdims=True).clip(1e-12)
        q[~mask] = 0
        return q
    return predict


def test_true_normals_give_the_albedo_colour_exactly():
    n, mask = sphere(96)
    rho, used, agree = estimate_colour(render(n, mask, SATURATED), mask, n, A)
    np.testing.assert_allclose(rho, TRUE_RHO, rtol=1e-5)  # float32 image: the closed form, to rounding
    assert used > 4000 and agree == 1.0  # every used pixel has the one colour


def test_noisy_normals_give_it_to_a_fraction_of_a_percent():
    n, mask = sphere(96)
    noisy = n + np.random.default_rng(0).normal(0.0, 0.1, n.shape)
    noisy /= np.linalg.norm(noisy, axis=-1, keepdims=True)
    noisy[~mask] = 0
    assert 5.0 < angular_error_deg(noisy[mask], n[mask]).mean() < 9.0  # measured 7.1 deg
    rho, _, agree = estimate_colour(render(n, mask, SATURATED), mask, noisy, A)
    np.testing.assert_allclose(rho, TRUE_RHO, rtol=0.01)  # measured 0.17 %: the median over ~4,800 pixels
    assert agree > 0.8  # measured 0.90 at the default tolerance 0.2


@pytest.mark.parametrize("rounds,most", [(1, 15.0), (2, 7.5), (3, 4.0)])
def test_the_loop_takes_back_the_colour_read_as_tilt(rounds, most):
    n, mask = sphere(96)
    img = render(n, mask, SATURATED)
    lit = unshadowed(n, L, mask)
    predict = stand_in(mask, n)
    before = angular_error_deg(predict(img)[lit], n[lit]).mean()
    out, seen, fit = calibrate(predict, img, mask, A, NetcalSettings(rounds=rounds))
    after = angular_error_deg(out[lit], n[lit]).mean()
    assert before > 25.0  # measured 30.1
    assert fit.applied and fit.rounds == rounds
    assert after < most  # measured 13.1 / 6.5 / 3.2: about half per round
    np.testing.assert_allclose(seen, img * fit.scale.astype(np.float32), rtol=1e-6)
    # the factor moves toward 1/rho (mean 1): every channel on the right side of 1
    want = (1 / TRUE_RHO) / (1 / TRUE_RHO).mean()
    assert np.all(np.sign(fit.scale - 1) == np.sign(want - 1))


def test_grey_and_two_colour_objects_pass_through():
    n, mask = sphere(96)
    predict = stand_in(mask, n)
    grey = render(n, mask, np.full(3, 0.5))
    out, seen, fit = calibrate(predict, grey, mask, A)
    assert not fit.applied and fit.rounds == 0 and seen is grey  # estimate ~1: below min_colour
    np.testing.assert_array_equal(out, predict(grey))
    two = render(n, mask, np.where((np.arange(96) < 48)[None, :, None], SATURATED, SATURATED[::-1]))
    _, seen, fit = calibrate(predict, two, mask, A)
    assert not fit.applied and seen is two
    assert fit.agree < NetcalSettings().min_agree  # measured 0.53: half the pixels have the other colour
    # with the true normals the ratios ARE the two albedos: the agreement is the majority colour's share
    r = pixel_ratios(two, mask, n, A)
    left = np.isclose(r[:, 0] / r[:, 2], SATURATED[0] / SATURATED[2], rtol=1e-3)
    assert 0 < left.sum() < len(r)
    assert chroma_agreement(r, 0.2) == pytest.approx(max(left.mean(), 1 - left.mean()), abs=1e-9)


def test_too_few_pixels_is_no_estimate():
    n, mask = sphere(96)
    small = np.zeros_like(mask)
    small[40:48, 40:48] = True
    rho, used, _ = estimate_colour(render(n, small, SATURATED), small, n, A)
    assert rho is None and used < NetcalSettings().min_pixels


def glossy_sphere(size: int = 96, ks: float = 0.3, p: float = 40.0):
    """The saturated Lambertian sphere plus a white Blinn-Phong lobe per light: the highlights break the
    unit-norm closed form, so selfcal refuses it (as it does DiLiGenT's objects) and the loop has to act."""
    n, mask = sphere(size)
    h = L + np.array([0.0, 0.0, 1.0])
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    spec = np.maximum(n @ h.T, 0.0) ** p * (n @ L.T > 0)
    return (render(n, mask, SATURATED) + ks * (spec @ M.T) * mask[..., None]).astype(np.float32), n, mask


def test_predict_netcal_with_the_shipped_network(tmp_path):
    """`msps predict --netcal` on a glossy saturated sphere that selfcal refuses: the loop is recorded and
    lowers the network's error; the Lambertian baseline is refused with one line."""
    img, n, mask = glossy_sphere()
    base = write_predict_inputs(tmp_path, img, n, mask)
    rig = base[:base.index("--method")] + base[base.index("--method") + 2:]  # the network, not the baseline
    m = {}
    for flag in ("", "--netcal"):
        r = cli("predict", tmp_path / "img.npy", "--out", tmp_path / f"o{flag}", *rig, *([flag] if flag else ["--steps", "none"]))
        assert r.returncode == 0, r.stderr
        m[flag] = json.loads((tmp_path / f"o{flag}-metrics.json").read_text())
    nc = m["--netcal"]
    assert m[""]["netcal"] is None and not nc["selfcal"]["applied"] and nc["netcal"]["applied"]
    want = (1 / TRUE_RHO) / (1 / TRUE_RHO).mean()
    np.testing.assert_allclose(nc["netcal"]["scale"], want, rtol=0.15)  # measured within 7 %
    assert nc["mae_deg"] < m[""]["mae_deg"] - 0.2  # measured 4.15 -> 3.60 deg
    r = cli("predict", tmp_path / "img.npy", "--out", tmp_path / "x", *base, "--netcal")
    assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1 and "--netcal" in r.stderr
    assert not (tmp_path / "x.npy").exists()


def test_eval_netcal_needs_a_network_and_whole_frames(tmp_path):
    render_tiny(COLOUR_SET.replace("store_frames = true", "store_frames = false"), tmp_path)
    for args, what in ((["--method", "lambertian", "--netcal"], "checkpoint"), (["--netcal"], "whole frames")):
        r = cli("eval", "--data", tmp_path / "ds", "--out", tmp_path / "ev", *args)
        assert r.returncode == 1, r.stderr
        err = r.stderr.strip().splitlines()
        assert len(err) == 1 and "--netcal" in err[0] and what in err[0], err
        assert not (tmp_path / "ev" / "metrics.json").exists()


def test_eval_netcal_frames_and_patches(tmp_path):
    """Rendered saturated objects through `msps eval --netcal --refine`: the twin columns exist for the
    network only, and the patch scores use the frame's loop (a factor per frame, like selfcal's)."""
    render_tiny(COLOUR_SET, tmp_path)
    r = cli("eval", "--data", tmp_path / "ds", "--out", tmp_path / "ev", "--method", "net", "--method",
            "lambertian", "--netcal", "--refine")
    assert r.returncode == 0, r.stderr
    m = json.loads((tmp_path / "ev" / "metrics.json").read_text())["methods"]
    assert set(m) == {"net", "lambertian", "net+selfcal+netcal", "net+refine", "net+selfcal+netcal+refine"}
    for k in m:
        (c,) = m[k]["conditions"].values()
        assert np.isfinite(c["frames"]["mae_deg"]) and np.isfinite(c["patches"]["mae_deg"])
    (plain,) = m["net"]["conditions"].values()
    (nc,) = m["net+selfcal+netcal"]["conditions"].values()
    # saturated Lambertian objects: selfcal divides the colour out first, so the network sees them grey
    assert nc["frames"]["mae_deg"] < plain["frames"]["mae_deg"] - 3.0, (nc["frames"], plain["frames"])
    assert nc["patches"]["mae_deg"] < plain["patches"]["mae_deg"] - 3.0


def test_eval_reuses_the_frame_loop_exactly(tmp_path, monkeypatch):
    """`msps eval` runs every method on a frame with one `Memo`: the loop's passes are shared with the
    plain column and the refined twin, and every column equals a fresh run of its method (the network is
    deterministic)."""
    from msps_render.calibration import Rig
    from msps_render.data import iter_frames
    import msps_render.models.tiles as tiles_mod
    from msps_render.models.evaluate import resolve_methods
    from msps_render.models.runner import Memo, run
    from msps_render.models.steps import from_flags

    render_tiny(COLOUR_SET, tmp_path)
    methods = resolve_methods(methods=["net"], columns=from_flags(True, netcal=True, refine=True))
    assert [m.name for m in methods] == ["net", "net+selfcal+netcal", "net+refine", "net+selfcal+netcal+refine"]
    calls = []
    real = tiles_mod.predict_image
    monkeypatch.setattr(tiles_mod, "predict_image", lambda *a, **k: calls.append(1) or real(*a, **k))
    for fr in iter_frames(tmp_path / "ds"):
        memo, rig = Memo(), Rig.of(fr)
        calls.clear()
        shared = [run(m, fr.image, fr.mask, rig, memo).normals for m in methods]
        assert len(calls) <= 3  # the image as rendered, after selfcal, after the loop's colour: once each
        for m, got in zip(methods, shared):
            np.testing.assert_array_equal(got, run(m, fr.image, fr.mask, rig).normals)

def test_eval_default_steps_without_whole_frames_fall_back_with_one_warning(tmp_path):
    """Plain `msps eval` (default steps, which fit whole frames) on a corpus stored without frames scores
    the raw network and says so in one warning line; the same steps asked for still refuse (above)."""
    render_tiny(COLOUR_SET.replace("store_frames = true", "store_frames = false"), tmp_path)
    r = cli("eval", "--data", tmp_path / "ds", "--out", tmp_path / "ev")
    assert r.returncode == 0, r.stderr
    warns = [ln for ln in r.stderr.splitlines() if ln.startswith("warning:")]
    assert len(warns) == 1 and "no whole frames" in warns[0] and "--steps none" in warns[0], r.stderr
    assert list(json.loads((tmp_path / "ev" / "metrics.json").read_text())["methods"]) == ["net"]
