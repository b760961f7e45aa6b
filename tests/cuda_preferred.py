"""pytest plugin `-p cuda_preferred`: make the variant resolver of this test process believe a working
NVIDIA GPU is present, so it prefers `cuda_ad_rgb` as it would on a GPU machine.

Used by tests/test_gpu.py to check that tests needing LLVM force it instead of skipping (or, worse,
rendering with a CUDA variant this machine cannot run).  Only this process is affected; `msps`
subprocesses resolve on their own (and see MSPS_VARIANT=llvm where `force_llvm` is in use)."""
from __future__ import annotations


def pytest_configure(config):
    import msps_render.render.variant as V

    real = V.probe_variant

    def probe(variant: str, timeout: float = 120.0):
        return (True, "") if variant.startswith("cuda") else real(variant, timeout)

    V.cuda_device_present = lambda: True
    V.probe_variant = probe
