"""MERL table IO and lookup: reference semantics, round trip, bad input (numpy only, no Mitsuba)."""
from __future__ import annotations

import math
import sys

import numpy as np
import pytest

from msps_render.brdf import analytic, merl
from msps_render.errors import InputError


# ------------------------------------------------ straightforward reference port
# A line-by-line port of MERL's BRDFRead.cpp (scalar, math module), kept deliberately
# independent of msps_render.brdf.merl so the vectorised lookup is checked against it.
def _ref_cross(v1, v2):
    return [v1[1] * v2[2] - v1[2] * v2[1], v1[2] * v2[0] - v1[0] * v2[2], v1[0] * v2[1] - v1[1] * v2[0]]


def _ref_normalize(v):
    ln = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    return [v[0] / ln, v[1] / ln, v[2] / ln]


def _ref_rotate(vector, axis, angle):
    cos_ang, sin_ang = math.cos(angle), math.sin(angle)
    out = [vector[0] * cos_ang, vector[1] * cos_ang, vector[2] * cos_ang]
    temp = axis[0] * vector[0] + axis[1] * vector[1] + axis[2] * vector[2]
    temp = temp * (1.0 - cos_ang)
    out = [out[k] + axis[k] * temp for k in range(3)]
    cross = _ref_cross(axis, vector)
    return [out[k] + cross[k] * sin_ang for k in range(3)]


def _ref_half_diff(theta_in, fi_in, theta_out, fi_out):
    in_z, proj_in = math.cos(theta_in), math.sin(theta_in)
    in_x, in_y = proj_in * math.cos(fi_in), proj_in * math.sin(fi_in)
    vin = _ref_normalize([in_x, in_y, in_z])
    out_z, proj_out = math.cos(theta_out), math.sin(theta_out)
    out_x, out_y = proj_out * math.cos(fi_out), proj_out * math.sin(fi_out)
    half = _ref_normalize([(in_x + out_x) / 2.0, (in_y + out_y) / 2.0, (in_z + out_z) / 2.0])
    theta_half = math.acos(half[2])
    fi_half = math.atan2(half[1], half[0])
    temp = _ref_rotate(vin, [0.0, 0.0, 1.0], -fi_half)
    diff = _ref_rotate(temp, [0.0, 1.0, 0.0], -theta_half)
    return theta_half, fi_half, math.acos(diff[2]), math.atan2(diff[1], diff[0])


def _ref_theta_half_index(theta_half):
    if theta_half <= 0.0:
        return 0
    temp = math.sqrt(((theta_half / (math.pi / 2.0)) * 90) * 90)
    return min(max(int(temp), 0), 89)


def _ref_theta_diff_index(theta_diff):
    tmp = int(theta_diff / (math.pi * 0.5) * 90)
    return 0 if tmp < 0 else (tmp if tmp < 89 else 89)


def _ref_phi_diff_index(phi_diff):
    if phi_diff < 0.0:
        phi_diff += math.pi
    tmp = int(phi_diff / math.pi * 360 / 2)
    return 0 if tmp < 0 else (tmp if tmp < 179 else 179)


def ref_lookup_brdf_val(brdf, theta_in, fi_in, theta_out, fi_out):
    th, _, td, pd = _ref_half_diff(theta_in, fi_in, theta_out, fi_out)
    ind = _ref_phi_diff_index(pd) + _ref_theta_diff_index(td) * 180 + _ref_theta_half_index(th) * 180 * 90
    n = 90 * 90 * 180
    return ind, (brdf[ind] * (1.0 / 1500.0), brdf[ind + n] * (1.15 / 1500.0), brdf[ind + 2 * n] * (1.66 / 1500.0))


# --------------------------------------------------------------------- helpers
def _random_angles(rng, n):
    return (rng.uniform(0, math.pi / 2, n), rng.uniform(0, 2 * math.pi, n),
            rng.uniform(0, math.pi / 2, n), rng.uniform(0, 2 * math.pi, n))


def _vec(theta, phi):
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)


@pytest.fixture(scope="module")
def random_raw_file(tmp_path_factory):
    """A MERL file of random raw values: equal values <=> equal bins."""
    rng = np.random.default_rng(7)
    rgb = rng.uniform(0.01, 1.0, size=(3, *merl.DIMS))
    path = merl.write_merl(tmp_path_factory.mktemp("merl") / "random.binary", rgb)
    return path, rgb


