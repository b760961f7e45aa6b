"""The shipped checkpoint against its claimed numbers, measured from scratch in the test.

The unseen-object test sets are rendered here from their presets (deterministic from the preset
seeds: the same 2 x 28 frames as `msps render unseen-test[-grey]`, docs/history.md) and
predicted with the shipped model and the calibrated Lambertian baseline, pixel-pooled over whole
frames as `benchmarks/unseen_report.py` does. Needs the test meshes in ../shared/data (skips
without them).

What is checked is the claim (README, models/README.md, docs/history.md), not only the
issue-9 target (<= 0.7x / <= 1x): the measured ratio shipped / Lambertian must lie within the
margin of the claimed one, on both sides -- a worse model fails, and so does a better one whose
claim was not updated. Replacing models/dualcue-cpu.pt: re-run with `-s`, which prints the ratio
and its frame-bootstrap interval, and update the CLAIM / MARGIN pair below.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]

pytest.importorskip("torch")

# Claimed pooled-MAE ratios shipped / Lambertian of models/dualcue-cpu.pt (v0.5), each with its
# noise margin: the larger side of the 95 % frame-bootstrap interval of the ratio on this test's
# own 28 frames (2,000 resamples of frames with replacement, rng seed 0, printed by the test),
# rounded up to 0.01. Measured on v0.5 from the stored renders of the same presets
# (`python benchmarks/shipped_claims.py --model v0.5=models/dualcue-cpu.pt`, which computes exactly
# what this test does): unseen-test 0.5273 [0.4423, 0.6302] (16.25 vs 30.81 deg), grey 0.9901
# [0.8857, 1.1147] (8.41 vs 8.50 deg). v0.4's were 0.5274 [0.4442, 0.6267] and 0.9239 [0.8263,
# 1.0397]. The margin says how far another draw of 28 frames of the same kind could move the
# number, so a ratio outside claim +- margin means the claim does not describe the model (v0.3's
# 0.65 on unseen-test, within the old 0.7 bar, is outside 0.53 +- 0.11).
UNSEEN_CLAIM, UNSEEN_MARGIN = 0.53, 0.11
GREY_CLAIM, GREY_MARGIN = 0.99, 0.13
# issue 9's targets, which the claims must meet
UNSEEN_TARGET, GREY_TARGET = 0.7, 1.0


@pytest.mark.slow  # renders 56 frames of 256² path-traced: 672-711 s per set measured (2 busy cores)
@pytest.mark.parametrize("preset,claim,margin,target", [("unseen-test", UNSEEN_CLAIM, UNSEEN_MARGIN, UNSEEN_TARGET),
                                                        ("unseen-test-grey", GREY_CLAIM, GREY_MARGIN, GREY_TARGET)])
def test_shipped_model_meets_its_claims_on_unseen_objects(preset, claim, margin, target, shared_data, rgb_variant,
                                                          tmp_path, monkeypatch):
    from msps_render.models.predict import default_checkpoint
    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.run import render_dataset
    from msps_render.models.evaluate import frame_errors
    from msps_render.testing import frame_bootstrap

    monkeypatch.setenv("MSPS_TEST_DATA", str(shared_data))  # where the unseen-* presets read their meshes
    cfg = load_config(preset)
    render_dataset(cfg, tmp_path / preset, progress=False, variant=rgb_variant)
    net, base, count = frame_errors(tmp_path / preset, default_checkpoint())
    assert len(net) == cfg.dataset.n_shards * cfg.dataset.frames_per_shard
    ratio = net.sum() / base.sum()
    lo, hi = frame_bootstrap(net, base)
    print(f"{preset}: shipped {net.sum() / count.sum():.2f} deg, Lambertian {base.sum() / count.sum():.2f} deg, "
          f"ratio {ratio:.4f}, 95% frame-bootstrap [{lo:.4f}, {hi:.4f}] (margin {max(ratio - lo, hi - ratio):.4f})")
    assert ratio <= target
    assert abs(ratio - claim) <= margin, f"{preset}: measured {ratio:.3f}, claimed {claim} +- {margin}"


# Claims of stages 8-9 (docs/history.md): the shipped model after --selfcal --refine, pooled-MAE ratio to
# calibrated Lambertian PS on the raw image, with the larger side of the 95 % frame-bootstrap interval
# (measured on v0.5 from the stored renders by benchmarks/shipped_claims.py: grey 0.6603 [0.5577, 0.7699]
# (5.61 vs 8.50 deg); colour 0.1753 [0.1311, 0.2341] (6.30 vs 35.92 deg); v0.4: 0.6551 [0.5552, 0.7625],
# 0.1777 [0.1317, 0.2395]). Issue 20's targets: grey <= 0.75x, colour <= 0.45x.
REFINE_CLAIMS = [("unseen-test-grey", 0.66, 0.11, 0.75), ("unseen-test-colour", 0.18, 0.06, 0.45)]
# Stage 13: with --selfcal --netcal --refine (models/netcal.py), the same terms, measured on v0.5 by
# benchmarks/shipped_claims.py: grey 0.6814
# [0.5744, 0.7963] (5.79 vs 8.50 deg), colour 0.1708 [0.1325, 0.2191] (6.13 vs 35.92), texture 0.5421
# [0.4862, 0.6005] (17.75 vs 32.74).  Targets as above; texture: issue 20's 0.45x is not met.
NETCAL_CLAIMS = [("unseen-test-grey", 0.68, 0.12, 0.75), ("unseen-test-colour", 0.17, 0.05, 0.45),
                 ("unseen-test-texture", 0.54, 0.06, None)]


@pytest.mark.slow  # renders 28 frames of 256² per set (about 15 s each with llvm_ad_rgb, minutes with scalar)
@pytest.mark.parametrize("preset,claim,margin,target,netcal",
                         [(*c, False) for c in REFINE_CLAIMS] + [(*c, True) for c in NETCAL_CLAIMS])
def test_shipped_model_with_selfcal_and_refine_meets_its_claims(preset, claim, margin, target, netcal, shared_data,
                                                                rgb_variant, tmp_path, monkeypatch):
    from msps_render.models.predict import default_checkpoint
    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.run import render_dataset
    from msps_render.models.evaluate import frame_errors
    from msps_render.testing import frame_bootstrap

    monkeypatch.setenv("MSPS_TEST_DATA", str(shared_data))
    render_dataset(load_config(preset), tmp_path / preset, progress=False, variant=rgb_variant)
    net, base, _ = frame_errors(tmp_path / preset, default_checkpoint(),
                                "selfcal+netcal+refine" if netcal else "selfcal+refine")
    ratio = net.sum() / base.sum()
    lo, hi = frame_bootstrap(net, base)
    print(f"{preset} +selfcal{'+netcal' if netcal else ''}+refine: ratio {ratio:.4f}, 95% frame-bootstrap [{lo:.4f}, {hi:.4f}]")
    if target is not None:  # a claim below an unmet target is still held at its measured value
        assert ratio <= target
    assert abs(ratio - claim) <= margin, f"{preset}: measured {ratio:.3f}, claimed {claim} +- {margin}"


def test_shipped_classic_network_scores_on_diligent_what_its_card_says(shared_data, tmp_path):
    """models/classic-cpu.pt on DiLiGenT's four objects with all 96 lights, measured here, against the model
    card's row (models/README.md; docs/history.md stages 16-17): each object and the mean to 0.02 deg (the card
    rounds to 0.01; CPU inference is deterministic), and the ratio of means to least squares.  A new model
    fails until its card follows.  ~15 s."""
    import json
    import re

    from cli_helpers import cli

    row = next(ln for ln in (ROOT / "models" / "README.md").read_text(encoding="utf-8").splitlines()
               if ln.startswith("| DiLiGenT ball/cat/goblet/pot1, 96 lights"))
    cells = [c.strip() for c in row.strip().strip("|").split("|")]
    m = re.fullmatch(r"\*\*([\d.]+) \(([\d.]+)x\)\*\*: ([\d.]+) / ([\d.]+) / ([\d.]+) / ([\d.]+)", cells[1])
    assert m, cells[1]
    mean, ratio, *per = (float(x) for x in m.groups())
    d = shared_data / "diligent"
    r = cli("bench-real", *[d / f"{o}PNG" for o in ("ball", "cat", "goblet", "pot1")], "--lights", "all",
            "--out", tmp_path / "br", "--checkpoint", f"shipped={ROOT / 'models' / 'classic-cpu.pt'}")
    assert r.returncode == 0, r.stderr[-2000:]
    s = json.loads((tmp_path / "br" / "results.json").read_text())
    got = [s["objects"][o]["shipped"] for o in ("ball", "cat", "goblet", "pot1")]
    assert np.allclose(got, per, atol=0.02), (got, per)
    assert abs(s["mean_deg"]["shipped"] - mean) < 0.02 and abs(float(cells[2]) - s["mean_deg"]["lambertian"]) < 0.02
    assert abs(s["ratio_of_means_to_lambertian"]["shipped"] - ratio) < 0.006
