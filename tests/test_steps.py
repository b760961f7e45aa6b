"""The test-time steps as one value (models/steps.py) and the bad inputs it refuses (issue 36):
an unknown step, two colour steps at once, a step that needs a network or the rig without one --
one line naming the step and what is missing, exit 1, nothing written."""
from __future__ import annotations

import json

import numpy as np
import pytest

from cli_helpers import cli, one_line_error
from msps_render.calibration import Rig
from msps_render.errors import InputError
from msps_render.models.steps import STEPS, Steps, from_flags


def test_parse_orders_names_and_adds_implied_steps():
    assert Steps.parse("refine+netcal") == Steps(("selfcal", "netcal", "refine"))
    assert str(Steps.parse(" segments ")) == "selfcal+segments"  # segments works on selfcal's result
    assert Steps.parse("none") == Steps() and str(Steps()) == "none"
    assert Steps.parse("mirror+selfcal").suffix == "+selfcal+mirror"  # the registry's order names columns
    for s in ("selfcal+netcal+refine", "selfcal+mirror", "refine"):
        assert str(Steps.parse(s)) == s  # canonical spellings round-trip


def test_every_registered_step_has_a_known_stage_and_a_record():
    from msps_render.models.steps import STAGES

    assert list(STEPS) == ["selfcal", "segments", "netcal", "mirror", "refine"]
    for s in STEPS.values():
        assert s.stage in STAGES and s.description and callable(s.apply) and callable(s.record)
        assert all(i in STEPS for i in s.implies)
    assert [n for n, s in STEPS.items() if s.colour] == ["segments", "netcal"]


@pytest.mark.parametrize("text, what", [("selfcall", "did you mean 'selfcal'"), ("netcal+refin", "did you mean 'refine'"),
                                        ("selfcal++refine", "joined by '+'"), ("", "joined by '+'")])
def test_unknown_or_malformed_steps(text, what):
    with pytest.raises(InputError, match="--steps") as e:
        Steps.parse(text)
    assert what in str(e.value)


def test_two_colour_steps_are_refused():
    with pytest.raises(InputError, match="segments and netcal are two ways to divide out the albedo colour"):
        Steps.parse("segments+netcal")
    with pytest.raises(InputError, match="^--netcal: segments and netcal"):  # the old flags name the flag
        from_flags(False, segments=True, netcal=True)


def test_needs_a_network_and_the_rig():
    rig = Rig(np.eye(3), np.eye(3))
    for name in ("netcal", "mirror", "refine"):
        with pytest.raises(InputError, match=f"^--steps [a-z+]*{name}[a-z+]*: {name} .*Lambertian"):
            Steps.parse(name).check(network=False, rig=rig)
    for name in ("selfcal", "segments", "netcal", "refine"):
        with pytest.raises(InputError, match=r"^--steps [a-z+]+: (selfcal|refine) needs the rig \(light directions"):
            Steps.parse(name).check(network=True, rig=None)
    Steps().check(network=False, rig=None)  # the raw predictor needs neither


def test_old_flags_map_to_the_old_columns():
    cols = from_flags(True, selfcal=True, segments=True, netcal=True, mirror=True, refine=True)
    assert [str(c) for c in cols][:6] == ["none", "selfcal", "selfcal+segments", "selfcal+netcal", "mirror",
                                          "selfcal+mirror"]
    assert len(cols) == 16 and all(c.alias for c in cols)
    assert [str(c) for c in from_flags(False, netcal=True, refine=True)] == ["selfcal+netcal+refine"]
    assert from_flags(True) == []


def _image(tmp_path):
    np.save(tmp_path / "img.npy", np.full((48, 48, 3), 0.5, np.float32))
    return tmp_path / "img.npy"


@pytest.mark.parametrize("args, words", [
    (["--steps", "selfcall"], ["--steps selfcall", "unknown step 'selfcall'", "did you mean 'selfcal'"]),
    (["--steps", "segments+netcal"], ["--steps segments+netcal", "two ways to divide out the albedo colour"]),
    (["--steps", "refine", "--method", "lambertian"], ["--steps refine", "refine refines a network's normals"]),
    (["--steps", "mirror", "--light-dirs", json.dumps([[0.5, 0, 0.866], [-0.1, 0.4, 0.91], [-0.3, -0.3, 0.9]])],
     ["--steps mirror", "no mirror symmetry"]),
    (["--steps", "selfcal", "--selfcal"], ["--steps", "not both"]),
])
def test_predict_refuses_bad_steps_in_one_line(tmp_path, args, words):
    r = cli("predict", _image(tmp_path), "--out", tmp_path / "o", *args)
    line = one_line_error(r)
    assert all(w in line for w in words), line
    assert not list(tmp_path.glob("o*"))


