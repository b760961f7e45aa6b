"""`msps compose` + the calibration schema + predict's geometry warning (issue 13).

The capture is synthetic and exact: an orthographic Lambertian sphere of grey,
spatially varying albedo under twelve white-ish lights of known direction and
RGB intensity, written DiLiGenT-style as 16-bit linear PNGs.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import cli, one_line_error
from msps_render.errors import InputError
from msps_render.testing import write_sphere_capture
from msps_render.scene.lights import direction_from_slant_tilt

# (slant, tilt): three near the paper's layout (30 deg; 0/120/240), the rest decoys
LIGHTS = [(15, 60), (28, 4), (45, 0), (31, 118), (45, 120), (20, 300), (29, 243), (45, 240), (60, 180),
          (38, 15), (24, 130), (50, 90)]
NEAR_PAPER = [1, 3, 6]  # indices of (28, 4), (31, 118), (29, 243)
SIZE = 64


def make_capture(d: Path, lights=LIGHTS, seed=0, with_filenames=True) -> dict:
    return write_sphere_capture(d, lights, SIZE, np.random.default_rng(seed), (0.5, 2.0),
                                with_filenames=with_filenames)


@pytest.mark.parametrize("crosstalk", [None, np.eye(3), np.array([[0.7, 0.2, 0.1], [0.1, 0.8, 0.1],
                                                                   [0.05, 0.15, 0.8]])])
def test_compose_then_lambertian_predict_recovers_the_sphere(tmp_path, crosstalk):
    from msps_render.calibration import load_calibration_file
    from msps_render.compose import compose_capture
    from msps_render.models.baseline import unshadowed
    from msps_render.models.metrics import angular_error_deg
    from msps_render.models.predict import load_rig, predict_main, predict_method

    cap = make_capture(tmp_path / "cap")
    r = compose_capture(tmp_path / "cap", tmp_path / "out", crosstalk=crosstalk)
    assert r["light_indices"] == [k + 1 for k in NEAR_PAPER] and r["warnings"] == []
    assert max(r["deviation_deg"]) < 3.5  # (28,4), (31,118), (29,243) are within ~2-3 deg of the targets
    L, M = load_calibration_file(tmp_path / "out" / "calibration.json")
    # the calibration holds the chosen lights' real directions (to the 6 decimals of the text file)
    assert np.abs(L - cap["L"][NEAR_PAPER]).max() < 2e-6
    warns = []
    predict_main(tmp_path / "out" / "image.exr", tmp_path / "pred", predict_method("lambertian"),
                 load_rig(tmp_path / "out" / "calibration.json"), mask=tmp_path / "out" / "mask.png",
                 warn=warns.append)
    assert warns == []
    n = np.load(tmp_path / "pred.npy")
    ok = unshadowed(cap["normal"], L, cap["mask"], margin=0.05)
    assert ok.sum() > 0.5 * cap["mask"].sum()
    err = angular_error_deg(n[ok], cap["normal"][ok])
    # Exact model (grey Lambertian, the same mixing as the renderer), so the error is only 16-bit
    # quantisation of the photos (relative 1/(2*65535*value) per pixel, up to ~1e-3 where n.l ~ 0.05 and
    # the albedo is 0.3) amplified by the conditioning of M L, plus 1e-6 text precision of the lights:
    # measured mean 0.003 deg, max 0.016 deg (dimmest unshadowed pixels).  Bounds ~3x / 6x above that;
    # a wrong light choice, intensity division or crosstalk mixing gives errors of degrees.
    assert err.mean() < 0.01, err.mean()
    assert err.max() < 0.1, err.max()


def test_compose_cli_and_predict_warns_about_trained_geometry(tmp_path):
    from msps_render.models.predict import load_rig, predict_main, predict_method

    make_capture(tmp_path / "cap", with_filenames=False)  # images found by name
    r = cli("compose", tmp_path / "cap", "--out", tmp_path / "o45", "--slant", "45", "--tilts", "0,120,240")
    assert r.returncode == 0, r.stderr
    assert "002.png" not in r.stdout and "003.png (0.0 deg off)" in r.stdout  # (45, 0) chosen exactly
    cal = json.loads((tmp_path / "o45" / "calibration.json").read_text())
    assert cal["info"]["light_indices"] == [3, 5, 8]
    assert sorted(p.name for p in (tmp_path / "o45").iterdir()) == ["calibration.json", "image.exr", "mask.png",
                                                                    "preview.png"]
    pytest.importorskip("torch")
    from msps_render.models.predict import default_checkpoint

    # a network trained at slant 30 only (v0.1: no recorded lights -> the model card's paper geometry);
    # the default v0.2 was trained at 20-40 deg, so 45 deg is within its tolerance (checked below)
    v01 = default_checkpoint().parent / "dualcue-cpu-v0.1.pt"
    warns = []
    predict_main(tmp_path / "o45" / "image.exr", tmp_path / "p45", predict_method(checkpoint=v01),
                 load_rig(tmp_path / "o45" / "calibration.json"), mask=tmp_path / "o45" / "mask.png", warn=warns.append)
    assert any("slant 45.0, 45.0, 45.0 deg differs from the 30 deg" in w for w in warns), warns
    assert any("takes no light input" in w for w in warns)
    # the paper layout: no warning
    r = cli("compose", tmp_path / "cap", "--out", tmp_path / "o30")
    assert r.returncode == 0, r.stderr
    warns = []
    predict_main(tmp_path / "o30" / "image.exr", tmp_path / "p30", rig=load_rig(tmp_path / "o30" / "calibration.json"),
                 mask=tmp_path / "o30" / "mask.png", warn=warns.append)
    assert warns == []
    # the CLI prints it (and still writes the prediction)
    r = cli("predict", tmp_path / "o45" / "image.exr", "--mask", tmp_path / "o45" / "mask.png", "--calibration",
            tmp_path / "o45" / "calibration.json", "--out", tmp_path / "cli45", "--checkpoint", v01)
    assert r.returncode == 0 and "warning: light slant" in r.stderr, r.stderr
    assert (tmp_path / "cli45.npy").is_file()
    # the default network records its training range (slant 20-40 deg): 45 is within 5 deg of it,
    # 55 is not
    warns = []
    predict_main(tmp_path / "o45" / "image.exr", tmp_path / "d45", rig=load_rig(tmp_path / "o45" / "calibration.json"),
                 mask=tmp_path / "o45" / "mask.png", warn=warns.append)
    assert warns == [], warns
    from msps_render.calibration import geometry_warnings
    from msps_render.models.checkpoint import load_checkpoint

    trained = load_checkpoint(default_checkpoint())[2]["train_lights"]
    assert trained["slant_deg"] == [20.0, 40.0] and trained["source"] == "training data manifests"
    far = [direction_from_slant_tilt(55, t) for t in (0, 120, 240)]
    assert any("differs from the 20-40 deg" in w for w in geometry_warnings(far, trained["crosstalk"], trained))


def test_compose_bad_captures_fail_with_one_line(tmp_path):
    make_capture(tmp_path / "cap")
    out = tmp_path / "out"
    bad = tmp_path / "bad1"
    make_capture(bad)
    (bad / "light_directions.txt").write_text("0 0 1\n0.1 0 1\n")
    (bad / "light_intensities.txt").unlink()  # optional (default 1)
    r = cli("compose", bad, "--out", out)
    assert "filenames.txt: 12 images but 2 light directions" in one_line_error(r)
    bad2 = tmp_path / "bad2"
    make_capture(bad2)
    (bad2 / "light_intensities.txt").write_text("1 1 1\n")
    r = cli("compose", bad2, "--out", out)
    assert "light_intensities.txt" in one_line_error(r)
    bad3 = tmp_path / "bad3"
    make_capture(bad3)
    (bad3 / "light_directions.txt").unlink()
    assert "light_directions.txt: missing" in one_line_error(cli("compose", bad3, "--out", out))
    bad4 = tmp_path / "bad4"
    make_capture(bad4)
    (bad4 / "007.png").write_bytes(b"not a png")
    assert "007.png" in one_line_error(cli("compose", bad4, "--out", out))
    r = cli("compose", tmp_path / "cap", "--out", out, "--crosstalk", "[[1,0],[0,1]]")
    assert "--crosstalk" in one_line_error(r)
    r = cli("compose", tmp_path / "cap", "--out", out, "--slant", "95")
    assert "slant" in one_line_error(r)
    out.mkdir()
    (out / "x").write_text("mine")
    assert "not empty" in one_line_error(cli("compose", tmp_path / "cap", "--out", out))
    assert [p.name for p in out.iterdir()] == ["x"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary directory left


@pytest.mark.parametrize("payload, message", [
    ("{", "not valid JSON"),
    ("[1, 2]", "must be a JSON object"),
    ('{"lights_dirs": []}', "unknown key 'lights_dirs' (did you mean 'light_dirs'?)"),
    ('{"light_dirs": [[0, 0, 1], [0.5, 0, 0.8]]}', "light_dirs must be 3x3, got shape [2, 3]"),
    ('{"light_dirs": [[0, 0, 1], [0.5, 0, 0.8], [0, 0.5, -0.8]]}', "light 2 points away from the camera"),
    ('{"light_dirs": [[0, 0, 1], [0, 0, 2], [0, 0.5, 0.8]]}', "coplanar"),
    ('{"light_dirs": [[0, 0, 1], [0.5, 0, 0.8], [0, 0.5, 0.8]], "slant_deg": 30}', "give one of"),
    ('{"slant_deg": "30"}', "slant_deg must be a finite number"),
    ('{"crosstalk": [[1, 0, 0], [0, 1, 0], [0, 0, -1]]}', "negative entries"),
    ('{"lights": [{"direction": [0, 0, 1]}, {"slant_deg": 30}]}', "list of 3 objects"),
    ('{"format": "lights-v2"}', "expected 'msps-calibration-1'"),
])
def test_calibration_schema_errors_name_the_file(tmp_path, payload, message):
    from msps_render.calibration import load_calibration_file

    p = tmp_path / "lights.json"
    p.write_text(payload)
    with pytest.raises(InputError) as e:
        load_calibration_file(p)
    assert str(e.value).startswith(str(p)) and message in str(e.value), str(e.value)


def test_calibration_accepted_shapes_agree(tmp_path):
    from msps_render.calibration import parse_calibration
    from msps_render.scene.lights import PAPER_CROSSTALK

    L0, M0 = parse_calibration({})
    assert np.allclose(M0, PAPER_CROSSTALK)
    L1, _ = parse_calibration({"slant_deg": 30, "tilts_deg": [0, 120, 240]})
    L2, M2 = parse_calibration({"lights": [{"slant_deg": 30, "tilt_deg": t, "rgb": list(PAPER_CROSSTALK[:, k] * 3)}
                                           for k, t in enumerate((0, 120, 240))]})
    L3, _ = parse_calibration({"light_dirs": (L0 * 2).tolist()})  # normalised on read
    for L in (L1, L2, L3):
        assert np.allclose(L, L0, atol=1e-12)
    assert np.allclose(M2, PAPER_CROSSTALK * 3)
    # predict's CLI: a bad calibration is one line, exit 1, and nothing written
    np.save(tmp_path / "img.npy", np.ones((8, 8, 3), np.float32))
    (tmp_path / "bad.json").write_text('{"light_dirs": "up"}')
    r = cli("predict", tmp_path / "img.npy", "--method", "lambertian", "--calibration", tmp_path / "bad.json",
            "--out", tmp_path / "pred")
    assert "bad.json: light_dirs must be a 3x3 array of numbers" in one_line_error(r)
    assert not (tmp_path / "pred.npy").exists()


def test_trained_geometry_comes_from_the_checkpoint_or_the_model_card(tmp_path):
    torch = pytest.importorskip("torch")  # noqa: F841
    from msps_render.calibration import geometry_warnings
    from msps_render.dataset import training_lights
    from msps_render.models.net import DualCueNet
    from msps_render.models.predict import load_rig, predict_main, predict_method
    from msps_render.models.presets import load_model_config
    from msps_render.models.checkpoint import save_checkpoint
    from msps_render.dataset import write_manifest
    from msps_render.scene.lights import PAPER_CROSSTALK

    # training_lights reads the data's manifests: a slant range widens the accepted slants
    for name, lights in (("a", {"slant_deg": 30.0, "tilts_deg": [0, 120, 240], "crosstalk": PAPER_CROSSTALK.tolist()}),
                         ("b", {"slant_deg": 30.0, "slant_range_deg": [20.0, 40.0], "tilts_deg": [0, 120, 240],
                                "crosstalk": PAPER_CROSSTALK.tolist()})):
        (tmp_path / name).mkdir()
        write_manifest(tmp_path / name, {"config": {"scene": {"lights": lights}}})
    tl = training_lights([tmp_path / "a", tmp_path / "b"])
    assert tl["slant_deg"] == [20.0, 40.0] and tl["tilts_deg"] == [0, 120, 240]
    L45 = np.array([direction_from_slant_tilt(45.0, t) for t in (0, 120, 240)])
    L38 = np.array([direction_from_slant_tilt(38.0, t) for t in (0, 120, 240)])
    assert geometry_warnings(L38, PAPER_CROSSTALK, tl) == []  # inside 20-40
    assert geometry_warnings(L38, PAPER_CROSSTALK, None)  # model card: 30 +- 5
    assert geometry_warnings(L45, PAPER_CROSSTALK, tl) == []  # 45 <= 40 + 5 deg tolerance
    L50 = np.array([direction_from_slant_tilt(50.0, t) for t in (0, 120, 240)])
    assert any("20-40 deg" in w for w in geometry_warnings(L50, PAPER_CROSSTALK, tl))
    rot = np.array([direction_from_slant_tilt(30.0, t) for t in (60, 180, 300)])
    assert any("tilts" in w for w in geometry_warnings(rot, PAPER_CROSSTALK, None))
    L30 = np.array([direction_from_slant_tilt(30.0, t) for t in (0, 120, 240)])
    assert geometry_warnings(L30, PAPER_CROSSTALK, None) == []
    assert any("crosstalk differs" in w for w in geometry_warnings(L30, np.eye(3), None))
    # predict reads train_lights from the checkpoint
    cfg = load_model_config("cpu")
    ck = save_checkpoint(tmp_path / "m.pt", DualCueNet(cfg.net_config()), cfg,
                         {"train_lights": {**tl, "slant_deg": [40.0, 40.0], "source": "training data manifests"}})
    np.save(tmp_path / "img.npy", np.ones((48, 48, 3), np.float32))
    warns = []
    predict_main(tmp_path / "img.npy", tmp_path / "p", predict_method(checkpoint=ck),
                 load_rig(light_dirs=json.dumps(L30.tolist())), warn=warns.append)
    assert any("differs from the 40 deg the network was trained for" in w for w in warns), warns


def test_a_warm_start_keeps_the_init_checkpoints_light_range():
    """A fine-tune at slant 30 from a network trained at 20-40 deg has seen 20-40: the checkpoint says so
    (else `msps predict` warns on slants the network handles); a different rig keeps the run's own record."""
    from msps_render.dataset.manifest import merge_training_lights
    from msps_render.scene.lights import PAPER_CROSSTALK

    run = {"slant_deg": [30.0, 30.0], "tilts_deg": [0, 120, 240], "crosstalk": PAPER_CROSSTALK.tolist(),
           "source": "training data manifests"}
    init = {**run, "slant_deg": [20.0, 40.0]}
    assert merge_training_lights(run, init)["slant_deg"] == [20.0, 40.0]
    assert merge_training_lights(run, None) == run and merge_training_lights(None, init) is None
    assert merge_training_lights(run, {**init, "tilts_deg": [60, 180, 300]}) == run
    assert merge_training_lights(run, {**init, "crosstalk": np.eye(3).tolist()}) == run


