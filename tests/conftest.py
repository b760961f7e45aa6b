"""Shared fixtures: Mitsuba variants that skip when unavailable, JIT cleanup, shared data."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def variant_or_skip(name: str) -> str:
    """Set Mitsuba variant `name`, or skip the test when it is missing or its LLVM is unusable."""
    mi = pytest.importorskip("mitsuba")
    if name not in mi.variants():
        pytest.skip(f"Mitsuba variant {name} not built")
    if name.startswith(("llvm", "cuda")):
        from msps_render.render.variant import probe_variant

        ok, why = probe_variant(name)
        if not ok:
            pytest.skip(f"{name} unusable here: {why}")
    mi.set_variant(name)
    return name


# One fixture per Mitsuba variant the tests use (as mitsuba3's own conftest does): the variant
# is set for the test, or the test is skipped where it is missing or its LLVM is unusable.
# MSPS_TEST_JIT=cuda runs the same physics tests with the CUDA variants (a GPU machine without libLLVM).
_JIT = os.environ.get("MSPS_TEST_JIT", "llvm")
VARIANT_FIXTURES = {
    "rgb_variant": f"{_JIT}_ad_rgb",
    "spectral_variant": f"{_JIT}_ad_spectral",
    "scalar_variant": "scalar_rgb",
}


def _variant_fixture(variant: str):
    def fixture() -> str:
        return variant_or_skip(variant)

    fixture.__doc__ = f"Mitsuba variant {variant} (set), or skip."
    return pytest.fixture(fixture)


for _name, _variant in VARIANT_FIXTURES.items():
    globals()[_name] = _variant_fixture(_variant)


@pytest.fixture(scope="module")
def force_llvm():
    """Render this module's tests with Mitsuba's LLVM variant where it works, in this process and in
    every `msps` subprocess (`cli_helpers.llvm_forced`: MSPS_VARIANT=llvm); elsewhere change nothing
    (tests that render skip by their own LLVM check, the others still run).

    Why: the resolver prefers CUDA, so on a GPU machine tests written for LLVM (its speed, its
    numbers) would otherwise skip.  Use `pytestmark = pytest.mark.usefixtures("force_llvm")`."""
    from cli_helpers import llvm_forced

    with llvm_forced() as v:
        yield v


@pytest.fixture
def mitsuba_variant():
    """`mitsuba_variant(name)` sets variant `name` or skips (for tests parametrized over variants)."""
    return variant_or_skip


@pytest.fixture(autouse=True)
def _clean_jit():
    """Like mitsuba3's own fixtures: free JIT kernels/memory between tests."""
    yield
    try:
        import drjit as dr
    except ImportError:
        return
    try:
        dr.sync_thread()
        dr.flush_kernel_cache()
        dr.flush_malloc_cache()
    except Exception:
        pass


@pytest.fixture(scope="module")
def paper_specs() -> list:
    """The 8 scenes of the first `paper-train` shard (blobs of a 9-shape pool, 2-3 materials):
    tests/test_pool.py and tests/test_batch.py."""
    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.plan import frame_rngs, frame_seed, plan
    from msps_render.scene.sample import sample_scene

    cfg = load_config("paper-train", ["dataset.n_shards=1"])
    t = plan(cfg)[0]
    return [sample_scene(cfg.scene, rng, seed=frame_seed(t, j), frame_index=j)
            for j, rng in enumerate(frame_rngs(t, cfg.dataset.frames_per_shard))]


@pytest.fixture
def shared_data() -> Path:
    """../shared/data (third-party assets); skip when absent (a user's fresh clone)."""
    if not SHARED.is_dir():
        pytest.skip("../shared/data not present")
    return SHARED


def pytest_configure(config):
    os.environ.setdefault("MSPS_THREADS", "2")
    if SHARED.is_dir():  # the unseen-* presets read their meshes and map from $MSPS_TEST_DATA
        os.environ.setdefault("MSPS_TEST_DATA", str(SHARED))
