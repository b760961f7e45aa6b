"""Choosing a Mitsuba variant: CUDA when a working GPU is present, else the LLVM JIT when it
really works, else scalar.

Why a subprocess probe: drjit's LLVM backend needs a shared libLLVM it can use;
an unusable one (e.g. LLVM 14 here) can abort the whole process, which no
try/except can catch.  So we try the LLVM variant once in a child process and
remember the answer for this process (`lru_cache`), then workers receive the
resolved name explicitly.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
import warnings
from functools import lru_cache

from msps_render.errors import InputError, closest, env_count

# fastest first; the last entry always works (no JIT)
PREFERRED = {"rgb": ("cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb"),
             "spectral": ("cuda_ad_spectral", "llvm_ad_spectral", "scalar_spectral")}


def cuda_device_present() -> bool:
    """A cheap check before the CUDA probe (which costs a child process): an NVIDIA driver is loaded."""
    return os.path.exists("/dev/nvidiactl") or os.path.exists("/proc/driver/nvidia/version")

_PROBE = """
import mitsuba as mi, drjit as dr
mi.set_variant({variant!r})
s = mi.load_dict({{'type': 'scene', 'sphere': {{'type': 'sphere'}},
    'sensor': {{'type': 'orthographic', 'film': {{'type': 'hdrfilm', 'width': 4, 'height': 4}}}},
    'light': {{'type': 'constant'}}, 'integrator': {{'type': 'direct'}}}})
