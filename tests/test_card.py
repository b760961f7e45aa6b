"""The dataset card (issue 23 item 3) and `msps preview` covering every condition.

On a tiny two-condition render (a sweep over the environment ratio) made by `msps render`
itself: card.json's counts equal the manifest's and the shards', every per-frame histogram
totals the frames, every per-part table the material parts, and `msps card` rewrites the
same bytes on demand.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import cli, one_line_error
from msps_render.dataset import schema as K

TINY = """
[dataset]
name = "tiny-card"
seed = 2
n_shards = 1
frames_per_shard = 3
[dataset.patches]
size = 16
stride = 8
[scene.environment]
enabled = true
[scene.camera]
width = 32
height = 32
[scene.integrator]
spp = 4
max_depth = 3
[sweep]
key = "scene.environment.ratio"
values = [0.0, 0.3]
"""


@pytest.fixture(scope="module")
def rendered(tmp_path_factory) -> Path:
    from msps_render.render.variant import resolve_variant

    if not resolve_variant("rgb").startswith("llvm"):
        pytest.skip("LLVM variant unavailable: rendering would be too slow")
    d = tmp_path_factory.mktemp("card")
    (d / "tiny.toml").write_text(TINY)
    r = cli("render", d / "tiny.toml", "--out", d / "ds", "--quiet")
    assert r.returncode == 0, r.stderr
    assert "card: " in r.stdout
    return d / "ds"


def _frames(root: Path) -> dict[str, list]:
    from msps_render.dataset.reader import open_shard  # registers the zstd filter (alone, h5py cannot read it)

    out = {"materials": [], "condition": [], "env_ratio": []}
    for p in sorted((root / "shards").glob("shard-*.h5")):
        with open_shard(p) as h:
            out["materials"] += h[K.FRAME_MATERIALS].asstr()[()].tolist()
            out["condition"] += h[K.FRAME_CONDITION].asstr()[()].tolist()
            out["env_ratio"] += h[K.FRAME_ENV_RATIO][()].tolist()
    return out


def _total(h: dict) -> int:
    assert sum(h["counts"]) + h["nan"] == h["total"]  # nothing falls outside the bins
    return h["total"]


def test_render_writes_card_whose_counts_and_totals_match_the_dataset(rendered):
    from PIL import Image

    m = json.loads((rendered / "dataset.json").read_text())
    card = json.loads((rendered / "card.json").read_text())
    assert Image.open(rendered / "card.png").size == (1600, 1650)
    d, n, fr, parts = card["dataset"], card["counts"], card["frames"], card["parts"]
    assert d["config_hash"] == m["config_hash"] and d["versions"] == m["versions"] and d["complete"]
    assert d["shard_versions"]["mitsuba_version"] == [m["versions"]["mitsuba"]]
    assert (n["shards"], n["frames"], n["patches"]) == (len(m["shards"]), m["n_frames"], m["n_patches"]) == (2, 6, n["patches"])
    for c in m["conditions"]:
        es = [e for e in m["shards"].values() if e["condition"] == c]
        assert n["conditions"][c] == {"shards": len(es), "frames": sum(e["n_frames"] for e in es),
                                      "patches": sum(e["n_patches"] for e in es)}
    F = m["n_frames"]
    for h in (fr["slant_deg"], fr["env_ratio"], fr["crosstalk_asymmetry"], fr["patches_per_frame"],
              *fr["tilt_deg"].values(), *fr["crosstalk_diagonal"].values()):
        assert _total(h) == F
    assert len(fr["tilt_deg"]) == 3 and len(fr["crosstalk_diagonal"]) == 3
    for cats in (fr["condition"], fr["shape_kind"], fr["object"], fr["spp"], fr["materials_per_frame"]):
        assert sum(cats.values()) == F
    assert fr["condition"] == {"ratio=0.0": 3, "ratio=0.3": 3}
    # patches per frame: the histogram's mean is the patch count over the frames
    assert sum(fr["patches_per_frame"]["counts"]) == F
    # per part: the frames' ';'-joined material names, one per part
    names = [s for j in _frames(rendered)["materials"] for s in j.split(";")]
    assert n["material_parts"] == len(names) == sum(int(k) * v for k, v in fr["materials_per_frame"].items())
    assert parts["material"] == {k: names.count(k) for k in parts["material"]}
    for cats in parts.values():
        assert sum(cats.values()) == len(names)
    al = card["albedo"]
    assert 0 < al["parts"] <= len(names) and al["textured_parts"] == len(names) - parts["texture"].get("none", 0)
    assert _total(al["luminance"]) == al["parts"] and all(0 <= x <= 1 for c in al["samples"] for x in c)
    # environment ratios: three frames at 0, three at 0.3 (the sweep)
    env = np.asarray(fr["env_ratio"]["counts"])
    assert (fr["env_ratio"]["min"], fr["env_ratio"]["max"]) == (0.0, 0.3)
    assert env[0] == 3 and env[-1] == 3 and env.sum() == 6
    cov = card["patches"]["coverage"]
    assert cov["sampled"] == cov["of"] == _total(cov) == m["n_patches"]  # small: every patch read


def test_card_on_demand_same_bytes_other_path_and_sampling(rendered, tmp_path):
    from msps_render.dataset.card import write_card

    png, js = (rendered / "card.png").read_bytes(), (rendered / "card.json").read_bytes()
    (rendered / "card.png").unlink()
    (rendered / "card.json").unlink()
    r = cli("card", rendered)
    assert r.returncode == 0, r.stderr
    assert (rendered / "card.png").read_bytes() == png and (rendered / "card.json").read_bytes() == js
    r = cli("card", rendered, "--out", tmp_path / "cards" / "tiny.png")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "cards" / "tiny.json").read_bytes() == js
    assert not [p for p in rendered.iterdir() if p.name.startswith(".")]  # atomic: no temporaries left
    # large datasets: a sample of the patch masks, spread over the shards, says how many of how many
    _, j = write_card(rendered, tmp_path / "s.png", max_patches=4)
    cov = json.loads(j.read_text())["patches"]["coverage"]
    assert cov["sampled"] == _total(cov) == 4 and cov["of"] > 4
    assert "no dataset.json" in one_line_error(cli("card", tmp_path))
    assert ".png" in one_line_error(cli("card", rendered, "--out", tmp_path / "c.jpg"))


def test_preview_shows_every_condition(rendered, tmp_path, monkeypatch):
    """`msps preview` used to fill its samples from the first shards only, leaving out the last
    conditions (the strongest environment light, plans being condition-major)."""
    from msps_render.pipeline import preview as P

    names = [f"shard-{i:05d}.h5" for i in range(12)]
    cond = {nm: f"ratio={i // 3}" for i, nm in enumerate(names)}  # 4 conditions x 3 shards
    for n in (1, 2, 8):
        q = P.sample_quota(names, cond, n)
        assert sum(q.values()) == max(n, 4)
        assert {cond[nm] for nm, k in q.items() if k} == set(cond.values())
    asked = []
    real = P.shard_samples
    monkeypatch.setattr(P, "shard_samples", lambda path, k, rng: (asked.append((Path(path).name, k)), real(path, k, rng))[1])
    P.preview_dataset(rendered, tmp_path / "p.png", n=1)
    m = json.loads((rendered / "dataset.json").read_text())
    shown = {m["shards"][name]["condition"] for name, k in asked if k > 0}
    assert shown == set(m["conditions"])
