"""`msps eval` comparing methods in one run (issue 23) and `msps predict` panels: the compare table's
columns equal single-method runs, CIs bracket the means, figures are drawn, predict's names and MAE."""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import render_tiny

torch = pytest.importorskip("torch")

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, MSPS_THREADS="1", OMP_NUM_THREADS="1")

SWEEP = """
[dataset]
name = "tiny-compare"
seed = 5
n_shards = 1
frames_per_shard = 3
[dataset.patches]
size = 16
stride = 16
[dataset.storage]
store_frames = true
[sweep]
key = "lights.slant_deg"
values = [20.0, 30.0]
[scene.shape]
source = "primitive"
primitives = ["torus"]
[scene.camera]
width = 48
height = 48
[scene.integrator]
spp = 4
max_depth = 3
"""


@pytest.fixture(scope="module")
def setup(tmp_path_factory) -> dict:
    """A one-object, two-condition whole-frame set and three untrained checkpoints (two dual, one SCN)."""
    from msps_render.models.checkpoint import save_checkpoint
    from msps_render.models.net import DualCueNet
    from msps_render.models.presets import load_model_config
    tmp = tmp_path_factory.mktemp("compare")
    render_tiny(SWEEP, tmp)
    cks = {}
    for name, ov, seed in (("a", [], 0), ("b", [], 1), ("s", ["net.mode=scn"], 2)):
        torch.manual_seed(seed)
        cfg = load_model_config("cpu", ov)
        cks[name] = save_checkpoint(tmp / f"{name}.pt", DualCueNet(cfg.net_config()), cfg, {})
    return {"tmp": tmp, "data": tmp / "ds", **cks}


STEP_FLAGS = {"--steps", "--selfcal", "--refine", "--segments", "--netcal", "--mirror"}


def _eval(setup, out: str, *args) -> tuple[dict, str]:
    """`msps eval` on the raw networks unless steps are asked for (these tests compare checkpoints)."""
    if not STEP_FLAGS & set(map(str, args)):
        args = (*args, "--steps", "none")
    d = setup["tmp"] / out
    r = subprocess.run([sys.executable, "-m", "msps_render.cli", "eval", "--data", str(setup["data"]), "--out",
                        str(d), *map(str, args)], capture_output=True, text=True, env=ENV)
    assert r.returncode == 0, r.stderr
    return json.loads((d / "metrics.json").read_text()), r.stdout


@pytest.fixture(scope="module")
def runs(setup) -> dict:
    cmp, out = _eval(setup, "cmp", "--checkpoint", f"new={setup['a']}", "--checkpoint", setup["b"],
                     "--checkpoint", setup["s"], "--method", "lambertian")
    lamb, _ = _eval(setup, "lamb", "--method", "lambertian")
    net, _ = _eval(setup, "net", "--checkpoint", setup["a"])
    return {"cmp": cmp, "cmp_out": out, "lamb": lamb, "net": net}


def test_compare_columns_equal_single_method_runs(runs):
    cmp, lamb, net = runs["cmp"], runs["lamb"], runs["net"]
    # checkpoints first (named, unnamed dual -> net, unnamed ablation -> its mode), then the baseline
    assert list(cmp["methods"]) == cmp["table"]["methods"] == ["new", "net", "scn", "lambertian"]
    assert cmp["methods"]["scn"]["mode"] == "scn" and cmp["methods"]["net"]["kind"] == "net"
    assert cmp["format"] == 2 and "conditions" not in cmp  # several methods: no single-method keys
    assert set(cmp["methods"]["new"]["conditions"]) == {"slant_deg=20.0", "slant_deg=30.0"}
    for single, name in ((lamb, "lambertian"), (net, "new")):
        assert single["format"] == 2 and list(single["methods"]) == [name if single is lamb else "net"]
        for cond, c in single["conditions"].items():  # format-1 keys kept for one method
            mine = cmp["methods"][name]["conditions"][cond]
            for key in ("mae_deg", "median_deg", "ssim", "n_patches", "n_frames"):
                assert mine["patches"][key] == pytest.approx(c["patches"][key], abs=1e-6), (name, cond, key)
            assert mine["patches"]["ci95_deg"] == pytest.approx(c["patches"]["ci95_deg"], abs=1e-6)
            assert mine["frames"]["mae_deg"] == pytest.approx(c["frames"]["mae_deg"], abs=1e-6)
            assert mine["per_object"] == pytest.approx(c["per_object"], abs=1e-6)
        assert single["robustness"]["mae_deg"] == pytest.approx(cmp["methods"][name]["robustness"]["mae_deg"],
                                                                abs=1e-6)
    # the table's lambertian column is the single run's numbers, row by row
    rows = {(r["condition"], r["what"], r["object"]): r for r in cmp["table"]["rows"]}
    for cond, c in lamb["conditions"].items():
        assert rows[(cond, "patch pixels", None)]["mae_deg"]["lambertian"] == pytest.approx(
            c["patches"]["mae_deg"], abs=1e-6)
        assert rows[(cond, "whole frames", None)]["mae_deg"]["lambertian"] == pytest.approx(
            c["frames"]["mae_deg"], abs=1e-6)
        assert rows[(cond, "object", "torus")]["mae_deg"]["lambertian"] == pytest.approx(
            c["per_object"]["torus"], abs=1e-6)
        assert rows[(cond, "patch pixels", None)]["n_patches"] == c["patches"]["n_patches"] > 0
    # pooled over both conditions: pixel-weighted patches, mean of every frame's MAE per object
    pooled = rows[("all", "patch pixels", None)]["mae_deg"]["lambertian"]
    c = lamb["conditions"]
    want = sum(v["patches"]["mae_deg"] * v["patches"]["n_pixels"] for v in c.values()) / \
        sum(v["patches"]["n_pixels"] for v in c.values())
    assert pooled == pytest.approx(want, abs=1e-6)
    assert rows[("all", "object", "torus")]["mae_deg"]["lambertian"] == pytest.approx(
        np.mean([v["per_object"]["torus"] for v in c.values()]), abs=1e-6)  # 3 frames each
    # two checkpoints, two different columns
    assert all(r["mae_deg"]["new"] != pytest.approx(r["mae_deg"]["net"], abs=1e-3) for r in cmp["table"]["rows"])


