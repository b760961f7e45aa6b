"""Any rig (msps_render.rig): closed-form physics for N lights x M channels, near LEDs, captures; config,
light files and shard format 2.

Tolerances (the same reasoning as tests/test_render_physics.py): an orthographic Lambertian sphere
under directional light n reads rho/pi * C[m, n] * max(0, n . l_n) exactly at a point; a pixel is the
box-filtered mean over its footprint, so the reference is averaged over 4 x 4 sub-pixel points (its
own error < 0.05 % away from the rim); pixel-sample noise at 64 spp is ~0.2 % per pixel and far less
in the mean.  1 % on the mean relative error over interior pixels thus has > 5x margin, and would
catch a wrong fall-off exponent (a 2 % change of 1/r^2 across the sphere), a missed cos^mu (tens of
%), a transposed channel-by-light matrix (the asymmetric one below: >= 6 %) or a light in the wrong
shot (100 %).
"""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.ndimage import binary_erosion

from msps_render.errors import InputError
from msps_render.rig import (Rig, RigSpec, compose_shots, lambertian_shots, read_light_file, rig_of_spec,
                             write_light_files)
from msps_render.scene.rig_layouts import RigConfig, sample_rig
from msps_render.scene.materials import lambertian
from msps_render.scene.sample import SceneConfig, sample_scene
from msps_render.scene.spec import CameraSpec, IntegratorSpec, SceneSpec, ShapeSpec

RHO = (0.6, 0.45, 0.3)
RES = 96
RADIUS = 0.95


def rig_sphere(rig: dict, spp=64, res=RES, seed=0) -> SceneSpec:
    """A Lambertian sphere (coloured albedo RHO) under the rig `[scene.rig]` table `rig`."""
    lights, spec = sample_rig(RigConfig.model_validate(rig), np.random.default_rng(seed))
    return SceneSpec(shape=ShapeSpec(kind="sphere", radius=RADIUS), materials=(lambertian(RHO),), lights=lights,
                     camera=CameraSpec(width=res, height=res), integrator=IntegratorSpec(kind="direct", spp=spp),
                     rig=spec)


def sphere_points(res: int, sub: int = 4):
    """Sub-pixel points (res, res, sub*sub, 3) on the orthographic sphere, their normals and validity."""
    ext = CameraSpec().extent
    o = (np.arange(sub) + 0.5) / sub
    xs = ((np.arange(res)[:, None] + o[None, :]).ravel() / res * 2 - 1) * ext
    ys = (1 - (np.arange(res)[:, None] + o[None, :]).ravel() / res * 2) * ext
    X, Y = np.meshgrid(xs, ys)
    r2 = (X ** 2 + Y ** 2) / RADIUS ** 2
    inside = r2 < 1
    Z = np.sqrt(np.clip(1 - r2, 0, None)) * RADIUS
    P = np.stack([X, Y, Z], -1)
    def blocks(a):
        return a.reshape(res, sub, res, sub, *a.shape[2:]).swapaxes(1, 2).reshape(res, res, sub * sub, *a.shape[2:])
    return blocks(P), blocks(P / RADIUS), blocks(inside)


