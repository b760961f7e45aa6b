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
    if name.startswith("llvm"):
        from msps_render.render.variant import probe_variant

        ok, why = probe_variant(name)
        if not ok:
            pytest.skip(f"{name} unusable here: {why}")
    mi.set_variant(name)
    return name


@pytest.fixture
def rgb_variant() -> str:
    """The fast RGB variant (llvm_ad_rgb), or skip."""
    return variant_or_skip("llvm_ad_rgb")


@pytest.fixture
def scalar_variant() -> str:
    return variant_or_skip("scalar_rgb")


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


@pytest.fixture
def shared_data() -> Path:
    """../shared/data (third-party assets); skip when absent (a user's fresh clone)."""
    if not SHARED.is_dir():
        pytest.skip("../shared/data not present")
    return SHARED


def pytest_configure(config):
    os.environ.setdefault("MSPS_THREADS", "2")