def test_confidence_intervals_bracket_the_means(runs):
    cmp = runs["cmp"]
    for r in cmp["table"]["rows"]:
        for n in cmp["table"]["methods"]:
            lo, hi = r["ci95_deg"][n]
            assert lo - 1e-9 <= r["mae_deg"][n] <= hi + 1e-9, (r, n)
            assert hi - lo < 180
    assert r["n_frames"] == 6  # the last row: the object over both conditions' 3 frames
    assert "bootstrap over frames" in cmp["ci"]


def test_bootstrap_ci_against_the_normal_approximation():
    from msps_render.models.evaluate import bootstrap_ci

    rng = np.random.default_rng(1)
    x = rng.normal(20.0, 4.0, 400)
    (lo, hi), = bootstrap_ci(x, np.ones_like(x), "t")
    half = 1.96 * x.std(ddof=1) / np.sqrt(len(x))
    assert lo < x.mean() < hi and (hi - lo) / 2 == pytest.approx(half, rel=0.15)
    assert (bootstrap_ci(x, np.ones_like(x), "t") == bootstrap_ci(x, np.ones_like(x), "t")).all()  # seeded
    one = bootstrap_ci(np.array([[3.0], [5.0]]), np.array([2.0]), "t")  # one unit: no spread
    assert one.tolist() == [[1.5, 1.5], [2.5, 2.5]]


def test_compare_outputs_table_md_and_figures(runs, setup):
    from PIL import Image

    d = setup["tmp"] / "cmp"
    md = (d / "table.md").read_text()
    assert "| condition | rows | n | new | net | scn | lambertian |" in md
    assert sum(ln.startswith("|") for ln in md.splitlines()) == 2 + len(runs["cmp"]["table"]["rows"])  # + head, rule
    assert "tiny-compare" in md and "new" in runs["cmp_out"] and "lambertian" in runs["cmp_out"]
    for name in ("error_hist.png", "per_object.png", "robustness.png"):
        im = np.asarray(Image.open(d / name).convert("L"))
        assert im.shape[0] >= 300 and im.shape[1] >= 500 and im.std() > 10, name  # drawn, readable
    # one object, one method: still a figure (the object per condition and pooled)
    im = np.asarray(Image.open(setup["tmp"] / "lamb" / "per_object.png").convert("L"))
    assert im.shape[0] >= 300 and im.shape[1] >= 500 and im.std() > 10