def closed_form(spec: SceneSpec, sub: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """(shots (S, H, W, M) box-filtered closed form, interior mask) of `rig_sphere` scenes."""
    P, N, inside = sphere_points(spec.camera.width, sub)
    rig = rig_of_spec(spec)
    channels = np.asarray(spec.rig.channels)
    albedo = channels @ np.asarray(RHO)  # exact for white lights: channel m reads sum_c w_mc rho_c E
    ref = lambertian_shots(rig, N, albedo, P)  # (S, H, W, k, M)
    ref = np.where(inside[None, ..., None], ref, 0.0).mean(axis=3)
    return ref, binary_erosion(inside.all(-1), iterations=2)


def check(spec, frame, tol=0.01):
    ref, inner = closed_form(spec)
    bright = ref > 0.05 * ref.max()
    sel = inner[None, ..., None] & bright
    rel = np.abs(frame.shots[sel] - ref[sel]) / ref[sel]
    assert sel.sum() > 2000
    assert rel.mean() < tol, f"mean relative error {rel.mean():.4f}"
    dark = np.stack([binary_erosion(r.max(-1) == 0, iterations=1) for r in ref]) & inner[None]
    if dark.any():
        assert frame.shots[dark].max() == 0.0  # unlit by every light of the shot: black (convex, no env)
    return rel.mean()


@pytest.mark.parametrize("capture,channels", [("sequential", "rgb"), ("sequential", "mono"),
                                              ([[0, 1], [2, 3, 4], [5]], "rgb")])
def test_directional_rig_matches_closed_form(rgb_variant, capture, channels):
    from msps_render.render import render_frame

    spec = rig_sphere({"layout": "hemisphere", "n_lights": 6, "slant_range_deg": [10, 60], "capture": capture,
                       "channels": channels, "allow_unseparable": True})
    f = render_frame(spec, variant=rgb_variant)
    S = 6 if capture == "sequential" else 3
    assert f.shots.shape == (S, RES, RES, 1 if channels == "mono" else 3)
    check(spec, f)


@pytest.mark.parametrize("mu", [0.0, 4.0])
def test_near_leds_match_closed_form_with_falloff_and_anisotropy(rgb_variant, mu):
    """LEDs on a plane 2.5 units away: 1/r^2 varies by ~2x over the sphere, cos^mu by more."""
    from msps_render.render import render_frame

    spec = rig_sphere({"layout": "grid", "grid": {"rows": 3, "cols": 3, "pitch": 1.2, "plane_distance": 2.5},
                       "anisotropy_mu": mu, "capture": "sequential", "channels": "rgb"})
    f = render_frame(spec, variant=rgb_variant)
    assert f.points is not None
    check(spec, f)
    # the surface points are exact: on the sphere, point / radius is the ground-truth normal
    m = f.mask & binary_erosion(f.mask, iterations=1)
    assert np.abs(f.points[m] / RADIUS - f.normal[m]).max() < 1e-4


def test_near_rig_per_pixel_directions_and_falloff_differ_from_far(rgb_variant):
    """The near-light reference is not the far one: a test of the closed form itself."""
    from msps_render.render import render_frame

    spec = rig_sphere({"layout": "grid", "grid": {"rows": 2, "cols": 2, "pitch": 1.5, "plane_distance": 2.2},
                       "capture": "sequential"})
    f = render_frame(spec, variant=rgb_variant)
    rig = rig_of_spec(spec)
    far = Rig(rig.light_dirs, rig.crosstalk, shots=rig.shots)
    P, N, inside = sphere_points(RES, 2)
    ref_far = lambertian_shots(far, N, np.asarray(RHO), P).mean(3)
    inner = binary_erosion(inside.all(-1), iterations=2)
    sel = inner[None, ..., None] & (ref_far > 0.05 * ref_far.max())
    assert (np.abs(f.shots[sel] - ref_far[sel]) / ref_far[sel]).mean() > 0.05


def test_sequential_sums_to_multiplexed_and_to_per_light_reference(rgb_variant):
    """Linearity: one image per light summed = all lights in one shot; the one-pass render of N lights
    agrees with Mitsuba's own per-light renders (same expectation; 64 spp noise)."""
    from msps_render.render import render_frame
    from msps_render.render.scene_dict import with_lights

    seq = rig_sphere({"layout": "ring", "n_lights": 5, "slant_deg": 40, "capture": "sequential"})
    mux = seq.model_copy(update={"rig": seq.rig.model_copy(update={"shots": (tuple(range(5)),),
                                                                     "allow_unseparable": True})})
    fs, fm = render_frame(seq, variant=rgb_variant), render_frame(mux, variant=rgb_variant)
    assert np.allclose(fs.shots.sum(0), fm.shots[0], rtol=1e-5, atol=1e-7)
    ref = render_frame(with_lights(mux, "per-light"), variant=rgb_variant)
    inner = binary_erosion(fm.mask, iterations=2)
    rel = np.abs(ref.shots[0][inner] - fm.shots[0][inner]).mean() / fm.shots[0][inner].mean()
    assert rel < 0.01


def test_compose_shots_is_linear_channel_map():
    rng = np.random.default_rng(0)
    per = rng.uniform(0, 1, (4, 5, 6, 3)).astype(np.float32)
    env = rng.uniform(0, 0.1, (5, 6, 3)).astype(np.float32)
    spec = RigSpec(channels=((0.2, 0.3, 0.5), (1.0, 0.0, 0.0)), channel_names=("a", "b"), shots=((0, 3), (1,), (2,)),
                   nominal_dirs=((0, 0, 1),) * 4, nominal_rgb=((1, 1, 1),) * 4)
    out = compose_shots(spec, per, env)
    W = np.array(spec.channels, np.float32)
    assert out.shape == (3, 5, 6, 2)
    assert np.allclose(out[0], (per[0] + per[3] + env) @ W.T, atol=1e-6)
    assert np.allclose(out[2], (per[2] + env) @ W.T, atol=1e-6)


# ------------------------------------------------------------------ the baseline on any rig
@pytest.mark.parametrize("near", [False, True])
def test_baseline_recovers_lambertian_normals_on_any_rig(rgb_variant, near):
    """Grey Lambertian sphere, 12 lights, sequential: least squares over all readings of the unshadowed
    pixels recovers the normal to < 0.5 deg (pixel-footprint averaging and 64-spp noise); near lights
    need the per-pixel directions and fall-off from the surface points."""
    from msps_render.models.baseline import lambertian_ps_rig
    from msps_render.render import render_frame

    rig = ({"layout": "grid", "grid": {"rows": 3, "cols": 4, "pitch": 1.0, "plane_distance": 3.0}} if near else
           {"layout": "hemisphere", "n_lights": 12, "slant_range_deg": [5, 50]})
    spec = rig_sphere({**rig, "capture": "sequential"})
    spec = spec.model_copy(update={"materials": (lambertian((0.5, 0.5, 0.5)),)})
    f = render_frame(spec, variant=rgb_variant)
    r = rig_of_spec(spec)
    from msps_render.rig import pixel_light_dirs
    L = pixel_light_dirs(r, f.points if near else np.zeros_like(f.normal))
    lit = binary_erosion(f.mask, iterations=3) & ((L * f.normal[None]).sum(-1) > 0.05).all(0)
    n = lambertian_ps_rig(f.shots, r, f.mask, f.points)
    err = np.degrees(np.arccos(np.clip((n * f.normal).sum(-1), -1, 1)))[lit]
    assert lit.sum() > 1000
    assert err.mean() < 0.5, err.mean()
    if near:  # ignoring the near geometry is visibly wrong: the check above is not vacuous
        n_far = lambertian_ps_rig(f.shots, Rig(r.light_dirs, r.crosstalk, shots=r.shots), f.mask)
        e_far = np.degrees(np.arccos(np.clip((n_far * f.normal).sum(-1), -1, 1)))[lit]
        assert e_far.mean() > 3 * max(err.mean(), 0.3)


def test_baseline_discard_drops_shadowed_shots():
    """Synthetic readings: a pixel whose darkest shots are cast-shadowed (0) is solved exactly once the
    darkest are dropped, and biased without."""
    from msps_render.models.baseline import lambertian_ps_rig

    rng = np.random.default_rng(3)
    D = np.array([[np.sin(s) * np.cos(t), np.sin(s) * np.sin(t), np.cos(s)]
                  for s, t in zip(np.radians(rng.uniform(10, 60, 10)), np.radians(np.arange(10) * 36))])
    n = np.array([0.3, -0.2, 0.93]); n /= np.linalg.norm(n)
    C = np.ones((1, 10))
    I = 0.7 * np.maximum(D @ n, 0)
    order = np.argsort(I)
    I[order[:2]] = 0.0  # cast shadows hide the two darkest lights
    shots = I[:, None, None, None].repeat(1, 1)
    rig = Rig(D, C, shots=tuple((k,) for k in range(10)))
    plain = lambertian_ps_rig(shots, rig)[0, 0]
    robust = lambertian_ps_rig(shots, rig, discard=(0.2, 0.0))[0, 0]
    ang = lambda a: np.degrees(np.arccos(np.clip(a @ n, -1, 1)))
    assert ang(robust) < 1e-4
    assert ang(plain) > 0.5


# ------------------------------------------------------------------ config, light files, bad input
def test_three_light_presets_keep_their_config_hash():
    """Configs without a [scene.rig] serialise and hash as before the rig existed (v0.6), so today's
    presets write the same shards, byte for byte (checked by rendering when this landed)."""
    from msps_render.pipeline.config import config_hash, load_config

    pinned = {"paper-train": "2b319df25a2768b5062020caabf78d54e585e3256f04ede26ccf469bfe21c817",
              "train": "2ca6727c3b7946687f008a728cd4ad7a778efe69e7f1c66b4e1c3b1531da841d",
              "spectral-train": "86c9c18647fc553c34b9e7dc7c4afe01b0d2d43724d1eab83c18e62747b6ee0d"}
    for name, h in pinned.items():
        assert config_hash(load_config(name)) == h, name
    spec = sample_scene(load_config("paper-train").scene, np.random.default_rng(0))
    assert "rig" not in json.loads(spec.to_json())


def test_layouts():
    rng = np.random.default_rng(0)
    for cfg, n in [({"layout": "three"}, 3), ({"layout": "ring", "n_lights": 7}, 7),
                   ({"layout": "hemisphere", "n_lights": 96, "slant_range_deg": [0, 75]}, 96),
                   ({"layout": "grid", "grid": {"rows": 5, "cols": 4}}, 20)]:
        lights, spec = sample_rig(RigConfig.model_validate(cfg), rng)
        assert len(lights) == n == len(spec.shots)
        d = np.array([l.direction for l in lights])
        assert np.allclose(np.linalg.norm(d, axis=1), 1) and (d[:, 2] > 0).all()
    lights, _ = sample_rig(RigConfig.model_validate({"layout": "hemisphere", "n_lights": 500,
                                                     "slant_range_deg": [20, 60]}), rng)
    slant = np.degrees(np.arccos([l.direction[2] for l in lights]))
    assert slant.min() >= 20 - 1e-6 and slant.max() <= 60 + 1e-6
    # uniform in solid angle: cos(slant) spread evenly over [cos 60, cos 20]
    z = np.sort([l.direction[2] for l in lights])
    assert np.abs(z - np.linspace(np.cos(np.radians(60)), np.cos(np.radians(20)), 500)).max() < 0.01


def test_random_hemisphere_is_per_frame_and_seeded():
    cfg = RigConfig.model_validate({"layout": "hemisphere", "n_lights": 8, "sampling": "random"})
    a = sample_rig(cfg, np.random.default_rng(1))[0]
    b = sample_rig(cfg, np.random.default_rng(1))[0]
    c = sample_rig(cfg, np.random.default_rng(2))[0]
    assert a == b and a != c


def test_calibration_errors_keep_truth_beside_nominal():
    cfg = RigConfig.model_validate({"layout": "ring", "n_lights": 6, "errors": {"jitter_deg": 5,
                                    "intensity_error": 0.2, "colour_error": 0.1}})
    lights, spec = sample_rig(cfg, np.random.default_rng(0))
    true = np.array([l.direction for l in lights])
    nominal = np.array(spec.nominal_dirs)
    ang = np.degrees(np.arccos(np.clip((true * nominal).sum(1), -1, 1)))
    assert (ang <= 5 + 1e-9).all() and ang.max() > 0.5
    ratio = np.array([l.rgb for l in lights]) / np.array(spec.nominal_rgb)
    assert np.abs(ratio - 1).max() < 0.2 * 1.1 + 0.1 and np.abs(ratio - 1).max() > 0.01


def test_light_files_round_trip_and_bad_rows(tmp_path):
    D = np.array([[0.1, 0.2, 0.97467943], [0.0, 0.0, 1.0], [-0.5, 0.1, 0.86023253]])
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    E = np.array([[1.0, 0.9, 0.8], [1.1, 1.0, 0.9], [0.7, 0.7, 0.7]])
    write_light_files(tmp_path, D, E)
    d, e = read_light_file(tmp_path / "light_directions.txt")
    assert np.allclose(d, D) and np.allclose(e, E)
    bad = tmp_path / "bad"
    bad.mkdir()
    cases = {"0.1 0.2\n": "2 columns", "0.5 0.5 0.5\n": "not unit", "0.6 0 -0.8\n": "below the horizon",
             "a b c\n": "numbers"}
    for text, why in cases.items():
        (bad / "light_directions.txt").write_text(text)
        with pytest.raises(InputError) as e:
            read_light_file(bad / "light_directions.txt")
        assert why in str(e.value) and "light_directions.txt" in str(e.value)


def test_file_layout_reads_intensities(tmp_path):
    D = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8], [-0.6, 0.0, 0.8]])
    E = np.array([[1.0, 1.0, 1.0], [2.0, 2.0, 2.0], [1.0, 0.5, 0.25], [1.0, 1.0, 1.0]])
    write_light_files(tmp_path, D, E)
    cfg = RigConfig.model_validate({"layout": "file", "file": str(tmp_path / "light_directions.txt"),
                                    "irradiance": 2.0})
    lights, spec = sample_rig(cfg, np.random.default_rng(0))
    assert len(lights) == 4
    assert np.allclose([l.rgb for l in lights], 2.0 * E)
    assert np.allclose(spec.nominal_dirs, D)


