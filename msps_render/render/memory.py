"""Keep pipeline workers' memory flat: drjit's kernel cache and glibc's arenas (docs/benchmarks.md)."""
from __future__ import annotations

from dataclasses import dataclass

KERNEL_BUDGET = 128  # kernels drjit may add to its in-memory cache between two flushes (~0.15 MiB each)


@dataclass(frozen=True)
class MemoryBudget:
    """What a worker keeps cached from one frame to the next: drjit kernels added between two flushes,
    measured tables kept mapped, loaded scenes (`render/pool.py`) and bytes of canonical meshes
    (`scene/shapes.py`); None: that cache's own limit ($MSPS_TABLE_CACHE, 16 scenes, 32 MiB)."""

    kernels: int = KERNEL_BUDGET
    tables: int | None = None
    scenes: int | None = None
    mesh_bytes: int | None = None
    batch: int = 64  # frames one launch may render (`dataset.batch_frames` is capped at it)


def frame_budget(n_lights: int) -> MemoryBudget:
    """The budget after a frame with `n_lights` lights.  Why it shrinks as N grows: a frame's own
    memory (film, N images, the shard's N-image patches) grows with N, so what is kept between frames
    must shrink for a worker to stay within its memory at N = 96 (docs/benchmarks.md "Any rig").
    The one-pass integrator unrolls one shadow ray per light, so its kernels grow with N (~5 MiB at
    N = 96): the kernel budget keeps the cache's bytes about those of three lights (flushed kernels
    come back from drjit's disk cache).  A measured table is 16.7 MiB of every worker's RSS while
    mapped, and mapping it again costs ~1 ms (page cache shared by the workers): beyond three lights
    only 2 stay mapped.  Pooled scenes (~3 MB) and canonical meshes (~0.7 MB) save a BVH build or a
    mesh generation (tens of ms) when a shape comes back, a small share of a many-light frame, and
    presets such as `classic-train` draw a new shape every frame.  Three-light frames keep today's
    budget.  Pixels never depend on any of it (tests/test_pool.py, test_scale_memory.py) -- but for
    `batch`: a batch's film holds N images of each of its frames (8 frames of 64 lights: 930 MiB of
    RSS against 510 unbatched; 2 frames: 580), so beyond three lights at most 128 // N frames share a
    launch (one when N > 64).  It depends on N alone, so a config's batches are always the same."""
    if n_lights <= 3:
        return MemoryBudget()
    return MemoryBudget(kernels=max(4, KERNEL_BUDGET * 3 // n_lights), tables=2, scenes=2, mesh_bytes=4 << 20,
                        batch=max(1, 128 // n_lights))


def kernel_cache_misses() -> int:
    """Kernels drjit has added to its in-memory cache in this process so far (compiled by LLVM
    or loaded from its disk cache): `dr.detail.launch_stats()`'s soft + hard misses; 0 without JIT."""
    try:
        import drjit as dr

        _, soft, hard = dr.detail.launch_stats()
        return int(soft) + int(hard)
    except Exception:  # no JIT backend / older drjit
        return 0


def release_frame_memory(misses_before: int | None = None, budget: MemoryBudget = MemoryBudget()) -> None:
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
    multiple of `budget.kernels` during this frame, so it never holds more than that
    plus one frame's kernels (~20 MiB) and memory stays bounded.  `budget.tables`,
    `budget.mesh_bytes`: measured tables and canonical meshes kept (`frame_budget`; the worker's
    scene pool is trimmed by its owner, `pipeline/execute.py`).  Without
    `misses_before` it is flushed every time (the old behaviour).
    """
    import gc

    import drjit as dr

    if budget.tables is not None:  # before the collection, so unmapped tables leave with this frame's scene
        from msps_render.render.merl_bsdf import device_table

        device_table.trim(budget.tables)
    if budget.mesh_bytes is not None:
        from msps_render.scene.shapes import trim_canonical_cache

        trim_canonical_cache(budget.mesh_bytes)
    k = budget.kernels
    flush_kernels = misses_before is None or kernel_cache_misses() // k > misses_before // k
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