def test_single_method_reports_still_feed_robust_table(runs):
    spec = importlib.util.spec_from_file_location("robust_table", ROOT / "benchmarks" / "robust_table.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    t = mod.table({"net": runs["net"], "lambertian": runs["lamb"]})
    assert f"{runs['lamb']['robustness']['mae_deg']['slant_deg=20.0']:.2f}" in t
    assert runs["lamb"]["robustness"]["reference"] == "slant_deg=30.0"


def test_method_names_and_errors(setup):
    from msps_render.errors import InputError
    from msps_render.models.evaluate import resolve_methods

    from msps_render.models.steps import DEFAULT_RENDERED, Steps

    ms = resolve_methods([setup["a"], setup["b"]], [], [Steps()])  # the raw networks: names alone
    assert ms[0].name == "net" and ms[1].name.startswith("net ") and ms[1].name.endswith("/b")
    assert resolve_methods([setup["a"]], [])[0].name == "net" + DEFAULT_RENDERED.suffix  # eval's default steps
    assert [m.name for m in resolve_methods([], ["lambertian"])] == ["lambertian"]
    with pytest.raises(InputError, match="given twice"):
        resolve_methods([f"x={setup['a']}", f"x={setup['b']}"])
    with pytest.raises(InputError, match="names the baseline"):
        resolve_methods([f"lambertian={setup['a']}"])
    with pytest.raises(InputError, match="unknown method"):
        resolve_methods([], ["nett"])
    with pytest.raises(InputError, match="checkpoint not found"):
        resolve_methods(["nope=missing.pt"])


def test_predict_panel_names_and_mae(setup, tmp_path):
    from PIL import Image

    from msps_render.data import iter_frames
    from msps_render.io import png16
    from msps_render.models import predict as P
    from msps_render.models.metrics import angular_error_deg

    fr = next(iter_frames(setup["data"]))
    np.save(tmp_path / "img.npy", fr.image)
    np.save(tmp_path / "mask.npy", fr.mask.astype(np.float32))
    gt = fr.normal.copy()
    gt[:6] = 0.0  # no truth in the top rows: left out
    np.save(tmp_path / "gt.npy", gt)
    r = subprocess.run([sys.executable, "-m", "msps_render.cli", "predict", str(tmp_path / "img.npy"), "--out",
                        str(tmp_path / "pred-v0.1"), "--checkpoint", str(setup["a"]), "--mask",
                        str(tmp_path / "mask.npy"), "--normal-gt", str(tmp_path / "gt.npy")],
                       capture_output=True, text=True, env=ENV)
    assert r.returncode == 0, r.stderr
    names = sorted(p.name for p in tmp_path.glob("pred-*"))
    assert names == ["pred-v0.1-metrics.json", "pred-v0.1-panel.png", "pred-v0.1.npy", "pred-v0.1.png"]
    n = np.load(tmp_path / "pred-v0.1.npy")
    m = json.loads((tmp_path / "pred-v0.1-metrics.json").read_text())
    scored = fr.mask.copy()
    scored[:6] = False
    assert m["mae_deg"] == pytest.approx(float(angular_error_deg(n[scored], gt[scored]).mean()), abs=1e-6)
    assert m["n_pixels"] == scored.sum() and m["n_left_out"] == fr.mask[:6].sum() > 0
    assert f"MAE {m['mae_deg']:.2f} deg" in r.stdout
    w, h = Image.open(tmp_path / "pred-v0.1-panel.png").size  # input, prediction, truth, error + colour bar
    assert (w, h) == (round(P.PANEL_DPI * (4 * P.PANEL_COL_IN + P.PANEL_CBAR_IN)), round(P.PANEL_DPI * P.PANEL_H_IN))
    assert np.asarray(Image.open(tmp_path / "pred-v0.1-panel.png").convert("L")).std() > 10
    # the same truth as a 16-bit (n+1)/2 PNG (mid grey = no normal): the same pixels, MAE within quantisation
    png16.write_png(tmp_path / "gt.png", png16.encode_normal(gt, np.linalg.norm(gt, axis=-1) > 0))
    files = P.predict_main(tmp_path / "img.npy", tmp_path / "p2", P.predict_method(checkpoint=setup["a"]),
                           mask=tmp_path / "mask.npy", normal_gt=tmp_path / "gt.png")
    m2 = json.loads((tmp_path / "p2-metrics.json").read_text())
    assert m2["n_pixels"] == m["n_pixels"] and m2["mae_deg"] == pytest.approx(m["mae_deg"], abs=0.01)
    assert [f.name for f in files] == ["p2.npy", "p2.png", "p2-panel.png", "p2-metrics.json"]
    # no truth: input and prediction only, no metrics
    P.predict_main(tmp_path / "img.npy", tmp_path / "lamb.png", P.predict_method("lambertian"), warn=lambda w: None)
    assert (tmp_path / "lamb.npy").is_file() and not (tmp_path / "lamb-metrics.json").exists()
    assert Image.open(tmp_path / "lamb-panel.png").size == (round(P.PANEL_DPI * 2 * P.PANEL_COL_IN),
                                                           round(P.PANEL_DPI * P.PANEL_H_IN))
    assert P.out_paths("a.b/pred-v0.1")["npy"] == Path("a.b/pred-v0.1.npy")
    from msps_render.errors import InputError

    with pytest.raises(InputError, match="normal map is 8x8"):
        np.save(tmp_path / "small.npy", np.zeros((8, 8, 3)))
        P.predict_main(tmp_path / "img.npy", tmp_path / "x", P.predict_method("lambertian"),
                       normal_gt=tmp_path / "small.npy", warn=lambda w: None)
    assert not (tmp_path / "x.npy").exists()  # failed before writing anything