img = mi.render(s, spp=1)
dr.eval(img)
print('OK')
"""


class VariantFallbackWarning(RuntimeWarning):
    pass


def mitsuba_info() -> dict:
    """{'mitsuba': version, 'variants': [...]} of the installed Mitsuba ({'mitsuba': None} without it)."""
    try:
        import mitsuba as mi
    except ImportError:
        return {"mitsuba": None}
    return {"mitsuba": mi.__version__, "variants": mi.variants()}


@lru_cache(maxsize=None)
def probe_variant(variant: str, timeout: float = 120.0) -> tuple[bool, str]:
    """Run a tiny render in a child process; (works, reason: the child's exception text)."""
    try:
        r = subprocess.run([sys.executable, "-c", _PROBE.format(variant=variant)], capture_output=True,
                           text=True, timeout=timeout, env=os.environ.copy())
    except subprocess.TimeoutExpired:
        return False, f"probe of {variant} timed out"
    if r.returncode == 0 and "OK" in r.stdout:
        return True, ""
    return False, failure_line(r.stderr or r.stdout, r.returncode)


_EXC_LINE = re.compile(r"^[A-Za-z_][\w.]*(Error|Exception|Exit|Interrupt)\b.*")


def failure_line(text: str, returncode: int) -> str:
    """The exception line of a child's traceback ('ImportError: ...'), even when something is printed
    after it (drjit's exit-time leak reports); else its last line; else its exit code."""
    lines = [ln.strip() for ln in (text or "").splitlines() if ln.strip()]
    exc = [ln for ln in lines if _EXC_LINE.match(ln)]
    line = (exc or lines or [f"exit code {returncode}"])[-1]
    return line[:300]


BACKENDS = ("cuda", "llvm", "scalar")  # MSPS_VARIANT=llvm: the LLVM variant of whatever mode is rendered


def _expand_backend(value: str, mode: str) -> str:
    """'llvm' -> the preferred LLVM variant of `mode`; a full variant name is returned as it is."""
    if value in BACKENDS:
        return next((v for v in PREFERRED[mode] if v.startswith(value)), value)
    return value


def check_variant(variant: str, mode: str = "rgb", source: str = "--variant") -> str:
    """`variant` if this Mitsuba has it, it renders `mode` ('rgb' / 'spectral') and it works here,
    else an `InputError` naming `source` (the option or variable that asked for it).

    Why before any work: a wrong one otherwise fails in a worker, with a traceback, after the
    output directory exists.  JIT variants are probed like the automatic choice (cached)."""
    import mitsuba as mi

    have = list(mi.variants())
    if variant not in have:
        raise InputError(source, f"Mitsuba variant '{variant}' is not available{closest(variant, have)} "
                                 f"(have: {', '.join(have)})")
    if mode not in variant.split("_"):
        fits = [v for v in have if mode in v.split("_")]
        raise InputError(source, f"Mitsuba variant '{variant}' cannot render a {mode}-mode config (scene.mode = "
                                 f"'{mode}'); use one of: {', '.join(fits) or 'none built'}")
    if not variant.startswith("scalar"):
        ok, why = probe_variant(variant)
        if not ok:
            raise InputError(source, f"Mitsuba variant '{variant}' does not work on this machine ({why})")
    return variant


def resolve_variant(mode: str = "rgb", requested: str | None = None) -> str:
    """The variant to render with. `requested` (`--variant`) or `MSPS_VARIANT` force one (checked): a
    variant name, or a backend ('cuda', 'llvm', 'scalar') meaning that backend's variant for `mode`
    (tests force LLVM this way whatever the machine prefers).  When a faster variant fails its
    probe, the warning says why (the probe's exception text)."""
    import mitsuba as mi

    if requested:
        return check_variant(_expand_backend(requested, mode), mode, "--variant")
    if os.environ.get("MSPS_VARIANT"):
        return check_variant(_expand_backend(os.environ["MSPS_VARIANT"], mode), mode, "MSPS_VARIANT")
    *fast, slow = PREFERRED[mode]
    reasons = []
    for v in fast:
        if v not in mi.variants():
            reasons.append(f"{v}: not built into this Mitsuba")
        elif v.startswith("cuda") and not cuda_device_present():
            continue  # no GPU: not worth a probe, and not worth a warning
        else:
            ok, why = probe_variant(v)
            if ok:
                gpu = [r for r in reasons if r.startswith("cuda")]
                if gpu and cuda_device_present():  # a GPU is there but its variant fails: say why
                    warnings.warn(f"Mitsuba's CUDA variant is unusable ({gpu[0]}); using {v} instead",
                                  VariantFallbackWarning, stacklevel=2)
                return v
            reasons.append(f"{v}: {why}")
    warnings.warn(f"Mitsuba variant {fast[-1]} is unusable ({'; '.join(reasons)}); falling back to {slow}, "
                  f"which is much slower. Install a shared libLLVM >= 15 (Debian: apt-get install libllvm19).",
                  VariantFallbackWarning, stacklevel=2)
    return slow


def flush_denormals() -> bool:
    """Flush denormal floats to zero on the calling thread (x86-64 MXCSR FTZ and DAZ), as drjit's worker
    threads run (Embree asks it of every thread that traces rays); True when set.

    Why: with one thread drjit runs a kernel on the calling thread, with more on its workers; a value
    that underflows then differs, and a rare sample came out inf at one thread and finite at two
    (spectral-train, docs/benchmarks.md "Every rig batches").  The same MXCSR on every thread makes a
    render independent of its thread count.  Linux x86-64 (glibc's fenv_t: MXCSR at byte 28) only."""
    import ctypes
    import platform

    if sys.platform != "linux" or platform.machine() not in ("x86_64", "AMD64"):
        return False
    try:
        libm = ctypes.CDLL("libm.so.6")
        env = (ctypes.c_uint8 * 32)()
        if libm.fegetenv(env) != 0:
            return False
        mxcsr = int.from_bytes(bytes(env[28:32]), "little")
        if mxcsr & 0x8040 != 0x8040:
            env[28:32] = list((mxcsr | 0x8040).to_bytes(4, "little"))
            if libm.fesetenv(env) != 0:
                return False
        return True
    except OSError:
        return False


THREADS_ENV = "MSPS_THREADS"


def env_threads() -> int | None:
    """Render threads from $MSPS_THREADS, None when unset (a bad value was a traceback from `int()` or drjit)."""
    return env_count(THREADS_ENV, "render threads")


def activate(variant: str, threads: int | None = None):
    """Set the Mitsuba variant (and thread count) for this process, with denormals flushed on this thread
    as on drjit's workers (`flush_denormals`); returns the `mi` module."""
    import drjit as dr
    import mitsuba as mi

    flush_denormals()
    if mi.variant() != variant:
        mi.set_variant(variant)
    threads = threads or env_threads()
    if threads:
        dr.set_thread_count(int(threads))
    return mi


def register_plugin(kind: str, name: str, plugin_class, registered: set[str], variant: str | None = None) -> str:
    """Register Python plugin `name` (`kind` 'bsdf' or 'integrator') for the current variant, once.

    Why per variant: a Python plugin subclasses the variant's `mi.BSDF` / `mi.SamplingIntegrator`,
    so `plugin_class(variant)` builds the class for it; `registered` is the caller's set of
    variants done (given or current; a given one must be current)."""
    import mitsuba as mi

    v = variant or mi.variant()
    if v is None:
        raise RuntimeError(f"set a Mitsuba variant before registering the {name} plugin")
    if v not in registered:
        cls = plugin_class(v)
        getattr(mi, f"register_{kind}")(name, lambda props: cls(props))
        registered.add(v)
    return v