@pytest.mark.parametrize("rig,why", [
    ({"layout": "ring", "n_lights": 4, "capture": "multiplexed"}, "cannot be separated"),
    ({"layout": "ring", "n_lights": 4, "capture": [[0, 1], [7]]}, "names light 7"),
    ({"layout": "ring", "n_lights": 2, "colours": [[1, 1, 1]]}, "1 entries for 2 lights"),
    ({"layout": "hemisphere", "slant_range_deg": [10, 95]}, "slant_range_deg"),
    ({"layout": "file"}, "needs file"),
])
def test_bad_rig_config_is_one_line(rig, why):
    from msps_render.config_io import validate

    with pytest.raises(InputError) as e:
        validate(SceneConfig, {"rig": rig}, "preset.toml")
    assert why in str(e.value)
    assert "\n" not in str(e.value)


def test_missing_light_file_is_one_line_when_a_frame_is_drawn():
    """A preset naming a light file (e.g. under $MSPS_TEST_DATA) validates without it, as mesh presets do;
    drawing a frame names the file."""
    cfg = RigConfig.model_validate({"layout": "file", "file": "/nonexistent/light_directions.txt"})
    with pytest.raises(InputError, match="light_directions.txt.*not found"):
        sample_rig(cfg, np.random.default_rng(0))


