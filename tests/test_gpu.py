"""GPU-ready tests (issue 21): the CUDA variant renders the frames LLVM renders, tests that need LLVM
force it where CUDA is preferred, and a CUDA variant that fails its probe says why."""
from __future__ import annotations

import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from msps_render.errors import InputError

import msps_render.render.variant as V

TESTS = Path(__file__).resolve().parent
NEED_LLVM = ("test_pipeline", "test_faults", "test_export", "test_eval_report", "test_recipes", "test_cli_help")


def _gpu_or_skip(also_llvm: bool = False) -> None:
    if not V.cuda_device_present():
        pytest.skip("no NVIDIA driver on this machine")
    ok, why = V.probe_variant("cuda_ad_rgb")
    if not ok:
        pytest.skip(f"cuda_ad_rgb unusable here: {why}")
    if also_llvm and not V.probe_variant("llvm_ad_rgb")[0]:  # a GPU node often has no shared libLLVM:
        pytest.skip("llvm_ad_rgb unusable here (benchmarks/gpu_check.py compares against carried LLVM renders)")


def _merl_one_pass_spec():
    """A real training frame: measured (MERL-table) materials only, three lights in one pass."""
    from msps_render.scene.sample import SceneConfig, sample_scene

    cfg = SceneConfig.model_validate({
        "camera": {"width": 64, "height": 64}, "integrator": {"spp": 16, "max_depth": 3, "lights": "one-pass"},
        "materials": {"merl_fraction": 1.0, "measured": "nbrdf", "min_count": 2, "max_count": 2}})
    spec = sample_scene(cfg, np.random.default_rng(4), seed=4)
    assert spec.integrator.lights == "one-pass" and all(m.kind == "merl" for m in spec.materials)
    return spec


def test_cuda_frame_equals_llvm_frame():
    """cuda_ad_rgb vs llvm_ad_rgb on one frame (one-pass integrator, MERL plugin, ground truth).

    Both backends run the same kernels on the same PCG32 sample streams (same seed, same wavefront
    size), so they differ only by float rounding (CUDA's approximate rcp/sqrt/trig intrinsics, FMA
    contraction).  Ground truth comes from one ray per pixel centre: normals agree to well below a
    degree, the mask except where a ray grazes the silhouette.  The image: a rounding difference can
    flip one of a pixel's 16 samples across a shadow or material-bin edge (1/16 of that pixel), so we
    bound the median relative error tightly, the share of pixels off by > 5 % loosely, and the frame's
    total radiance at 0.5 %.  A wrong plugin, a missing light or a mis-ordered film channel fails all
    three by orders of magnitude."""
    _gpu_or_skip(also_llvm=True)
    from msps_render.render import render_frame

    spec = _merl_one_pass_spec()
    a = render_frame(spec, variant="llvm_ad_rgb")
    b = render_frame(spec, variant="cuda_ad_rgb")
    assert a.meta["lights"] == b.meta["lights"] == "one-pass"
    both = a.mask & b.mask
    assert (a.mask != b.mask).mean() < 0.005 and both.sum() > 500
    cos = np.clip((a.normal[both] * b.normal[both]).sum(-1), -1, 1)
    assert np.percentile(np.degrees(np.arccos(cos)), 99) < 0.1
    np.testing.assert_allclose(a.depth[both], b.depth[both], rtol=1e-4)
    ia, ib = a.image[both], b.image[both]
    rel = np.abs(ia - ib) / np.maximum(np.abs(ia), 1e-3 * ia.max())
    assert np.median(rel) < 1e-3, np.median(rel)
    assert (rel.max(-1) > 0.05).mean() < 0.02
    assert abs(ib.sum() / ia.sum() - 1) < 0.005


def test_cuda_probe_failure_is_the_exception_text():
    """Where CUDA cannot run, the probe's reason is the child's exception line (this machine: drjit's
    'the CUDA backend hasn't been initialized'), not an empty string or a traceback frame."""
    mi = pytest.importorskip("mitsuba")
    if "cuda_ad_rgb" not in mi.variants():
        pytest.skip("cuda_ad_rgb not built into this Mitsuba")
    ok, why = V.probe_variant("cuda_ad_rgb")
    if ok:
        pytest.skip("CUDA works here")
    assert re.match(r"^[A-Za-z_][\w.]*(Error|Exception)\b", why), why


def test_failure_line_finds_the_exception_behind_exit_noise():
    tb = ("Traceback (most recent call last):\n  File \"<string>\", line 3, in <module>\n"
          "ImportError: jit_init_thread_state(): the CUDA backend hasn't been initialized.\n"
          "drjit-autodiff: variable leak detected (2 variables remain in use)!\n")
    assert V.failure_line(tb, 1).startswith("ImportError: jit_init_thread_state()")
    assert V.failure_line("", 134) == "exit code 134"
    assert V.failure_line("Segmentation fault\n", -11) == "Segmentation fault"


