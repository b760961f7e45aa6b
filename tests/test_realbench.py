"""`msps bench-real` (issue 20 item 4): real captures in the DiLiGenT layout scored against ground truth.

(a) A synthetic, exact capture: an orthographic Lambertian sphere of grey, spatially varying albedo
under six white-ish lights of known direction and RGB intensity (three near the rig's layout, three
decoys), written as 16-bit linear PNGs with Normal_gt.mat holding a zero-normal hole inside the mask.
(b) The four DiLiGenT objects of ../shared/data (skipped when absent): the numbers the benchmark
reproduces.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import cli, one_line_error
from msps_render.io.png16 import write_png
from msps_render.testing import write_sphere_capture

# (slant, tilt): 1, 3, 5 are near the paper's layout (30 deg; 0/120/240), the rest decoys
LIGHTS = [(15, 60), (28, 4), (45, 10), (31, 118), (42, 250), (29, 243)]
NEAR = [1, 3, 5]
SIZE = 48  # >= the network's 40x40 tile
HOLE = (slice(20, 24), slice(22, 26))  # 16 mask pixels whose ground-truth normal is (0, 0, 0)
DILIGENT = Path(__file__).resolve().parents[2] / "shared" / "data" / "diligent"


def make_capture(d: Path, seed: int = 0, gt: str = "mat") -> dict:
    # the mask is the central cap (normal slant < ~53 deg): every light near the layout (slant <= 31 deg)
    # lights all of it (n . l >= cos 84 deg > 0), so the images follow the unshadowed Lambertian model exactly
    cap = write_sphere_capture(d, LIGHTS, SIZE, np.random.default_rng(seed), (0.6, 1.8),
                               mask=lambda n, sphere: sphere & (n[..., 2] > 0.6), mask_channels=3)
    n, mask, L, E, names = cap["normal"], cap["mask"], cap["L"], cap["E"], cap["names"]
    gtn = n.copy()
    gtn[HOLE] = 0.0
    assert mask[HOLE].all()
    if gt == "mat":
        import scipy.io

        scipy.io.savemat(d / "Normal_gt.mat", {"Normal_gt": gtn})
    else:
        from msps_render.io.png16 import encode_normal

        write_png(d / "Normal_gt.png", encode_normal(gtn, np.ones_like(mask)))  # zero normal = mid grey
    return {"normal": n, "mask": mask, "L": L, "E": E, "names": names}


def _no_out(tmp_path: Path, out: Path) -> None:
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no staging directory left


def test_read_photo_keeps_16_bits_and_reads_8_bits(tmp_path):
    from msps_render.compose import read_photo
    from msps_render.io.png16 import encode_png

    rng = np.random.default_rng(3)
    a16 = rng.integers(256, 65536, size=(5, 7, 3), dtype=np.uint16)  # every value above 8 bits
    a16[0, 0] = (65535, 257, 4095)
    (tmp_path / "a16.png").write_bytes(encode_png(a16))
    got = read_photo(tmp_path / "a16.png")
    assert got.shape == (5, 7, 3) and np.array_equal(np.round(got * 65535).astype(np.uint16), a16)
    a8 = rng.integers(0, 256, size=(5, 7, 3), dtype=np.uint8)
    write_png(tmp_path / "a8.png", a8)
    assert np.array_equal(np.round(read_photo(tmp_path / "a8.png") * 255).astype(np.uint8), a8)


def test_lambertian_recovers_the_synthetic_sphere_and_leaves_out_zero_normals(tmp_path):
    from msps_render.models.realbench import evaluate_real, lambertian_method, load_real_object

    cap = make_capture(tmp_path / "sphPNG")
    obj = load_real_object(tmp_path / "sphPNG")
    assert obj.name == "sph" and obj.images == [cap["names"][i] for i in NEAR]
    assert obj.light_indices == [i + 1 for i in NEAR] and max(obj.deviation_deg) < 3.5
    hole = int(np.zeros((SIZE, SIZE), bool)[HOLE].size)
    assert obj.left_out == hole and obj.valid.sum() == cap["mask"].sum() - hole
    r = evaluate_real([obj], [lambertian_method()]).summary
    row = r["objects"]["sph"]
    assert row["left_out_zero_normal"] == hole and row["methods"]["lambertian"]["n_pixels"] == obj.valid.sum()
    # Exact model (grey Lambertian, every scored pixel lit by all three chosen lights, their measured
    # directions and intensities known), so the error is only 16-bit quantisation of the photos
    # (relative <= 1/(2*65535*0.01) for the dimmest scored pixel) amplified by the conditioning of M L,
    # plus the 6-decimal text of the lights: measured mean 0.0009-0.0014 deg (seeds 0-2).  0.5 deg (the
    # brief's bound) is >300x that, and still far below a wrong light choice, a missing intensity
    # division (the RGB intensities here differ by up to 3x: measured 20-38 deg) or a wrong crosstalk.
    mae = row["methods"]["lambertian"]["mae_deg"]
    assert mae < 0.5, mae
    assert mae < 0.05, mae  # what the exact model actually achieves (see above)
    # the zero-normal pixels really are out: scoring them would count 90 deg each
    assert row["methods"]["lambertian"]["median_deg"] < 0.05


def test_normal_gt_png_fallback_and_skip_changes_the_chosen_captures(tmp_path):
    from msps_render.models.realbench import evaluate_real, lambertian_method, load_real_object

    make_capture(tmp_path / "pngPNG", gt="png")
    obj = load_real_object(tmp_path / "pngPNG")
    assert obj.gt_source == "Normal_gt.png" and obj.left_out == 16
    mae = evaluate_real([obj], [lambertian_method()]).summary["objects"]["png"]["methods"]["lambertian"]["mae_deg"]
    assert mae < 0.05, mae  # 16-bit normals: quantisation ~1e-3 deg
    # skipping 004.png (31, 118): tilt 120 goes to the next nearest light left, 001.png (15, 60);
    # skipping 002.png (28, 4): tilt 0 goes to 003.png (45, 10)
    assert load_real_object(tmp_path / "pngPNG", skip=["004.png"]).images == ["002.png", "001.png", "006.png"]
    skipped = load_real_object(tmp_path / "pngPNG", skip=["002.png"])
    assert skipped.images == ["003.png", "004.png", "006.png"] and skipped.skipped == ["002.png"]
    assert skipped.light_indices == [3, 4, 6]  # rows of the original light_directions.txt, not of the rest


def test_cli_writes_the_report_and_skip_is_recorded(tmp_path):
    make_capture(tmp_path / "aPNG", seed=1)
    make_capture(tmp_path / "bPNG", seed=2)
    out = tmp_path / "out"
    r = cli("bench-real", tmp_path / "aPNG", tmp_path / "bPNG", "--out", out, "--skip", "b/002.png",
            "--steps", "none", "--threads", "1", env_extra={"OMP_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr
    assert "| a |" in r.stdout and "**mean**" in r.stdout
    res = json.loads((out / "results.json").read_text())
    assert list(res["methods"]) == ["net", "lambertian"] and "validation only" in res["note"]
    a, b = res["objects"]["a"], res["objects"]["b"]
    assert a["images"] == ["002.png", "004.png", "006.png"] and "002.png" not in b["images"]
    assert b["skipped"] == ["002.png"] and a["skipped"] == []
    assert a["left_out_zero_normal"] == 16 and a["methods"]["lambertian"]["mae_deg"] < 0.05
    assert set(a["methods"]["net"]) >= {"mae_deg", "median_deg", "n_pixels", "ratio_to_lambertian"}
    assert set(res["mean"]["net"]) >= {"mae_deg", "median_deg", "ratio_to_lambertian"}
    assert res["pooled"]["lambertian"]["n_pixels"] == a["n_pixels"] + b["n_pixels"]
    names = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
    assert names == ["a/error_lambertian.png", "a/error_net.png", "a/normal_lambertian.png", "a/normal_net.png",
                     "b/error_lambertian.png", "b/error_net.png", "b/normal_lambertian.png", "b/normal_net.png",
                     "figure.png", "results.json", "results.md"]
    md = (out / "results.md").read_text()
    assert "| object | net MAE (median) | lambertian MAE (median) | net / Lambertian" in md
    from msps_render.io.png16 import read_png

    assert read_png(out / "a" / "error_net.png").shape == (SIZE, SIZE, 3)
    assert read_png(out / "figure.png").shape[0] > 200


def test_bad_inputs_one_line_exit_1_nothing_written(tmp_path):
    out = tmp_path / "out"

    def broken(name, damage):
        d = tmp_path / name
        make_capture(d)
        damage(d)
        return d

    cases = [
        (broken("c1PNG", lambda d: (d / "light_directions.txt").unlink()), [], "light_directions.txt: missing"),
        # 001.png is not one of the three chosen: a broken folder is refused all the same
        (broken("c2PNG", lambda d: (d / "001.png").unlink()), [],
         "001.png: image file not found (listed in filenames.txt)"),
        (broken("c3PNG", lambda d: (d / "mask.png").unlink()), [], "mask.png: missing"),
        (broken("c4PNG", lambda d: (d / "Normal_gt.mat").unlink()), [],
         "Normal_gt.mat: missing, and no Normal_gt.png"),
        (broken("c5PNG", lambda d: None), ["--skip", "097.png"], "097.png: --skip names no image"),
    ]
    for folder, extra, message in cases:
        r = cli("bench-real", folder, "--out", out, *extra)
        line = one_line_error(r)
        assert message in line and str(folder) in line, line
        _no_out(tmp_path, out)
    # a skip naming an object that was not given, and a bad --checkpoint spec
    r = cli("bench-real", tmp_path / "c5PNG", "--out", out, "--skip", "cat/001.png")
    assert "no capture folder of object 'cat'" in one_line_error(r)
    r = cli("bench-real", tmp_path / "c5PNG", "--out", out, "--checkpoint", f"a={tmp_path / 'none.pt'}")
    assert "none.pt: checkpoint not found" in one_line_error(r)
    _no_out(tmp_path, out)


def test_help_says_validation_only():
    from typer.testing import CliRunner

    import msps_render.models.realbench as rb
    from msps_render.cli import app

    r = CliRunner().invoke(app, ["bench-real", "-h"], terminal_width=200)
    assert r.exit_code == 0 and "validation only" in " ".join(r.output.split())
    assert "VALIDATION ONLY" in rb.__doc__


# measured by this benchmark (masked composition, the shipped checkpoint, v0.5): see the test below
# (v0.4: ball 7.31, cat 12.22, pot1 18.27, goblet 17.70)
DILIGENT_LAMBERTIAN = {"ball": 21.27, "cat": 12.89, "pot1": 28.93, "goblet": 26.34}
DILIGENT_NET = {"ball": 6.16, "cat": 12.20, "pot1": 17.66, "goblet": 17.69}
# the earlier session's numbers (with v0.4, models/dualcue-cpu-v0.4.pt): the same three captures, but the
# composed image fed to the network with its background (outside mask.png) not zeroed
DILIGENT_NET_UNMASKED = {"ball": 7.48, "cat": 12.32, "pot1": 18.32, "goblet": 18.27}


@pytest.mark.skipif(not DILIGENT.is_dir(), reason="../shared/data/diligent absent")
def test_diligent_numbers_reproduce(tmp_path):
    out = tmp_path / "bench"
    folders = [DILIGENT / f"{o}PNG" for o in DILIGENT_LAMBERTIAN]
    if not all(f.is_dir() for f in folders):
        pytest.skip("a DiLiGenT object folder is missing")
    r = cli("bench-real", *folders, "--out", out, "--steps", "none", "--threads", "1",
            env_extra={"OMP_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr
    res = json.loads((out / "results.json").read_text())
    for o, want in DILIGENT_LAMBERTIAN.items():
        row = res["objects"][o]
        assert abs(row["methods"]["lambertian"]["mae_deg"] - want) < 0.05, (o, row["methods"])
        assert abs(row["methods"]["net"]["mae_deg"] - DILIGENT_NET[o]) < 0.1, (o, row["methods"])
        assert row["left_out_zero_normal"] == 0 and row["n_pixels"] == row["n_mask"]
        assert max(row["deviation_deg"]) < 4.0
    assert res["objects"]["goblet"]["images"] == ["085.png", "024.png", "017.png"]
    assert res["mean"]["net"]["ratio_to_lambertian"] < 0.7
    # Why the network numbers differ from the earlier session's (7.48 / 12.32 / 18.32 / 18.27): that
    # measurement fed the network the composition with the background outside mask.png left as
    # photographed (dark but not zero); `msps compose` and this benchmark zero it, as in training renders.
    # The Lambertian numbers are per pixel, so the same either way.  Reproduce the earlier numbers:
    import torch

    from msps_render.compose import read_capture, select_lights, read_photo
    from msps_render.models.checkpoint import load_checkpoint
    from msps_render.models.metrics import angular_error_deg
    from msps_render.models.predict import default_checkpoint, predict_image
    from msps_render.models.realbench import load_real_object

    torch.set_num_threads(1)
    model = load_checkpoint(default_checkpoint().parent / "dualcue-cpu-v0.4.pt")[0]
    for f in folders:
        obj = load_real_object(f)
        cap = read_capture(f)
        idx, _ = select_lights(cap)
        raw = sum(read_photo(cap.images[i], linear=True) / cap.intensities[i] * obj.crosstalk[:, k] for k, i in enumerate(idx))
        assert np.allclose(raw[obj.mask], obj.image[obj.mask], atol=1e-6) and not obj.image[~obj.mask].any()
        n = predict_image(model, raw.astype(np.float32), obj.mask)
        mae = float(angular_error_deg(n[obj.valid], obj.normal_gt[obj.valid]).mean())
        assert abs(mae - DILIGENT_NET_UNMASKED[obj.name]) < 0.1, (obj.name, mae)


# The default steps of bench-real (`selfcal+netcal`, chosen by docs/history.md "Stage 14") with the shipped
# checkpoint (v0.5): the colour read off the network's normals, one round (models/netcal.py; settings chosen
# on validation frames, "Stage 13").  goblet: the agreement gate refuses it (a metal's ratios spread), so
# it keeps the network's number.  The old `--netcal` flag gives the same column beside the raw network.
DILIGENT_NETCAL = {"ball": 4.53, "cat": 12.18, "pot1": 14.35, "goblet": 17.69}


@pytest.mark.skipif(not DILIGENT.is_dir(), reason="../shared/data/diligent absent")
def test_diligent_netcal_numbers_reproduce(tmp_path):
    folders = [DILIGENT / f"{o}PNG" for o in DILIGENT_LAMBERTIAN]
    if not all(f.is_dir() for f in folders):
        pytest.skip("a DiLiGenT object folder is missing")
    out = tmp_path / "bench"
    r = cli("bench-real", *folders, "--out", out, "--threads", "1", env_extra={"OMP_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr
    res = json.loads((out / "results.json").read_text())
    assert list(res["methods"]) == ["net+selfcal+netcal", "lambertian"]  # no flag: the default steps
    for o, want in DILIGENT_NETCAL.items():
        got = res["objects"][o]["methods"]
        assert abs(got["net+selfcal+netcal"]["mae_deg"] - want) < 0.1, (o, got)
        assert got["net+selfcal+netcal"]["mae_deg"] < got["lambertian"]["mae_deg"]
    # the reading of "mean": mean MAE over the objects / the Lambertian mean MAE (v0.5 alone 0.60)
    mean = lambda k: np.mean([res["objects"][o]["methods"][k]["mae_deg"] for o in DILIGENT_NETCAL])  # noqa: E731
    assert abs(mean("net+selfcal+netcal") / mean("lambertian") - 0.545) < 0.01
    # the report's own mean row says the same: one definition of the ratio (a ratio of means)
    assert res["mean"]["net+selfcal+netcal"]["ratio_to_lambertian"] == pytest.approx(
        mean("net+selfcal+netcal") / mean("lambertian"), rel=1e-9)


def test_selfcal_and_refine_columns(tmp_path):
    """`--selfcal --refine`: a refined twin for each network (none for the baseline); this sphere's albedo
    varies across it, so the one-albedo test refuses it and the refined columns equal the network's."""
    make_capture(tmp_path / "aPNG", seed=1)
    out = tmp_path / "out"
    r = cli("bench-real", tmp_path / "aPNG", "--out", out, "--selfcal", "--refine", "--threads", "1",
            env_extra={"OMP_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr
    res = json.loads((out / "results.json").read_text())
    assert list(res["methods"]) == ["net", "lambertian", "net+selfcal", "lambertian+selfcal", "net+refine",
                                    "net+selfcal+refine"]
    a = res["objects"]["a"]["methods"]
    assert a["net+refine"]["mae_deg"] == a["net"]["mae_deg"]
    assert a["net+selfcal+refine"]["mae_deg"] == a["net+selfcal"]["mae_deg"]
    assert res["settings"]["refine"] is True


def test_segments_columns(tmp_path):
    """`--selfcal --segments --refine`: a +selfcal+segments twin of each method (after the +selfcal ones), each
    network's refined twin refines on the image its base method saw; recorded in the settings."""
    make_capture(tmp_path / "aPNG", seed=1)
    out = tmp_path / "out"
    r = cli("bench-real", tmp_path / "aPNG", "--out", out, "--selfcal", "--segments", "--refine", "--threads", "1",
            env_extra={"OMP_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr
    res = json.loads((out / "results.json").read_text())
    assert list(res["methods"]) == ["net", "lambertian", "net+selfcal", "lambertian+selfcal", "net+selfcal+segments",
                                    "lambertian+selfcal+segments", "net+refine", "net+selfcal+refine",
                                    "net+selfcal+segments+refine"]
    assert res["settings"]["segments"] is True
    a = res["objects"]["a"]["methods"]
    assert all(np.isfinite(a[m]["mae_deg"]) for m in res["methods"])


def test_bench_and_predict_read_a_normal_map_alike(tmp_path):
    """One rule (io/normals.py): `bench-real`'s Normal_gt.png and `predict --normal-gt` give the same unit
    normals, and a white pixel (|n| = 1.73 once decoded) is no normal to either (it was one to the bench)."""
    from msps_render.io.png16 import write_png
    from msps_render.models.predict import read_normal_gt as predict_gt
    from msps_render.models.realbench import read_normal_gt as bench_gt

    rng = np.random.default_rng(0)
    n = rng.normal(size=(8, 8, 3))
    n[..., 2] = np.abs(n[..., 2])
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    code = np.round((n + 1) / 2 * 65535).astype(np.uint16)
    code[0, 0] = 65535  # white
    code[0, 1] = 32768  # mid grey: the zero vector
    write_png(tmp_path / "Normal_gt.png", code)
    a, src = bench_gt(tmp_path, (8, 8))
    b, valid = predict_gt(tmp_path / "Normal_gt.png", (8, 8))
    assert src.name == "Normal_gt.png"
    np.testing.assert_array_equal(a, b)
    assert not valid[0, 0] and not valid[0, 1] and valid.sum() == 62
    assert np.all(a[0, :2] == 0)
    np.testing.assert_allclose(np.linalg.norm(a[valid], axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(a[valid], n[valid], atol=1e-4)  # 16-bit quantisation