def test_point_light_inside_bounding_sphere_is_refused():
    cfg = RigConfig.model_validate({"layout": "grid", "grid": {"rows": 3, "cols": 3, "pitch": 0.1,
                                                               "plane_distance": 1.2}})
    ok = sample_rig(cfg, np.random.default_rng(0))  # 1.2 away: outside the unit sphere
    assert len(ok[0]) == 9
    with pytest.raises(Exception) as e:
        RigConfig.model_validate({"layout": "ring", "kind": "point", "distance": 0.8})
    assert "distance" in str(e.value)


def test_multiplexed_allowed_explicitly_for_universal_methods():
    cfg = RigConfig.model_validate({"layout": "ring", "n_lights": 8, "capture": "multiplexed",
                                    "allow_unseparable": True})
    assert cfg.shot_list(8) == (tuple(range(8)),)


# ------------------------------------------------------------------ shards, format 2
def test_rig_dataset_writes_format_2_and_verifies(tmp_path):
    from msps_render.dataset import verify_dataset
    from msps_render.dataset import schema as K
    from msps_render.dataset.reader import (iter_rig_frames, open_shard, read_patches, read_rig_patches,
                                            rig_shape)
    from cli_helpers import cli

    out = tmp_path / "ds"
    r = cli("render", "demo-rig", "--out", out, "--set", "dataset.n_shards=1", "--set", "dataset.frames_per_shard=1",
            "--set", "scene.camera.width=64", "--set", "scene.camera.height=64", "--set", "dataset.patches.stride=8")
    assert r.returncode == 0, r.stderr[-2000:]
    assert verify_dataset(out) == {}
    shard = next((out / "shards").glob("*.h5"))
    with open_shard(shard) as h:
        assert h.attrs[K.ATTR_FORMAT_VERSION] == 2
        assert rig_shape(h) == (8, 3)
        p = read_rig_patches(h)
        assert p["image"].ndim == 5 and p["image"].shape[1:] == (8, 32, 32, 3)
        with pytest.raises(InputError, match="dual-cue"):
            read_patches(h)
    (f,) = list(iter_rig_frames(shard))
    # every patch is a window of the stored whole-frame shots
    y, x = 0, 0
    with open_shard(shard) as h:
        y, x = h[K.PATCH_YX][0]
    assert np.array_equal(p["image"][0].astype(np.float32), f.shots[:, y:y + 32, x:x + 32].astype(np.float16).astype(np.float32))


