"""Keep pipeline workers' memory flat: drjit's kernel cache and glibc's arenas (docs/benchmarks.md)."""
from __future__ import annotations


KERNEL_BUDGET = 128  # kernels drjit may add to its in-memory cache between two flushes (~0.15 MiB each)


def kernel_budget(n_lights: int) -> int:
    """The kernel budget of a frame with `n_lights` lights: the one-pass integrator unrolls one shadow ray
    per light, so its kernels grow with N (~5 MiB at N = 96); the budget shrinks as N grows, keeping the
    cache's bytes about those of three lights (flushed kernels come back from drjit's disk cache)."""
    return max(4, KERNEL_BUDGET * 3 // max(3, n_lights))


def kernel_cache_misses() -> int:
    """Kernels drjit has added to its in-memory cache in this process so far (compiled by LLVM
    or loaded from its disk cache): `dr.detail.launch_stats()`'s soft + hard misses; 0 without JIT."""
    try:
        import drjit as dr

        _, soft, hard = dr.detail.launch_stats()
        return int(soft) + int(hard)
    except Exception:  # no JIT backend / older drjit
        return 0


def release_frame_memory(misses_before: int | None = None, budget: int = KERNEL_BUDGET) -> None:
    """Free what a finished frame left behind; pipeline workers call it after every frame.

    Two sources of unbounded worker growth, both outside our code
    (benchmarks/bench_memory.py, docs/benchmarks.md "Worker memory"):
    drjit keeps every kernel it ever compiled, and glibc keeps freed heap in its
    arenas (a slow creep and ~20 MiB steps, worst under CPU contention).
    The garbage collector runs first so objects in reference cycles are freed
    (per frame: ~60 small objects, the classes `mi.traverse` defines on each
    call; scenes themselves are freed by reference counting); then drjit's
    malloc cache is flushed, glibc is capped at 2 arenas and `malloc_trim(0)`
    returns the heap.  Only the young generations are collected per frame
    (<1 ms); a full collection walks every live object (~110k, 50-70 ms a frame)
    and runs only when the kernel cache is flushed, and of course whenever
    Python's own thresholds trigger one.

    The kernel cache: scenes of one structure now share their kernels
    (docs/architecture.md "Kernels reused across scenes"), so flushing it after
    every frame threw away exactly what the next frame needs.  With
    `misses_before` (`kernel_cache_misses()` at the start of the frame) it is
    flushed only when the running count of kernels added to it crosses a
    multiple of `budget` during this frame, so it never holds more than `budget`
    plus one frame's kernels (~20 MiB) and memory stays bounded.  Without
    `misses_before` it is flushed every time (the old behaviour).
    """
    import gc

    import drjit as dr

    flush_kernels = misses_before is None or kernel_cache_misses() // budget > misses_before // budget
    gc.collect(2 if flush_kernels else 1)
    try:
        dr.sync_thread()
        if flush_kernels:
            dr.flush_kernel_cache()
        dr.flush_malloc_cache()
    except Exception:  # scalar variants / no JIT backend: nothing cached
        pass
    _malloc_trim()


def _malloc_trim() -> None:
    """Return freed heap to the OS (glibc only; a no-op elsewhere).

    The first call also caps glibc at 2 malloc arenas (M_ARENA_MAX): under CPU
    contention glibc opens a new arena whenever a thread finds the others locked,
    and each arena keeps its own freed memory (RSS steps of ~20 MiB at random moments);
    and fixes the mmap threshold at 4 MiB (large arrays are mapped and unmapped, never heap).
    """
    global _LIBC
    if _LIBC is None:
        import ctypes
        import ctypes.util

        try:
            _LIBC = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            _LIBC.malloc_trim  # noqa: B018 - raises AttributeError off glibc
            _LIBC.mallopt(-8, 2)  # M_ARENA_MAX
            # M_MMAP_THRESHOLD fixed at 4 MiB: glibc otherwise raises it after each large free (up to 32 MiB),
            # so a rig's per-frame arrays (19 MB of per-light images at N = 96, the shard's patches) move into
            # the heap, where fragments of them stay: the worker's floor crept ~50 MiB per shard
            _LIBC.mallopt(-3, 4 << 20)
        except (OSError, AttributeError):
            _LIBC = False
    if _LIBC:
        _LIBC.malloc_trim(0)


_LIBC = None