def test_gpu_present_but_cuda_fails_warns_why_and_uses_llvm(monkeypatch):
    """The real probe failure text (not a stub) reaches the warning."""
    monkeypatch.delenv("MSPS_VARIANT", raising=False)
    ok, why = V.probe_variant("cuda_ad_rgb")
    if ok:
        pytest.skip("CUDA works here")
    if not V.probe_variant("llvm_ad_rgb")[0]:
        pytest.skip("llvm_ad_rgb unusable here")
    monkeypatch.setattr(V, "cuda_device_present", lambda: True)
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        assert V.resolve_variant("rgb") == "llvm_ad_rgb"
    msgs = [str(w.message) for w in got if issubclass(w.category, V.VariantFallbackWarning)]
    assert len(msgs) == 1 and why in msgs[0] and "using llvm_ad_rgb" in msgs[0], msgs


def test_msps_variant_backend_shorthand(monkeypatch):
    pytest.importorskip("mitsuba")
    monkeypatch.setattr(V, "probe_variant", lambda v, *a, **kw: (True, ""))  # the expansion, not this machine's GPU
    for env, mode, want in (("llvm", "rgb", "llvm_ad_rgb"), ("llvm", "spectral", "llvm_ad_spectral"),
                            ("scalar", "spectral", "scalar_spectral"), ("cuda", "rgb", "cuda_ad_rgb")):
        monkeypatch.setenv("MSPS_VARIANT", env)
        assert V.resolve_variant(mode) == want
    monkeypatch.undo()
    monkeypatch.setenv("MSPS_VARIANT", "cuda")  # asked for by name where it cannot run: one clear error
    if not V.probe_variant("cuda_ad_rgb")[0]:
        with pytest.raises(InputError, match="MSPS_VARIANT: .*cuda_ad_rgb.*does not work"):
            V.resolve_variant("rgb")


def test_force_llvm_beats_a_cuda_preference(monkeypatch):
    """With the resolver preferring CUDA (stubbed GPU), `llvm_forced` (the `force_llvm` fixture)
    makes this process and an `msps`-style subprocess resolve LLVM; the six modules use it."""
    from cli_helpers import llvm_forced

    monkeypatch.delenv("MSPS_VARIANT", raising=False)
    real = V.probe_variant
    monkeypatch.setattr(V, "cuda_device_present", lambda: True)
    monkeypatch.setattr(V, "probe_variant", lambda v, timeout=120.0: (True, "") if v.startswith("cuda")
                        else real(v, timeout))
    assert V.resolve_variant("rgb") == "cuda_ad_rgb"  # the preference is in effect
    with llvm_forced() as v:
        if v is None:
            pytest.skip("llvm_ad_rgb unusable here")
        assert V.resolve_variant("rgb") == "llvm_ad_rgb"
        r = subprocess.run([sys.executable, "-c", "from msps_render.render.variant import resolve_variant as r;"
                            "print(r('rgb'), r('spectral'))"], capture_output=True, text=True, env=os.environ)
        assert r.stdout.split() == ["llvm_ad_rgb", "llvm_ad_spectral"], r.stderr
    assert V.resolve_variant("rgb") == "cuda_ad_rgb"  # restored afterwards
    for name in NEED_LLVM:
        assert 'pytest.mark.usefixtures("force_llvm")' in (TESTS / f"{name}.py").read_text(), name


# One test per module that renders (and so skipped where the resolver preferred CUDA before).
RENDERING = ["test_pipeline.py::test_reference_dataset_is_complete_and_verifies",
             "test_faults.py::test_force_deletes_only_toolkit_files",
             "test_export.py::test_png16_and_exr_read_back_equal_the_shard",
             "test_eval_report.py::test_eval_writes_its_plots_and_the_per_object_numbers_add_up",
             "test_recipes.py::test_recipe_1_own_meshes_fixed_frames_per_mesh",
             "test_cli_help.py::test_render_scene_writes_per_light_pngs_and_part_map_and_says_what_it_does"]


@pytest.mark.slow
def test_llvm_modules_run_not_skip_where_cuda_is_preferred():
    """The six modules under `-p cuda_preferred` (the resolver believes a working GPU is present):
    one rendering test of each passes instead of skipping (before: all skipped)."""
    if not V.probe_variant("llvm_ad_rgb")[0]:
        pytest.skip("llvm_ad_rgb unusable here")
    env = dict(os.environ, PYTHONPATH=str(TESTS), MSPS_THREADS="1")
    env.pop("MSPS_VARIANT", None)
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "cuda_preferred",
                        "-rs", *[str(TESTS / t) for t in RENDERING]], capture_output=True, text=True, env=env,
                       cwd=TESTS.parent, timeout=1800)
    tail = r.stdout[-3000:]
    assert r.returncode == 0 and f"{len(RENDERING)} passed" in tail and "skipped" not in tail, tail
