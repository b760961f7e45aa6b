"""docs/reproducing.md, the model card (models/README.md) and docs/recipes.md quote numbers that tests pin:
the docs must say what the tests check, so they cannot drift from the shipped model or from each other
(a new model updates the tests, then this fails until the docs follow).

One definition of "ratio" everywhere: a ratio of means, the method's mean MAE over the objects (or
pixel-pooled over the frames) / calibrated Lambertian PS's on the same pixels (docs/history.md "Stage 14").
A "mean (ratio)" row is therefore checked against its own column: the mean of the cells above it, and
that mean over the Lambertian column's."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "docs" / "reproducing.md"
CARD = ROOT / "models" / "README.md"
RECIPES = ROOT / "docs" / "recipes.md"
OBJECTS = ("ball", "cat", "goblet", "pot1")  # the order every doc lists DiLiGenT's objects in
# v0.4 (models/dualcue-cpu-v0.4.pt) alone on DiLiGenT, as docs/recipes.md's table and the model card quote it:
# `msps bench-real .../{ball,cat,goblet,pot1}PNG --checkpoint v0.4=models/dualcue-cpu-v0.4.pt --steps none`
# (measured again 2026-12-04; docs/history.md "Stage 6" has the same four)
DILIGENT_V04 = {"ball": 7.31, "cat": 12.22, "pot1": 18.27, "goblet": 17.70}


def _rows(text: str, first: str) -> list[list[str]]:
    """The cells of each row of the table whose header starts with `first`."""
    block = text[text.index(f"| {first}"):].split("\n\n")[0]
    return [[c.strip() for c in ln.strip().strip("|").split("|")] for ln in block.splitlines()[2:]]


def _mean_cell(column: list[float], lambertian: list[float], shown: str) -> str:
    """What a "mean (ratio)" cell must say for `column`, with the ratio to as many decimals as `shown` has."""
    mean = lambda v: sum(v) / len(v)  # noqa: E731
    if column == lambertian:
        return f"{mean(column):.2f}"
    digits = len(re.search(r"\(\d\.(\d+)\)", shown).group(1))
    return f"{mean(column):.2f} ({mean(column) / mean(lambertian):.{digits}f})"


def _check_diligent_table(text: str, first: str, pinned: list[dict[str, float]]) -> None:
    """A table of DiLiGenT objects x columns (the last column Lambertian PS): each object row equals the
    pinned numbers, and its "mean (ratio)" row is the ratio of means of the cells above it."""
    rows = {r[0]: r[1:] for r in _rows(text, first)}
    assert set(rows) == {*OBJECTS, "mean (ratio)"}, rows
    for o in OBJECTS:
        assert [float(x) for x in rows[o]] == [p[o] for p in pinned], o
    columns = [[p[o] for o in OBJECTS] for p in pinned]
    assert rows["mean (ratio)"] == [_mean_cell(c, columns[-1], s) for c, s in zip(columns, rows["mean (ratio)"])]


def _floats(pattern: str, text: str) -> list[float]:
    m = re.search(pattern, text, flags=re.S)
    assert m, pattern
    return [float(g) for g in m.groups()]


def _card_v05() -> str:
    """The model card's v0.5 section (the shipped model), not the older checkpoints' below it."""
    text = CARD.read_text()
    return text[text.index("## Model card: `dualcue-cpu.pt`"):text.index("## `dualcue-cpu-v0.4.pt`")]


def _card_row(first: str) -> str:
    return next(ln for ln in _card_v05().splitlines() if ln.startswith(f"| {first}"))


def _guide_unseen() -> dict[str, list[float]]:
    """The guide's first table: test set -> [network alone, eval's default, Lambertian PS]."""
    rows = _rows(GUIDE.read_text(), "test |")
    return {re.match(r"`([\w-]+)`", r[0]).group(1): [float(x) for x in r[1:4]] for r in rows}


def test_diligent_table_is_the_pinned_numbers():
    from test_realbench import DILIGENT_LAMBERTIAN, DILIGENT_NET, DILIGENT_NETCAL

    _check_diligent_table(GUIDE.read_text(), "DiLiGenT object", [DILIGENT_NET, DILIGENT_NETCAL, DILIGENT_LAMBERTIAN])


def test_recipes_diligent_table_is_the_pinned_numbers():
    from test_realbench import DILIGENT_LAMBERTIAN, DILIGENT_NET, DILIGENT_NETCAL

    _check_diligent_table(RECIPES.read_text(), "DiLiGenT object |",
                          [DILIGENT_NET, DILIGENT_NETCAL, DILIGENT_V04, DILIGENT_LAMBERTIAN])


def test_recipes_step_numbers_are_the_pinned_numbers():
    from test_realbench import DILIGENT_LAMBERTIAN, DILIGENT_NET, DILIGENT_NETCAL

    text = RECIPES.read_text()
    mean = lambda d: sum(d.values()) / len(d)  # noqa: E731
    net, netcal, lam, r_net, r_netcal = _floats(
        r"takes the shipped network from ([\d.]+)° to ([\d.]+)° mean \(Lambertian\s+PS ([\d.]+)°: "
        r"([\d.]+)× → ([\d.]+)×, ratio of means\)", text)
    assert [net, netcal, lam] == [round(mean(d), 2) for d in (DILIGENT_NET, DILIGENT_NETCAL, DILIGENT_LAMBERTIAN)]
    assert r_net == round(mean(DILIGENT_NET) / mean(DILIGENT_LAMBERTIAN), 2)
    assert r_netcal == round(mean(DILIGENT_NETCAL) / mean(DILIGENT_LAMBERTIAN), 3)
    # predict vs bench-real on cat: the .mat truth gives bench-real's number
    assert _floats(r"--normal-gt \$C/Normal_gt\.mat --out cat/pred\s+# ([\d.]+)°", text) == [DILIGENT_NETCAL["cat"]]
    assert _floats(r"msps bench-real \$C --out cat-bench\s+# ([\d.]+)°", text) == [DILIGENT_NETCAL["cat"]]
    # refine on the grey unseen meshes: the guide's network alone, and the selfcal+refine claim
    alone, refined = _floats(r"\(v0\.5: ([\d.]+)° to ([\d.]+)°", text)
    assert alone == _guide_unseen()["unseen-test-grey"][0]
    pytest.importorskip("torch")
    import test_shipped_targets as t

    grey_claim = dict((s, c) for s, c, _, _ in t.REFINE_CLAIMS)["unseen-test-grey"]
    assert round(refined / _guide_unseen()["unseen-test-grey"][2], 2) == grey_claim


def test_model_card_diligent_is_the_pinned_numbers():
    from test_realbench import DILIGENT_LAMBERTIAN, DILIGENT_NET, DILIGENT_NETCAL

    row = _card_row("real DiLiGenT")
    assert "ball / cat / goblet / pot1" in row
    fours = [[float(x) for x in m] for m in re.findall(r"([\d.]+) / ([\d.]+) / ([\d.]+) / ([\d.]+)°?", row)]
    assert fours == [[d[o] for o in OBJECTS] for d in (DILIGENT_NET, DILIGENT_LAMBERTIAN, DILIGENT_NETCAL)]
    mean = lambda d: sum(d.values()) / len(d)  # noqa: E731
    got = re.findall(r"mean ([\d.]+)° vs ([\d.]+)° = \*\*([\d.]+)×\*\*", row)
    want = [(f"{mean(d):.2f}", f"{mean(DILIGENT_LAMBERTIAN):.2f}",
             f"{mean(d) / mean(DILIGENT_LAMBERTIAN):.{digits}f}") for d, digits in ((DILIGENT_NET, 2), (DILIGENT_NETCAL, 3))]
    assert got == want
    # the v0.4 line further down quotes the same v0.4 numbers as recipes, with the same ratio of means
    v04 = _floats(r"ball / cat / goblet / pot1 ([\d.]+) / ([\d.]+) / ([\d.]+) / ([\d.]+)° \(`msps bench-real`, mean "
                  r"([\d.]+)° vs Lambertian ([\d.]+)° = ([\d.]+)×\)", CARD.read_text())
    assert v04[:4] == [DILIGENT_V04[o] for o in OBJECTS]
    assert v04[4:] == [round(mean(DILIGENT_V04), 2), round(mean(DILIGENT_LAMBERTIAN), 2),
                       round(mean(DILIGENT_V04) / mean(DILIGENT_LAMBERTIAN), 2)]


def test_model_card_unseen_numbers_are_the_guides_and_the_pinned_claims():
    pytest.importorskip("torch")
    import test_shipped_targets as t

    guide = _guide_unseen()
    refine = {s: c for s, c, _, _ in t.REFINE_CLAIMS}
    net, ratio, lam = _floats(r"\| ([\d.]+)° = \*\*([\d.]+) × Lambertian\*\* \(([\d.]+)°\)", _card_row("test (unseen"))
    assert [net, lam] == [guide["unseen-test"][0], guide["unseen-test"][2]] and ratio == t.UNSEEN_CLAIM
    grey = _card_row("grey-Lambertian control")
    alone, lam, ratio = _floats(r"network alone ([\d.]+)° vs Lambertian ([\d.]+)° \(\*\*([\d.]+)×", grey)
    assert [alone, lam] == [guide["unseen-test-grey"][0], guide["unseen-test-grey"][2]] and ratio == t.GREY_CLAIM
    refined, ratio = _floats(r"`--steps selfcal\+refine` ([\d.]+)° \(\*\*([\d.]+)×", grey)
    assert ratio == refine["unseen-test-grey"] == round(refined / lam, 2)
    # the README's (and the guide's) eval-default number, named as the other chain
    assert _floats(r"the README's ([\d.]+)° is `msps eval`'s default chain `selfcal\+segments\+refine`", grey) == \
        [guide["unseen-test-grey"][1]]
    colour, ratio = _floats(r"one saturated colour ([\d.]+)° \(([\d.]+)× Lambertian", _card_row("coloured objects"))
    assert colour == guide["unseen-test-colour"][1] and ratio == refine["unseen-test-colour"]


def test_claims_table_is_the_pinned_claims():
    pytest.importorskip("torch")
    import test_shipped_targets as t

    rows = _rows(GUIDE.read_text(), "test set")
    claims = {(s, "selfcal+refine"): (c, m) for s, c, m, _ in t.REFINE_CLAIMS}
    claims |= {(s, "selfcal+netcal+refine"): (c, m) for s, c, m, _ in t.NETCAL_CLAIMS}
    claims |= {("unseen-test", "none"): (t.UNSEEN_CLAIM, t.UNSEEN_MARGIN),
               ("unseen-test-grey", "none"): (t.GREY_CLAIM, t.GREY_MARGIN)}
    got = {}
    for first, steps, value in rows:
        name = re.match(r"`([\w-]+)`", first).group(1)
        c, m = (float(x) for x in value.split("±"))
        got[(name, steps.strip("`"))] = (c, m)
    assert got == claims and len(rows) == len(claims)