def test_unknown_format_version_is_one_line(tmp_path):
    import h5py

    from msps_render.dataset.reader import format_version, open_shard

    p = tmp_path / "shard-00000.h5"
    with h5py.File(p, "w") as h:
        h.attrs["format_version"] = 9
    with open_shard(p) as h, pytest.raises(InputError) as e:
        format_version(h)
    assert "shard-00000.h5" in str(e.value) and "unknown shard format version 9" in str(e.value)


def test_three_light_rig_in_format_2_reads_as_the_dual_cue_reads_format_1(tmp_path):
    """A `[scene.rig]` of three coloured lights in one RGB shot writes format 2 (one shot per patch); the
    dual-cue network's loader reads it as it reads today's shards: (N, 3, P, P) images."""
    from cli_helpers import render_tiny
    from msps_render.data import PatchDataset

    out = render_tiny('''
[dataset]
n_shards = 1
frames_per_shard = 1
[dataset.patches]
size = 32
stride = 16
[scene.shape]
source = "sphere"
[scene.materials]
min_count = 1
max_count = 1
[scene.rig]
layout = "three"
capture = "multiplexed"
colours = [[0.92, 0.04, 0.04], [0.04, 0.92, 0.04], [0.04, 0.04, 0.92]]
[scene.camera]
width = 64
height = 64
[scene.integrator]
spp = 4
''', tmp_path)
    ds = PatchDataset(out)
    b = ds[0]
    assert b["image"].shape == (3, 32, 32) and b["light_dirs"].shape == (3, 3) and b["crosstalk"].shape == (3, 3)
    assert np.allclose(np.asarray(b["crosstalk"]).sum(0), 3.0, atol=1e-5)  # irradiance 3 x columns summing to 1


