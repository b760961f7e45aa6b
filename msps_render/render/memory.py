"""Keep pipeline workers' memory flat: drjit's kernel cache and glibc's arenas (docs/benchmarks.md)."""
from __future__ import annotations


def release_frame_memory() -> None:
    """Free what a finished frame left behind; pipeline workers call it after every frame.

    Two sources of unbounded worker growth, both outside our code
    (benchmarks/bench_memory.py, docs/benchmarks.md "Worker memory"):
    drjit keeps every kernel it ever compiled and each new scene compiles a few
    (the bare-Mitsuba `--repro` loop grows ~0.16 MiB per frame too), and glibc
    keeps freed heap in its arenas (a slow creep and ~20 MiB steps once the kernel
    cache is flushed, worst under CPU contention).  Flushing drjit's kernel and
    malloc caches, capping glibc's arenas and `malloc_trim(0)` keep RSS flat for
    ~1-5% of a paper-size frame's time.  `gc.collect()` first so scenes
    held by reference cycles release their buffers.
    """
    import gc

    import drjit as dr

    gc.collect()
    try:
        dr.sync_thread()
        dr.flush_kernel_cache()
        dr.flush_malloc_cache()
    except Exception:  # scalar variants / no JIT backend: nothing cached
        pass
    _malloc_trim()


def _malloc_trim() -> None:
    """Return freed heap to the OS (glibc only; a no-op elsewhere).

    The first call also caps glibc at 2 malloc arenas (M_ARENA_MAX): under CPU
    contention glibc opens a new arena whenever a thread finds the others locked,
    and each arena keeps its own freed memory (RSS steps of ~20 MiB at random moments).
    """
    global _LIBC
    if _LIBC is None:
        import ctypes
        import ctypes.util

        try:
            _LIBC = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            _LIBC.malloc_trim  # noqa: B018 - raises AttributeError off glibc
            _LIBC.mallopt(-8, 2)  # M_ARENA_MAX
        except (OSError, AttributeError):
            _LIBC = False
    if _LIBC:
        _LIBC.malloc_trim(0)


_LIBC = None
