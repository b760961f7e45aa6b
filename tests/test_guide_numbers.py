"""docs/reproducing.md quotes numbers that tests pin: the guide's tables must say what the tests check,
so the guide cannot drift from the shipped model (a new model updates the tests, then this fails until
the guide follows)."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

GUIDE = Path(__file__).resolve().parents[1] / "docs" / "reproducing.md"


def _rows(text: str, first: str) -> list[list[str]]:
    """The cells of each row of the table whose header starts with `first`."""
    block = text[text.index(f"| {first}"):].split("\n\n")[0]
    return [[c.strip() for c in ln.strip().strip("|").split("|")] for ln in block.splitlines()[2:]]


def test_diligent_table_is_the_pinned_numbers():
    from test_realbench import DILIGENT_LAMBERTIAN, DILIGENT_NET, DILIGENT_NETCAL

    rows = {r[0]: r[1:] for r in _rows(GUIDE.read_text(), "DiLiGenT object")}
    for o in DILIGENT_LAMBERTIAN:
        assert [float(x) for x in rows[o]] == [DILIGENT_NET[o], DILIGENT_NETCAL[o], DILIGENT_LAMBERTIAN[o]], o
    mean = lambda d: sum(d.values()) / len(d)  # noqa: E731  the guide's "ratio": mean MAE / mean MAE
    want = [f"{mean(DILIGENT_NET):.2f} ({mean(DILIGENT_NET) / mean(DILIGENT_LAMBERTIAN):.2f})",
            f"{mean(DILIGENT_NETCAL):.2f} ({mean(DILIGENT_NETCAL) / mean(DILIGENT_LAMBERTIAN):.3f})",
            f"{mean(DILIGENT_LAMBERTIAN):.2f}"]
    assert rows["mean (ratio)"] == want


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
