"""The loader on a quiet machine and with the other core busy (issue 45: 23.3k patches/s quiet, 3.3k
while the other core was busy).

Usage: python benchmarks/bench_loader_load.py --data DIR [--rounds 3] [--workers 0 2] [--batch 64]

Per round, each mode reads one epoch with `make_loader` (workers started before the clock), first on
the quiet machine, then with a busy-loop process on the other core; "old cast" is the batch cast as it
was before (one `copy_` of the whole batch, on torch's intra-op threads), "cast in pieces" the
shipped `data._float32`.  Prints medians of patches/s and the main process's CPU seconds per epoch.
"""
from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

import numpy as np
import torch

from msps_render import data
from msps_render.data import PatchDataset, make_loader


def old_cast(rows: np.ndarray, out: np.ndarray) -> None:
    torch.from_numpy(out).copy_(torch.from_numpy(rows))


def epoch(ds, workers: int, batch: int) -> tuple[float, float]:
    it = iter(make_loader(ds, batch, num_workers=workers, seed=0))
    next(it)
    n, t, c = 0, time.perf_counter(), time.process_time()
    for b in it:
        n += len(b["image"])
    return n / (time.perf_counter() - t), time.process_time() - c


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--workers", type=int, nargs="+", default=[0, 2])
    ap.add_argument("--batch", type=int, default=64)
    a = ap.parse_args()
    ds = PatchDataset(a.data)
    shipped = data._float32
    rows = {}
    for r in range(a.rounds):
        for load in ("quiet", "other core busy"):
            spin = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if load != "quiet" else None
            try:
                time.sleep(0.5 if spin else 0)
                for cast_name, cast in (("old cast", old_cast), ("cast in pieces", shipped)):
                    data._float32 = cast
                    for w in a.workers:
                        rows.setdefault((load, cast_name, w), []).append(epoch(ds, w, a.batch))
            finally:
                data._float32 = shipped
                if spin:
                    spin.kill()
                    spin.wait()
        print(f"round {r + 1} done", flush=True)
    print(f"\n{a.data}: {len(ds):,} patches, batch {a.batch}, torch threads {torch.get_num_threads()}, "
          f"{a.rounds} rounds (medians)\n")
    print("| machine | batch cast | workers | patches/s | main CPU s per epoch |\n|---|---|---|---|---|")
    for (load, cast_name, w), v in rows.items():
        print(f"| {load} | {cast_name} | {w} | {statistics.median(x[0] for x in v):,.0f} | "
              f"{statistics.median(x[1] for x in v):.2f} |")


if __name__ == "__main__":
    main()