def test_rig_render_resumes_to_the_same_bytes(tmp_path):
    """Kill-and-resume for rig datasets: a shard removed after the run is re-rendered byte-identically."""
    from cli_helpers import cli, llvm_forced
    from msps_render.dataset.digest import file_digest

    with llvm_forced() as v:
        if v is None:
            pytest.skip("LLVM variant unavailable")
        args = ["render", "demo-rig", "--out", tmp_path / "d", "--set", "dataset.frames_per_shard=1",
                "--set", "scene.camera.width=64", "--set", "scene.camera.height=64", "--set",
                "dataset.patches.stride=8", "--workers", "1"]
        assert cli(*args).returncode == 0
        shard = tmp_path / "d" / "shards" / "shard-00001.h5"
        before = file_digest(shard)
        shard.unlink()
        r = cli(*args, "--resume")
        assert r.returncode == 0, r.stderr[-1500:]
        assert file_digest(shard) == before


def test_sensor_model_records_every_shot(rgb_variant):
    """A [sensor] on a rig: each shot quantised to the sensor's levels at one exposure (no longer clean)."""
    from msps_render.render import render_frame
    from msps_render.render.sensor import SensorConfig, apply_sensor

    spec = rig_sphere({"layout": "ring", "n_lights": 4, "slant_deg": 40, "capture": "sequential"}, spp=4, res=48)
    f = render_frame(spec, variant=rgb_variant)
    cfg = SensorConfig(enabled=True, bits=8, poisson=False, read_noise_e=0.0)
    g = apply_sensor(f, cfg, np.random.default_rng(0))
    exp = g.meta["sensor"]["shots_exposure_used"]
    levels = g.shots * exp * 255
    assert np.allclose(levels, np.round(levels), atol=1e-3)  # 8-bit codes
    assert not np.array_equal(g.shots, f.shots) and np.abs(g.shots - np.minimum(f.shots, 1 / exp)).max() <= 0.5 / 255 / exp + 1e-6


@pytest.mark.parametrize("text,why", [("0.1 0.2\n", "2 columns"), ("0.6 0 -0.8\n", "below the horizon")])
def test_render_with_a_bad_light_file_is_one_line_and_writes_nothing(tmp_path, text, why):
    from cli_helpers import cli, one_line_error

    lights = tmp_path / "light_directions.txt"
    lights.write_text(text)
    cfg = tmp_path / "lab.toml"
    cfg.write_text(f'[dataset]\nn_shards = 1\nframes_per_shard = 1\n[scene.rig]\nlayout = "file"\nfile = "{lights}"\n')
    r = cli("render", cfg, "--out", tmp_path / "out")
    line = one_line_error(r)
    assert "light_directions.txt" in line and why in line
    assert not (tmp_path / "out").exists()
