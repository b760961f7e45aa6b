"""scripts/build_wheelhouse.py: the slim Mitsuba it ships renders every preset family msps renders.

Why this test: a GPU visit lost most of its time to a slim wheel without the `gaussian` plugin (hdrfilm's
default reconstruction filter, never named in msps's scene dicts): Mitsuba then fell back to scalar
variants.  Here the installed Mitsuba is copied through the same `keeps` filter the wheel rewrite uses and
the variant probe and frames of the RGB (one-pass and measured materials, textures, environment) and
spectral presets are rendered with that copy in a child process."""
from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("build_wheelhouse", ROOT / "scripts" / "build_wheelhouse.py")
W = importlib.util.module_from_spec(spec)
spec.loader.exec_module(W)

RENDER = """
import sys, numpy as np
sys.path.insert(0, {bench!r})
import mitsuba
assert mitsuba.__file__.startswith({site!r}), mitsuba.__file__
import gpu_check as g
from msps_render.render.variant import probe_variant
for v in ("llvm_ad_rgb", "llvm_ad_spectral", "scalar_rgb"):  # the variant probe's own scene (hdrfilm defaults)
    assert probe_variant(v) == (True, ""), (v, probe_variant(v))
for name, variant in (("paper-train", "llvm_ad_rgb"), ("train-colour", "llvm_ad_rgb"),
                      ("robust-env", "llvm_ad_rgb"), ("spectral-train", "llvm_ad_spectral")):
    spec = g.preset_spec(name)
    from msps_render.render import render_frame
    f = render_frame(spec, variant=variant)
    assert f.mask.sum() > 100 and np.isfinite(f.image).all() and f.image[f.mask].mean() > 0, name
    print(name, "ok")
"""


def test_slim_mitsuba_renders_every_preset_family(tmp_path):
    mi = pytest.importorskip("mitsuba")
    from msps_render.render.variant import probe_variant

    if not probe_variant("llvm_ad_rgb")[0]:
        pytest.skip("llvm_ad_rgb unusable here")
    src = Path(mi.__file__).parent
    site = tmp_path / "site"
    kept = dropped = 0
    for f in src.rglob("*"):
        if f.is_file():
            rel = "mitsuba/" + f.relative_to(src).as_posix()
            if W.keeps(rel, ("llvm_ad_rgb", "llvm_ad_spectral", "scalar_rgb"), W.PLUGINS):
                (site / rel).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(f, site / rel)
                kept += 1
            else:
                dropped += 1
    assert dropped > 50 and not (site / "mitsuba" / "plugins" / "volpath.so").exists()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(site), str(ROOT)]), MSPS_TEST_DATA=str(ROOT.parent / "shared" / "data"))
    r = subprocess.run([sys.executable, "-c", RENDER.format(bench=str(ROOT / "benchmarks"), site=str(site))],
                       capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split().count("ok") == 4, r.stdout


def test_slim_wheel_drops_what_it_should_and_keeps_a_consistent_record(tmp_path):
    """A synthetic wheel: unused variants and plugins, headers and stubs go; the RECORD lists exactly
    the files left (pip verifies it on install); the config names only the kept variants."""
    src, dst = tmp_path / "mitsuba-0-cp312-cp312-linux_x86_64.whl", tmp_path / "slim.whl"
    files = {"mitsuba/__init__.py": b"", "mitsuba/__init__.pyi": b"stub",
             "mitsuba/config.py": b"MI_VARIANTS = ['scalar_rgb', 'llvm_ad_mono', 'cuda_ad_rgb']\n",
             "mitsuba/cuda_ad_rgb.cpython-312-x86_64-linux-gnu.so": b"a",
             "mitsuba/llvm_ad_mono.cpython-312-x86_64-linux-gnu.so": b"b",
             "mitsuba/plugins/gaussian.so": b"c", "mitsuba/plugins/volpath.so": b"d",
             "mitsuba/include/x.h": b"e", "mitsuba/data/srgb.coeff": b"f",
             "mitsuba-0.dist-info/RECORD": b"whatever"}
    with zipfile.ZipFile(src, "w") as z:
        for k, v in files.items():
            z.writestr(k, v)
    W.slim_mitsuba(src, dst, variants=("cuda_ad_rgb",))
    with zipfile.ZipFile(dst) as z:
        names = set(z.namelist())
        record = z.read("mitsuba-0.dist-info/RECORD").decode().split()
        config = z.read("mitsuba/config.py").decode()
    assert names == {"mitsuba/__init__.py", "mitsuba/config.py", "mitsuba/cuda_ad_rgb.cpython-312-x86_64-linux-gnu.so",
                     "mitsuba/plugins/gaussian.so", "mitsuba-0.dist-info/RECORD"}
    assert {ln.split(",")[0] for ln in record} == names
    assert "MI_VARIANTS = ['cuda_ad_rgb']" in config


def test_a_requirement_not_installed_here_is_one_line(tmp_path, monkeypatch):
    """The wheelhouse pins what is installed here; a requirement that is not installed stops the build with
    one line naming it (before anything is downloaded), and neither the output folder nor a temporary
    one is left."""
    monkeypatch.setattr(W, "msps_requirements", lambda extras: ["numpy", "surely-not-a-package-msps>=1"])
    with pytest.raises(SystemExit) as e:
        W.main(["--out", str(tmp_path / "wh")])
    assert str(e.value) == "error: surely-not-a-package-msps is required but not installed here; run scripts/setup.sh first"
    assert list(tmp_path.iterdir()) == []


def test_have_adds_to_the_default_with_a_plus():
    """`--have +a,b` is the default list and a, b (what the GPU visit carries: RGB only, 37.5 MB);
    without '+', the list given is the whole list."""
    default = W.have_set(",".join(W.HAVE))
    plus = W.have_set("+kornia-rs,colour-science")
    assert plus == default | {"kornia-rs", "colour-science"} and "torch" in plus
    assert W.have_set("kornia_rs") == {"kornia-rs"}
