"""How often a batched launch brings a render kernel this process has not run before (issue 45, a probe,
not product).

Renders PRESET's first N shards at `dataset.batch_frames = 8` through the pipeline's own `render_shard`
(one worker), with drjit's kernel history, and prints one character per launch: `N` when the launch's
render kernel (its largest) is new to the process (compiled, or loaded from drjit's disk cache), `.`
when it ran before; then how many of the launches after the first 8 were new.  Use a seed no run has
used (`dataset.seed`), or the disk cache hides what new content costs a user.

    MSPS_THREADS=1 PYTHONPATH=. .venv/bin/python experiments/batch_kernel_count.py train-colour 24 \
        --set dataset.seed=9917
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import drjit as dr

import msps_render.render.batch as batch
from msps_render.pipeline.config import load_config
from msps_render.pipeline.execute import WorkerSettings, render_shard
from msps_render.pipeline.plan import plan
from msps_render.render.pool import ScenePool
from msps_render.render.variant import activate


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("preset")
    ap.add_argument("shards", type=int)
    ap.add_argument("--set", action="append", default=[])
    a = ap.parse_args()
    activate("llvm_ad_rgb", 1)
    cfg = load_config(a.preset, [f"dataset.n_shards={a.shards}", "dataset.batch_frames=8", *a.set])
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    hashes = []
    render_batch = batch.render_batch

    def counted(specs, **kw):
        dr.kernel_history()
        out = render_batch(specs, **kw)
        hashes.append(max(dr.kernel_history(), key=lambda k: k.get("operation_count") or 0)["hash"])
        return out

    batch.render_batch = counted  # `pipeline.execute` imports it from the module at each launch
    scenes = ScenePool()
    with tempfile.TemporaryDirectory() as out:
        (Path(out) / "shards").mkdir()
        ws = WorkerSettings(out_dir=out, variant="llvm_ad_rgb", threads=1)
        for task in plan(cfg):
            render_shard(task, ws, scenes=scenes)
    seen, marks = set(), []
    for h in hashes:
        marks.append("." if h in seen else "N")
        seen.add(h)
    print("".join(marks), f"new after the first 8: {marks[8:].count('N')} of {len(marks[8:])}")


if __name__ == "__main__":
    main()
