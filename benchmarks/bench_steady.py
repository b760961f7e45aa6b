"""Steady state of one render worker: per-shard wall time over a long run (docs/benchmarks.md).

    MSPS_THREADS=1 .venv/bin/python benchmarks/bench_steady.py --shards 40 [--preset paper-train]
        [--profile 15]   # cProfile the last 15 shards (functions by cumulative time)

Renders the first N shards of a preset in THIS process through the pipeline's own
`render_shard`, one after the other, and prints every 5 shards the last shard's wall time
and (where the code has `msps_render.timing`) the mean seconds per frame of each stage over
the last 40 frames.  The first shards pay MERL table reads and kernel compiles; the later
ones show the per-frame floor a long run settles at.  Runs against any checkout
(`PYTHONPATH=<tree>`), so two versions can be compared in one session.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shards", type=int, default=40)
    ap.add_argument("--preset", default="paper-train")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--profile", type=int, default=0, help="cProfile the last N shards, print the top functions")
    a = ap.parse_args()

    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.execute import WorkerSettings, render_shard
    from msps_render.pipeline.plan import plan
    from msps_render.render.variant import activate, resolve_variant
    try:
        from msps_render.timing import StageTimer
        timer = StageTimer()
    except ImportError:  # a checkout from before the stage timer
        timer = None

    cfg = load_config(a.preset, [f"dataset.n_shards={a.shards}"])
    variant = resolve_variant("spectral" if cfg.scene.mode == "spectral" else "rgb")
    activate(variant, a.threads)
    with tempfile.TemporaryDirectory(prefix="msps-steady-") as out:
        (Path(out) / "shards").mkdir()
        ws = WorkerSettings(out_dir=out, variant=variant, threads=a.threads)
        prof = None
        for i, task in enumerate(plan(cfg)):
            if a.profile and i == a.shards - a.profile:
                import cProfile

                prof = cProfile.Profile()
                prof.enable()
            t0 = time.perf_counter()
            render_shard(task, ws, timer=timer) if timer is not None else render_shard(task, ws)
            dt = time.perf_counter() - t0
            if i % 5 == 4:
                line = f"shards {i - 4}-{i}: last shard {dt:.2f} s"
                if timer is not None:
                    fr = timer.frames[-40:]
                    means = {k: float(np.mean([f.get(k, 0.0) for f in fr])) for k in sorted({k for f in fr for k in f})}
                    line += "; " + " ".join(f"{k}={v:.3f}" for k, v in means.items() if v > 0.004)
                print(line, flush=True)
        if prof is not None:
            import pstats

            prof.disable()
            pstats.Stats(prof).sort_stats("cumulative").print_stats(40)


if __name__ == "__main__":
    main()