def test_export_checkpoint_strips_training_state(tmp_path):
    """A shipped model keeps weights, config and provenance, drops optimizer and RNG state, and takes the
    widened light range; it loads and predicts exactly as the training checkpoint does."""
    torch = pytest.importorskip("torch")
    from msps_render.models.checkpoint import export_checkpoint, load_checkpoint, save_checkpoint
    from msps_render.models.net import DualCueNet
    from msps_render.models.presets import load_model_config

    cfg = load_model_config("cpu")
    net = DualCueNet(cfg.net_config())
    opt = torch.optim.Adam(net.parameters())
    lights = {"slant_deg": [30.0, 30.0], "tilts_deg": [0, 120, 240], "crosstalk": np.eye(3).tolist(),
              "source": "training data manifests"}
    src = save_checkpoint(tmp_path / "last.pt", net, cfg, {"optimizer": opt.state_dict(), "torch_rng": torch.get_rng_state(),
                                                           "state": {"step": 7, "batch_in_epoch": 3}, "train_lights": lights})
    dst = export_checkpoint(src, tmp_path / "ship.pt", {**lights, "slant_deg": [20.0, 40.0]})
    ck = torch.load(dst, weights_only=True)
    assert "optimizer" not in ck and "torch_rng" not in ck and ck["state"] == {"step": 7}
    assert ck["train_lights"]["slant_deg"] == [20.0, 40.0]
    assert dst.stat().st_size < src.stat().st_size
    x = torch.rand(1, 3, 40, 40)
    mk = torch.ones(1, 1, 40, 40)
    a, b = load_checkpoint(src)[0], load_checkpoint(dst)[0]
    assert torch.equal(a(x, mk)[0], b(x, mk)[0])
