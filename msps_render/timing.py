"""Per-stage wall-clock timing of the render path (benchmarks/bench_breakdown.py).

The pipeline's own functions (`render_shard`, `render_frame`, `build_scene_dict`)
take an optional `StageTimer` and wrap their steps in `stage(timer, name)`, so a
benchmark measures the real code path.  Why an explicit argument: no global
registry to reset between runs, and `timer=None` (what the pipeline passes) costs
one `nullcontext` per step.  Pure Python: no Mitsuba, no numpy.
"""
from __future__ import annotations

import time
from contextlib import AbstractContextManager, contextmanager, nullcontext
from typing import Callable, Iterator

Probe = Callable[[], dict[str, float]]


class StageTimer:
    """Exclusive wall seconds per named stage, frame by frame.

    Stages may nest; a stage's time excludes its inner stages, so the stages of a
    frame sum to the time spent inside them.  `probe` (optional) is called when a
    stage ends and returns seconds to move out of that stage into other named
    stages, e.g. the drjit kernel compile time of kernels launched inside it
    (`msps_render.render.kernels.KernelLog.probe`).  `frame_counts` (optional) is
    called at the end of each frame; its numbers (e.g. kernels compiled during the
    frame) are kept per frame in `counts`, apart from the stage times.
    """

    def __init__(self, probe: Probe | None = None, frame_counts: Probe | None = None,
                 clock: Callable[[], float] = time.perf_counter):
        self.probe = probe
        self.clock = clock  # time.process_time: CPU seconds, robust on a machine shared with other jobs
        self.frame_counts = frame_counts
        self.frames: list[dict[str, float]] = []
        self.counts: list[dict[str, float]] = []
        self.current: dict[str, float] = {}
        self._inner: list[float] = []

    def add(self, name: str, seconds: float) -> None:
        self.current[name] = self.current.get(name, 0.0) + seconds

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        t0 = self.clock()
        self._inner.append(0.0)
        try:
            yield
        finally:
            total = self.clock() - t0
            own = total - self._inner.pop()
            for other, s in (self.probe() if self.probe else {}).items():
                self.add(other, s)
                own -= s
            self.add(name, own)
            if self._inner:
                self._inner[-1] += total

    def end_frame(self, extra: dict[str, float] | None = None) -> dict[str, float]:
        """Close the current frame (adding `extra` stages) and start the next; returns the closed one."""
        for k, v in (extra or {}).items():
            self.add(k, v)
        done, self.current = self.current, {}
        self.frames.append(done)
        self.counts.append(self.frame_counts() if self.frame_counts else {})
        return done


def stage(timer: StageTimer | None, name: str) -> AbstractContextManager:
    """`timer.stage(name)`, or a no-op without a timer."""
    return nullcontext() if timer is None else timer.stage(name)
