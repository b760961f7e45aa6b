"""Count drjit kernel launches and compilations (benchmarks/bench_breakdown.py, tests/test_kernels.py).

drjit's kernel history (`JitFlag.KernelHistory`) records every kernel launch
with its hash and how it was served; `dr.kernel_history()` returns the records
since the last call and clears them.  Observed in drjit 1.5 (LLVM backend):
`cache_hit=1, cache_disk=0` = found in the in-memory cache; `cache_hit=1,
cache_disk=1` = not in memory, loaded from the on-disk cache (~/.drjit);
`cache_hit=0` = compiled by LLVM (`backend_time` > 0).  Times are in ms.
A new kernel *hash* is what matters for reuse across scenes: the disk cache
hides recompilation only for kernels some earlier process already compiled.
"""
from __future__ import annotations

from dataclasses import dataclass, field

COMPILE_STAGE = "kernel compile"


@dataclass
class KernelLog:
    """Running totals over drained kernel-history records (JIT kernels only).

    `compile_seconds`: codegen + backend time of launches not served from the
    in-memory cache (a launch served from memory still pays its codegen, which
    stays in the stage that launched it).
    """

    launches: int = 0
    memory_hits: int = 0
    disk_loads: int = 0
    compiled: int = 0
    compile_seconds: float = 0.0
    hashes: set[str] = field(default_factory=set)
    new_hashes: int = 0  # launches whose hash this log had not seen before

    def __post_init__(self) -> None:
        import drjit as dr

        self._prev_flag = dr.flag(dr.JitFlag.KernelHistory)
        dr.kernel_history()  # drop records from before this log
        dr.set_flag(dr.JitFlag.KernelHistory, True)

    def drain(self) -> float:
        """Fold the records since the last call into the totals; returns their compile seconds."""
        import drjit as dr

        seconds = 0.0
        for h in dr.kernel_history([dr.KernelType.JIT]):
            self.launches += 1
            if h["hash"] not in self.hashes:
                self.hashes.add(h["hash"])
                self.new_hashes += 1
            if h["cache_hit"] and not h["cache_disk"]:
                self.memory_hits += 1
                continue
            if h["cache_hit"]:
                self.disk_loads += 1
            else:
                self.compiled += 1
            seconds += (h["codegen_time"] + h["backend_time"]) / 1000.0
        self.compile_seconds += seconds
        return seconds

    def probe(self) -> dict[str, float]:
        """A `StageTimer` probe: moves compile time out of the stage that launched the kernels."""
        return {COMPILE_STAGE: self.drain()}

    def frame_counts(self) -> dict[str, float]:
        """A `StageTimer` frame hook: launches, compiles, disk loads and new hashes since its last call."""
        now = self.snapshot()
        last, self._last = getattr(self, "_last", None) or dict.fromkeys(now, 0), now
        return {k: now[k] - last[k] for k in now}

    def snapshot(self) -> dict[str, float]:
        self.drain()
        return {"launches": self.launches, "memory_hits": self.memory_hits, "disk_loads": self.disk_loads,
                "compiled": self.compiled, "new_hashes": self.new_hashes,
                "compile_seconds": self.compile_seconds}

    def close(self) -> None:
        """Drain and restore the KernelHistory flag as it was."""
        import drjit as dr

        self.drain()
        dr.set_flag(dr.JitFlag.KernelHistory, self._prev_flag)