@pytest.mark.parametrize("args, words", [
    (["--steps", "none", "--steps", "netcal+segments"], ["--steps netcal+segments", "give one"]),
    (["--steps", "refne"], ["unknown step 'refne'", "did you mean 'refine'"]),
])
def test_eval_and_bench_real_refuse_bad_steps_in_one_line(tmp_path, args, words):
    r = cli("eval", "--data", tmp_path / "nowhere", "--out", tmp_path / "ev", *args)
    line = one_line_error(r)
    assert all(w in line for w in words), line
    assert not (tmp_path / "ev" / "metrics.json").exists()
    r = cli("bench-real", tmp_path / "nowhere", "--out", tmp_path / "br", *args)
    line = one_line_error(r)
    assert all(w in line for w in words), line
    assert not (tmp_path / "br").exists()


def test_predict_steps_none_is_the_raw_network(tmp_path):
    """`--steps none` and no steps give the same normals; `--steps selfcal` records what it did."""
    img = _image(tmp_path)
    outs = {}
    for name, args in (("plain", []), ("none", ["--steps", "none"]), ("sc", ["--steps", "selfcal"])):
        r = cli("predict", img, "--out", tmp_path / name, "--quiet", *args)
        assert r.returncode == 0, r.stderr
        outs[name] = np.load(tmp_path / f"{name}.npy")
    np.testing.assert_array_equal(outs["plain"], outs["none"])
    np.testing.assert_array_equal(outs["plain"], outs["sc"])  # a flat grey image: selfcal keeps it as it is


def test_eval_steps_columns_equal_the_old_flags(tmp_path):
    """`--steps none --steps selfcal` gives the columns `--selfcal` gave, with the same numbers."""
    from cli_helpers import render_tiny
    from test_selfcal import COLOUR_SET

    render_tiny(COLOUR_SET, tmp_path)
    got = {}
    for name, args in (("steps", ["--steps", "none", "--steps", "selfcal"]), ("flag", ["--selfcal"])):
        r = cli("eval", "--data", tmp_path / "ds", "--out", tmp_path / name, "--method", "lambertian", *args)
        assert r.returncode == 0, r.stderr
        got[name] = json.loads((tmp_path / name / "metrics.json").read_text())
    assert list(got["steps"]["methods"]) == list(got["flag"]["methods"]) == ["lambertian", "lambertian+selfcal"]
    assert got["steps"]["table"] == got["flag"]["table"]
    assert got["steps"]["methods"]["lambertian+selfcal"]["steps"] == "selfcal"


def test_the_defaults_are_the_validated_chains_and_skip_nothing_silently():
    """docs/history.md "Stage 14": photographs selfcal+netcal, rendered sets selfcal+segments+refine.  Under a
    default the baseline runs without steps (it cannot take netcal or refine); asked for explicitly, a
    network-only step with no network is one line."""
    from msps_render.errors import InputError
    from msps_render.models.predict import predict_method
    from msps_render.models.runner import default_checkpoint, lambertian_predictor, checkpoint_predictor, methods
    from msps_render.models.steps import DEFAULT_PHOTOS, DEFAULT_RENDERED, Steps

    assert DEFAULT_PHOTOS == Steps.parse("selfcal+netcal") and DEFAULT_RENDERED == Steps.parse("selfcal+segments+refine")
    net, lam = checkpoint_predictor(default_checkpoint()), lambertian_predictor()
    assert [m.name for m in methods([net, lam], [DEFAULT_RENDERED])] == ["net+selfcal+segments+refine", "lambertian"]
    assert [str(m.steps) for m in methods([lam], [DEFAULT_PHOTOS])] == ["none"]
    assert str(predict_method("lambertian").steps) == "none" and str(predict_method().steps) == "selfcal+netcal"
    with pytest.raises(InputError, match="refine"):
        methods([lam], [Steps.parse("selfcal+refine")])


# ------------------------------------------------------------------ the registry's hooks (issue 43 item 5)
@pytest.mark.parametrize("name", list(STEPS))
def test_every_registered_step_has_its_stage_hooks(name):
    """Each step carries what its stage's patch path calls: predictor -> batch, normals -> frame + patches."""
    st = STEPS[name]
    if st.stage == "predictor":
        assert callable(st.batch)
    if st.stage == "normals":
        assert callable(st.frame) and callable(st.patches)


def test_a_normals_step_without_hooks_is_refused_at_registration():
    from msps_render.models.steps import Step

    with pytest.raises(ValueError, match="needs the hook"):
        Step("bad", "normals", lambda s: s, "", lambda f: {}, lambda f: "")
    with pytest.raises(ValueError, match="needs the hook"):
        Step("bad", "predictor", lambda s: s, "", lambda f: {}, lambda f: "", whole_image=False)


def test_duplicate_steps_are_an_error():
    with pytest.raises(InputError, match="given twice"):
        Steps.parse("selfcal+selfcal")