# ----------------------------------------------------------------------- tests
def test_lookup_matches_reference_port_exactly(random_raw_file):
    path, _ = random_raw_file
    table = merl.read_merl(path, dtype=np.float64)
    raw = np.fromfile(path, dtype="<f8", offset=12)
    rng = np.random.default_rng(123)
    n = 12_000
    ti, pi_, to, po = _random_angles(rng, n)
    # Include near-normal and near-grazing directions, where the index clamps act.
    ti[:200] = rng.uniform(0, 1e-3, 200)
    to[200:400] = rng.uniform(math.pi / 2 - 1e-3, math.pi / 2 - 1e-9, 200)
    idx = merl.lookup_index(_vec(ti, pi_), _vec(to, po))
    vals = merl.lookup(table, _vec(ti, pi_), _vec(to, po))
    ref_idx = np.empty(n, dtype=np.int64)
    ref_vals = np.empty((n, 3))
    for k in range(n):
        ref_idx[k], ref_vals[k] = ref_lookup_brdf_val(raw, ti[k], pi_[k], to[k], po[k])
    assert np.array_equal(idx, ref_idx), f"{np.count_nonzero(idx != ref_idx)} of {n} bins differ"
    assert np.array_equal(vals, ref_vals)
    # the bins cover all three index ranges
    assert len(np.unique(idx // (180 * 90))) > 80 and len(np.unique(idx % 180)) == 180


def test_half_diff_inverse_round_trip():
    rng = np.random.default_rng(1)
    th = rng.uniform(0.01, 1.5, 1000)
    td = rng.uniform(0.01, 1.5, 1000)
    pd = rng.uniform(0.01, math.pi - 0.01, 1000)
    ph = rng.uniform(-3.0, 3.0, 1000)
    wi, wo = merl.half_diff_to_dirs(th, td, pd, ph)
    th2, ph2, td2, pd2 = merl.half_diff_angles(wi, wo)
    np.testing.assert_allclose(th2, th, atol=1e-9)
    np.testing.assert_allclose(td2, td, atol=1e-9)
    np.testing.assert_allclose(pd2, pd, atol=1e-9)
    np.testing.assert_allclose(np.angle(np.exp(1j * (ph2 - ph))), 0.0, atol=1e-9)


def test_write_read_is_lossless(random_raw_file):
    path, rgb = random_raw_file
    t64 = merl.read_merl(path, dtype=np.float64)
    np.testing.assert_allclose(t64.rgb, rgb, rtol=4 * 2.0**-52, atol=0)  # one divide + one multiply
    t32 = merl.read_merl(path)
    assert t32.rgb.dtype == np.float32 and t32.nbytes == 3 * merl.N_BINS * 4
    np.testing.assert_allclose(t32.rgb, rgb, rtol=2.0**-24 + 4 * 2.0**-52, atol=0)
    assert t32.n_negative == 0 and t32.n_nonfinite == 0


def _bin_variation(model, params, wi, wo, steps=3):
    """max - min of the model over each sample's MERL bin (grid of steps^3 points incl. corners)."""
    th, _, td, pd = merl.half_diff_angles(wi, wo)
    i_h = merl.theta_half_index(th)
    i_d = merl.theta_diff_index(td)
    i_p = merl.phi_diff_index(pd)
    t = np.linspace(0.0, 1.0, steps)
    lo = np.full((len(th), 3), np.inf)
    hi = np.full((len(th), 3), -np.inf)
    for a in t:
        for b in t:
            for c in t:
                h = ((i_h + a) / 90.0) ** 2 * (math.pi / 2)
                d = (i_d + b) / 90.0 * (math.pi / 2)
                p = (i_p + c) / 180.0 * math.pi
                f = analytic.evaluate(model, params, *merl.half_diff_to_dirs(h, d, p))
                lo, hi = np.minimum(lo, f), np.maximum(hi, f)
    return hi - lo


@pytest.mark.parametrize("model,params", [
    ("lambert", {"albedo": [0.8, 0.5, 0.2]}),
    ("ggx", {"kd": [0.3, 0.2, 0.1], "ks": [1.0, 1.0, 1.0], "alpha": 0.3, "f0": 0.04}),
    ("ggx", {"kd": [0.0, 0.0, 0.0], "ks": [0.9, 0.6, 0.3], "alpha": 0.1, "f0": 1.0}),
])
def test_round_trip_within_quantisation_bound(tmp_path, model, params):
    """Analytic -> MERL file -> lookup.  Bound: a nearest-bin table returns f at the bin centre,
    so |lookup - f(w)| <= (max - min of f over w's bin) (+ float32 storage, 2^-24 relative)."""
    path = merl.write_merl(tmp_path / "t.binary", analytic.make_table(model, params))
    table = merl.read_merl(path)
    rng = np.random.default_rng(5)
    n = 4000
    ti, pi_, to, po = _random_angles(rng, n)
    keep = (ti < math.radians(80)) & (to < math.radians(80))
    wi, wo = _vec(ti[keep], pi_[keep]), _vec(to[keep], po[keep])
    got = merl.lookup(table, wi, wo)
    want = analytic.evaluate(model, params, wi, wo)
    bound = _bin_variation(model, params, wi, wo) * 1.05 + 2.0**-23 * np.abs(want) + 1e-12
    err = np.abs(got - want)
    assert np.all(err <= bound), f"worst excess {np.max(err - bound):.3g}"
    # at the bin centres the table is the model itself (to float32 rounding)
    th, td, pd = (((np.array([3, 40, 60]) + 0.5) / 90) ** 2 * math.pi / 2, np.radians([2.5, 20.5, 40.5]),
                  np.radians([10.5, 90.5, 170.5]))
    ci, co = merl.half_diff_to_dirs(th, td, pd, 0.7)
    np.testing.assert_allclose(merl.lookup(table, ci, co), analytic.evaluate(model, params, ci, co), rtol=2e-7)
    if model == "lambert":
        np.testing.assert_allclose(got, want, rtol=2e-7)  # constant: exact up to float32


def test_negative_and_nan_entries_are_counted_and_zeroed(tmp_path):
    raw = np.full((3, *merl.DIMS), 1500.0)
    raw[0, 0, 0, :10] = -1.0
    raw[2, 5, 5, 5] = np.nan
    p = tmp_path / "holes.binary"
    with open(p, "wb") as fh:
        fh.write(np.array(merl.DIMS, "<i4").tobytes())
        fh.write(raw.astype("<f8").tobytes())
    t = merl.read_merl(p)
    assert (t.n_negative, t.n_nonfinite) == (10, 1)
    assert t.rgb[0, 0, 0, :10].max() == 0 and t.rgb[2, 5, 5, 5] == 0
    assert t.rgb[1].min() == pytest.approx(1.15)


def _write_bytes(path, header, n_doubles, fill=1.0):
    with open(path, "wb") as fh:
        fh.write(np.asarray(header, "<i4").tobytes())
        fh.write(np.full(n_doubles, fill, "<f8").tobytes())
    return path


@pytest.mark.parametrize("case,expect", [
    ("truncated", "truncated MERL file"),
    ("header_only", "truncated MERL file"),
    ("tiny", "smaller than the 12-byte header"),
    ("wrong_dims", "header dims (90, 90, 360)"),
    ("oversized", "oversized MERL file"),
    ("text", "not a MERL BRDF"),
    ("all_nan", "no finite values"),
    ("missing", "cannot read MERL file"),
])
def test_bad_files_fail_with_one_clear_line(tmp_path, case, expect):
    p = tmp_path / f"{case}.binary"
    n = 3 * merl.N_BINS
    if case == "truncated":
        _write_bytes(p, merl.DIMS, n - 1000)
    elif case == "header_only":
        _write_bytes(p, merl.DIMS, 0)
    elif case == "tiny":
        p.write_bytes(b"\x5a\x00")
    elif case == "wrong_dims":
        _write_bytes(p, (90, 90, 360), 10)
    elif case == "oversized":
        _write_bytes(p, merl.DIMS, n + 3)
    elif case == "text":
        p.write_text("this is not a brdf, just some words in a text file\n" * 10)
    elif case == "all_nan":
        _write_bytes(p, merl.DIMS, n, np.nan)
    with pytest.raises(InputError) as e:
        merl.read_merl(p)
    msg = str(e.value)
    assert e.value.source == str(p) and msg.startswith(str(p)) and expect in msg and "\n" not in msg


def test_writer_rejects_wrong_shape(tmp_path):
    with pytest.raises(ValueError):
        merl.write_merl(tmp_path / "x.binary", np.zeros((3, 90, 90, 90)))
    assert not list(tmp_path.iterdir())


def test_generated_tables_are_deterministic_and_cached(tmp_path, monkeypatch):
    monkeypatch.setenv("MSPS_CACHE_DIR", str(tmp_path))
    params = {"albedo": (0.5, 0.4, 0.3)}
    p1 = analytic.generated_table("lambert", params)
    assert p1.parent == tmp_path / "brdf" and p1.stat().st_size == merl.FILE_BYTES
    mtime = p1.stat().st_mtime_ns
    p2 = analytic.generated_table("lambert", {"albedo": [0.5, 0.4, 0.3]})
    assert p2 == p1 and p2.stat().st_mtime_ns == mtime  # same key, not rebuilt
    assert analytic.table_key("lambert", params) != analytic.table_key("lambert", {"albedo": (0.5, 0.4, 0.31)})
    assert not [f for f in p1.parent.iterdir() if f.name.endswith(".tmp")]


def test_merl_module_does_not_import_mitsuba():
    import subprocess

    code = ("import sys, msps_render.brdf.merl, msps_render.brdf.analytic, msps_render.brdf.library, "
            "msps_render.render.merl_bsdf; print('mitsuba' in sys.modules, 'drjit' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False False"


def test_fit_sampling_lobe_recovers_alpha():
    shiny = analytic.make_table("ggx", {"kd": [0.05] * 3, "ks": [1.0] * 3, "alpha": 0.08, "f0": 0.04})
    alpha, weight = merl.fit_sampling_lobe(shiny)
    assert 0.06 < alpha < 0.1 and weight > 0.1
    _, w_diffuse = merl.fit_sampling_lobe(analytic.make_table("lambert", {"albedo": [0.8] * 3}))
    assert w_diffuse == 0.0


def test_sampling_lobe_is_fit_once_per_cached_table_and_kept_beside_it(tmp_path, monkeypatch):
    """A worker process used to fit every measured table's sampling lobe before its first frames (5-20 ms
    each, 80 tables for the shipped catalogue).  The fit is now stored beside the table in the cache: a
    new process reads the same floats (so pixels do not change), a re-baked table is fit again, and a
    table outside msps's cache gets no file beside it."""
    import json
    import os

    from msps_render.render import merl_bsdf

    monkeypatch.setenv("MSPS_CACHE_DIR", str(tmp_path / "cache"))
    src = analytic.generated_table("ggx", {"kd": [0.05] * 3, "ks": [1.0] * 3, "alpha": 0.08, "f0": 0.04})
    baked = merl_bsdf._baked_file(str(src))
    side = baked + merl_bsdf.LOBE_SUFFIX
    fits = []
    real_fit, real_write = merl.fit_sampling_lobe, merl_bsdf.write_bytes
    monkeypatch.setattr(merl, "fit_sampling_lobe", lambda rgb: fits.append(1) or real_fit(rgb))
    monkeypatch.setattr(merl_bsdf, "_LOBES", {})
    _, alpha, weight = merl_bsdf._load_table(str(src))
    assert len(fits) == 1 and (alpha, weight) == real_fit(merl.read_table(baked).rgb)
    assert json.loads(open(side).read())["alpha"] == alpha  # the fit's own float, exactly
    monkeypatch.setattr(merl_bsdf, "_LOBES", {})  # a new process
    assert merl_bsdf._load_table(str(src))[1:] == (alpha, weight) and len(fits) == 1  # read, not fit
    st = os.stat(baked)
    os.utime(baked, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # the table file replaced
    monkeypatch.setattr(merl_bsdf, "_LOBES", {})
    assert merl_bsdf._load_table(str(src))[1:] == (alpha, weight) and len(fits) == 2
    assert json.loads(open(side).read())["mtime_ns"] == st.st_mtime_ns + 10**9
    open(side, "w").write('{"size": 1, "alpha": ')  # a damaged file (a crash mid-write leaves none: atomic)
    monkeypatch.setattr(merl_bsdf, "_LOBES", {})
    assert merl_bsdf._load_table(str(src))[1:] == (alpha, weight) and len(fits) == 3
    assert json.loads(open(side).read())["alpha"] == alpha  # rewritten
    os.remove(side)  # a full cache disk: the sidecar is skipped, the render goes on with the fit

    def full(path, *a, **k):
        raise merl_bsdf.WriteFailed(path, 28)

    monkeypatch.setattr(merl_bsdf, "write_bytes", full)
    monkeypatch.setattr(merl_bsdf, "_LOBES", {})
    assert merl_bsdf._load_table(str(src))[1:] == (alpha, weight) and len(fits) == 4 and not os.path.exists(side)
    monkeypatch.setattr(merl_bsdf, "write_bytes", real_write)
    own = merl.write_baked(tmp_path / "mine.npy", merl.read_table(baked).rgb)  # a user's own baked table
    assert merl_bsdf._load_table(str(own))[1:] == (alpha, weight) and len(fits) == 5
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache", "mine.npy"]
    assert not [p for p in (tmp_path / "cache" / "brdf").iterdir() if p.name.endswith(".tmp")]
