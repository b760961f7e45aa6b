"""The classic (any-light) network: order-agnostic, any number of lights, exact augmentation, the whole
command loop (train -> eval -> bench-real --lights) on tiny data, checkpoints refused across networks."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest
import torch

from cli_helpers import cli, llvm_forced, one_line_error
from msps_render.models.classic import _rotate
from msps_render.models.classic_net import ClassicNet, ClassicNetConfig, pad4, prepare


def _batch(B=2, K=5, P=16, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(B, K, 3, P, P, generator=g), torch.nn.functional.normalize(torch.rand(B, K, 3, generator=g) +
                                                                                  torch.tensor([0, 0, 1.0]), dim=-1))


def test_order_agnostic_and_chunked_pooling_equal():
    torch.manual_seed(0)
    net = ClassicNet(ClassicNetConfig(3, (8, 16, 16))).eval()
    x, d = _batch()
    with torch.no_grad():
        a = net(x, d)
        perm = torch.tensor([3, 0, 4, 1, 2])
        b = net(x[:, perm], d[:, perm])
        c = net(x, d, chunk=2)
    assert torch.allclose(a, b, atol=1e-6) and torch.allclose(a, c, atol=1e-6)
    assert torch.allclose(a.norm(dim=1), torch.ones(()), atol=1e-5)


def test_pixel_normalisation_divides_out_albedo_and_not_the_number_of_lights():
    """`prepare(normalize="pixel")` (PS-FCN (Norm.)): two Lambertian pixels with the same normal and albedos
    4x apart read the same values; every object pixel's root mean square over lights and channels is 1 and
    repeating the lights (N doubled) changes nothing; off the object 0; "object" (the default, the shipped
    model's) keeps the albedo ratio."""
    g = torch.Generator().manual_seed(1)
    K, H, W = 12, 4, 4
    dirs = torch.nn.functional.normalize(torch.rand(K, 3, generator=g) * torch.tensor([2.0, 2.0, 1.0])
                                         - torch.tensor([1.0, 1.0, -0.5]), dim=-1)
    n = torch.nn.functional.normalize(torch.rand(H, W, 3, generator=g) - torch.tensor([0.5, 0.5, -0.6]), dim=-1)
    albedo = 0.1 + 0.8 * torch.rand(H, W, 3, generator=g)
    albedo[0, 1] = 4 * albedo[0, 0]
    n[0, 1] = n[0, 0]
    shading = (torch.einsum("kc,hwc->khw", dirs, n)).clamp_min(0)  # (K, H, W)
    images = (shading[:, None] * albedo.permute(2, 0, 1)[None])[None]  # (1, K, 3, H, W)
    readings = torch.full((1, K, 3), 2.0)
    mask = torch.ones(1, H, W, dtype=torch.bool)
    mask[0, 3, 3] = False
    x = prepare(images, readings, mask, "pixel")
    assert torch.allclose(x[0, :, :, 0, 0], x[0, :, :, 0, 1], atol=1e-6)
    rms = (x[0] ** 2).mean((0, 1)).sqrt()
    assert torch.allclose(rms[mask[0]], torch.ones(()), atol=1e-5) and float(x[0, :, :, 3, 3].abs().max()) == 0.0
    x2 = prepare(images.repeat(1, 2, 1, 1, 1), readings.repeat(1, 2, 1), mask, "pixel")
    assert torch.allclose(x2[:, :K], x, atol=1e-6)
    o = prepare(images, readings, mask)  # "object": albedo ratios stay
    assert torch.allclose(o[0, :, :, 0, 1], 4 * o[0, :, :, 0, 0], rtol=1e-5)
    with pytest.raises(ValueError, match="normalize"):
        prepare(images, readings, mask, "pixels")


@pytest.mark.parametrize("K", [1, 3, 96])
def test_any_number_of_lights(K):
    net = ClassicNet(ClassicNetConfig(3, (8, 16, 16))).eval()
    x, d = _batch(1, K, 12)
    x, pads = pad4(x)
    with torch.no_grad():
        assert net(x, d, chunk=16).shape == (1, 3, 12, 12)


def test_prepare_removes_exposure_and_light_readings():
    x, _ = _batch(1, 4, 8)
    r = torch.rand(1, 4, 3) + 0.5
    m = torch.ones(1, 8, 8, dtype=torch.bool)
    a = prepare(x * r[..., None, None], r, m)
    b = prepare(7.0 * x * r[..., None, None], r, m)
    assert torch.allclose(a, b, atol=1e-5) and torch.allclose(a, prepare(x, torch.ones_like(r), m), atol=1e-5)


@pytest.mark.parametrize("k", [1, 2, 3])
def test_rotation_augmentation_is_exact_for_lambertian_images(k):
    """A Lambertian image I = n . l, rotated by k x 90 deg with its normals and lights, is again n' . l'."""
    P = 12
    yy, xx = torch.meshgrid(torch.linspace(-0.7, 0.5, P), torch.linspace(-0.4, 0.8, P), indexing="ij")
    n = torch.nn.functional.normalize(torch.stack([xx, -yy, torch.ones_like(xx)]), dim=0)[None]  # (1, 3, P, P)
    d = torch.nn.functional.normalize(torch.tensor([[[0.5, 0.2, 1.0], [-0.3, 0.6, 1.0]]]), dim=-1)  # (1, 2, 3)
    img = torch.einsum("bkc,bchw->bkhw", d, n).clamp_min(0)[:, :, None].expand(-1, -1, 3, -1, -1)
    b = _rotate({"image": img, "normal": n, "dirs": d, "mask": torch.ones(1, P, P, dtype=torch.bool),
                 "readings": torch.ones(1, 2, 3)}, k)
    again = torch.einsum("bkc,bchw->bkhw", b["dirs"], b["normal"]).clamp_min(0)
    assert torch.allclose(b["image"][:, :, 0], again, atol=1e-6)
    assert not torch.allclose(b["normal"], n)


@pytest.fixture(scope="module")
def rig_data(tmp_path_factory):
    with llvm_forced() as v:
        if v is None:
            pytest.skip("LLVM variant unavailable: rendering would be too slow")
        root = tmp_path_factory.mktemp("classic")
        for name, seed in (("train", 1), ("val", 2)):
            r = cli("render", "demo-rig", "--out", root / name, "--set", f"dataset.seed={seed}", "--set",
                    "dataset.n_shards=1", "--set", "dataset.frames_per_shard=2", "--set", "scene.camera.width=64",
                    "--set", "scene.camera.height=64", "--set", "dataset.patches.stride=8", "--workers", "1")
            assert r.returncode == 0, r.stderr[-2000:]
        return root


def test_train_eval_bench_real_loop(rig_data, tmp_path):
    from msps_render.testing import write_sphere_capture
    from scipy.io import savemat

    run = tmp_path / "run"
    r = cli("train", "classic-cpu", "--data", rig_data / "train", "--val", rig_data / "val", "--out", run,
            "--set", "train.max_steps=4", "--set", "train.batch_size=4", "--set", "train.val_max_patches=16",
            env_extra={"MSPS_PROGRESS_EVERY": "0"})  # every line, start-up stages too, however short
    assert r.returncode == 0, r.stderr[-2000:]
    assert "classic network" in r.stdout and (run / "best.pt").is_file() and (run / "metrics.jsonl").is_file()
    lines = [l for l in r.stderr.splitlines() if l.startswith("train: ")]
    assert lines[0] == "train: opening the corpus and reading the validation patches", lines
    assert re.fullmatch(r"train: [\d,]+ training patches, \d+ validation patches; classic-cpu on cpu \([\d.]+ s\)",
                        lines[1]), lines
    assert lines[2].startswith("train: 1/4 steps"), lines
    # resume: a finished run does no extra step
    r2 = cli("train", "classic-cpu", "--data", rig_data / "train", "--val", rig_data / "val", "--out", run,
             "--set", "train.max_steps=4", "--set", "train.batch_size=4", "--set", "train.val_max_patches=16",
             "--resume")
    assert r2.returncode == 0 and "4 steps" in r2.stdout, r2.stdout + r2.stderr[-1000:]
    r = cli("eval", "--data", rig_data / "val", "--out", tmp_path / "ev", "--checkpoint", f"net={run / 'best.pt'}",
            "--method", "lambertian")
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert set(m["mean_deg"]) == {"net", "lambertian"} and all(np.isfinite(v) for v in m["mean_deg"].values())
    rng = np.random.default_rng(0)
    cap = write_sphere_capture(tmp_path / "ballPNG", [(30, t) for t in range(0, 360, 45)], 40, rng)
    savemat(tmp_path / "ballPNG" / "Normal_gt.mat", {"Normal_gt": cap["normal"]})
    r = cli("bench-real", tmp_path / "ballPNG", "--out", tmp_path / "br", "--lights", "all",
            "--checkpoint", f"net={run / 'best.pt'}")
    assert r.returncode == 0, r.stderr[-2000:]
    s = json.loads((tmp_path / "br" / "results.json").read_text())
    assert s["objects"]["ball"]["lights"] == 8
    # an exact Lambertian sphere: least squares errs only where a light is below the rim pixels' horizon
    # (attached shadows read 0): 1.6 deg measured; ignoring the random intensities (0.5-2) gives > 10
    assert s["objects"]["ball"]["lambertian"] < 3.0
    # the wrong network's checkpoint, one line each way
    r = cli("eval", "--data", rig_data / "val", "--out", tmp_path / "ev2", "--checkpoint",
            "models/dualcue-cpu.pt")
    assert "not an msps classic-network checkpoint" in one_line_error(r)


def test_warm_start_takes_the_checkpoints_weights_and_refuses_mixups_in_one_line(rig_data, tmp_path):
    """`--init`: a new run starts from a checkpoint's weights (fresh optimizer and schedule), e.g. a shipped
    model trained further on a larger corpus; what would overwrite, resume nothing or mix networks is one line."""
    small = ["--set", "train.batch_size=4", "--set", "train.val_max_patches=16"]
    base = ["--data", rig_data / "train", "--val", rig_data / "val"]
    a = tmp_path / "a"
    assert cli("train", "classic-cpu", *base, "--out", a, "--set", "train.max_steps=4", *small).returncode == 0
    # one step at a vanishing rate: the warm start's weights are the checkpoint's (Adam moves each by ~lr)
    tiny = ["--set", "train.max_steps=1", "--set", "train.lr=1e-12", *small]
    r = cli("train", "classic-cpu", *base, "--out", tmp_path / "b", "--init", a / "best.pt", *tiny)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "warm start from best.pt sha1:" in r.stdout, r.stdout
    r = cli("train", "classic-cpu", *base, "--out", tmp_path / "c", *tiny)  # the same run without --init
    assert r.returncode == 0, r.stderr[-2000:]
    wa, wb, wc = (torch.load(f, map_location="cpu", weights_only=True)["model"]
                  for f in (a / "best.pt", tmp_path / "b" / "last.pt", tmp_path / "c" / "last.pt"))
    assert max(float((wa[k].float() - wb[k].float()).abs().max()) for k in wa) < 1e-6
    assert max(float((wa[k].float() - wc[k].float()).abs().max()) for k in wa) > 1e-4  # 4 steps at 1e-3 apart
    r = cli("train", "classic-cpu", *base, "--out", tmp_path / "s", "--init", "classic-cpu", *tiny)  # shipped, by name
    assert r.returncode == 0 and "warm start from classic-cpu.pt sha1:" in r.stdout, r.stdout + r.stderr[-1000:]
    line = one_line_error(cli("train", "classic-cpu", *base, "--out", tmp_path / "n", "--init", "no-such-model"))
    assert "no-such-model" in line and "not found" in line, line
    line = one_line_error(cli("train", "classic-gpu", *base, "--out", tmp_path / "d", "--init", a / "best.pt"))
    assert "best.pt" in line and "different network" in line, line
    # the same weights under another input normalisation: a fine-tune, recorded in the new checkpoint
    r = cli("train", "classic-cpu", *base, "--out", tmp_path / "p", "--init", a / "best.pt", "--set",
            "net.normalize=pixel", *tiny)
    assert r.returncode == 0, r.stderr[-2000:]
    assert torch.load(tmp_path / "p" / "last.pt", map_location="cpu", weights_only=True)["config"]["net"]["normalize"] == "pixel"
    line = one_line_error(cli("train", "classic-cpu", *base, "--out", tmp_path / "q", "--set", "net.normalize=pixels"))
    assert "net.normalize" in line and "'object' or 'pixel'" in line, line
    line = one_line_error(cli("train", "classic-cpu", *base, "--out", tmp_path / "e", "--init",
                              "models/dualcue-cpu.pt"))
    assert "not an msps classic-network checkpoint" in line, line
    line = one_line_error(cli("train", "classic-cpu", *base, "--out", a, *tiny))  # a run is never overwritten
    assert "already holds a training run; use --resume" in line, line
    line = one_line_error(cli("train", "classic-cpu", *base, "--out", tmp_path / "f", "--resume"))
    assert "nothing to resume" in line, line
    line = one_line_error(cli("train", "classic-cpu", *base, "--out", a, "--resume", "--init", a / "best.pt"))
    assert "--init" in line, line
    assert not any((tmp_path / d).exists() for d in ("d", "e", "f", "q"))


def test_several_corpora_train_as_one_and_other_rig_sizes_are_refused(rig_data, tmp_path):
    """`--data` repeated: the corpora's patches are one training set (the summary counts both); a corpus of
    another rig size (6 lights against 8) is refused in one line naming the shard, before any step."""
    small = ["--val", rig_data / "val", "--set", "train.batch_size=4", "--set", "train.val_max_patches=16",
             "--set", "train.max_steps=2", "--json"]
    counts = {}
    for name in ("train", "val"):
        r = cli("train", "classic-cpu", "--data", rig_data / name, "--out", tmp_path / name, *small)
        assert r.returncode == 0, r.stderr[-2000:]
        counts[name] = json.loads(r.stdout)["corpus_patches"]
    r = cli("train", "classic-cpu", "--data", rig_data / "train", "--data", rig_data / "val", "--out",
            tmp_path / "both", *small)
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads(r.stdout)["corpus_patches"] == counts["train"] + counts["val"] > counts["train"]
    with llvm_forced():
        r = cli("render", "demo-rig", "--out", tmp_path / "six", "--set", "scene.rig.n_lights=6", "--set",
                "dataset.n_shards=1", "--set", "dataset.frames_per_shard=1", "--set", "scene.camera.width=64",
                "--set", "scene.camera.height=64", "--set", "dataset.patches.stride=8", "--workers", "1")
    assert r.returncode == 0, r.stderr[-2000:]
    line = one_line_error(cli("train", "classic-cpu", "--data", rig_data / "train", "--data", tmp_path / "six",
                              "--out", tmp_path / "mixed", *small))
    assert "6 images of 3 channel(s) per patch" in line and "has 8 of 3" in line and "six" in line, line
    assert not (tmp_path / "mixed").exists()


def test_dual_cue_refuses_rig_shards_in_one_line(rig_data, tmp_path):
    r = cli("train", "cpu", "--data", rig_data / "train", "--val", rig_data / "val", "--out", tmp_path / "r")
    line = one_line_error(r)
    assert "dual-cue" in line and "image(s)" in line


def test_predict_on_a_capture_folder(tmp_path):
    """`msps predict FOLDER`: per-light photos with their lights -> normals, by the shipped classic network
    (default) or least squares; single-image options are refused in one line."""
    from msps_render.testing import write_sphere_capture

    cap = write_sphere_capture(tmp_path / "sphere", [(s, t) for s in (20, 40) for t in range(0, 360, 60)], 48,
                               np.random.default_rng(1))
    m = cap["mask"]
    errs = {}
    for method in ("lambertian", "net"):
        r = cli("predict", tmp_path / "sphere", "--out", tmp_path / method, "--method", method)
        assert r.returncode == 0, r.stderr[-1500:]
        n = np.load(tmp_path / f"{method}.npy")
        errs[method] = np.degrees(np.arccos(np.clip((n[m] * cap["normal"][m]).sum(-1), -1, 1))).mean()
    assert errs["lambertian"] < 3.0  # exact Lambertian sphere; attached shadows at the rim only
    assert errs["net"] < 15.0, errs  # the shipped network on a sphere it never saw: not a random normal
    r = cli("predict", tmp_path / "sphere", "--out", tmp_path / "x", "--steps", "selfcal")
    assert "capture folder" in one_line_error(r)
