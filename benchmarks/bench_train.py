"""Training throughput of the model presets and their FLOP rate vs this CPU's fp32 GEMM rate.

Usage: .venv/bin/python benchmarks/bench_train.py [--threads 2] [--steps 20]
       python3 benchmarks/bench_train.py --device cuda --batch 24,256 --presets cpu,gpu,paper   # on a GPU

For each preset: median time of a full training step (forward, paper losses,
backward, Adam) on random 40x40 batches of 24 -> patches/s; model FLOPs per
patch (forward conv multiply-adds x2, counted by hooks) x 3 (forward +
backward ~ 3x forward) x patches/s -> achieved FLOP/s; divided by the
measured fp32 GEMM rate (torch.matmul 2048x2048, same threads).  With `--device cuda` the step runs as
`msps train` runs it there (`models.accel`: bf16 autocast, channels-last) on batches already on the device,
so the number is the model's ceiling without the loader; the first steps (cuDNN autotuning) are reported
apart, and each step waits for the device (`torch.cuda.synchronize`) before it is timed.
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from msps_render.models.losses import total_loss
from msps_render.models.net import DualCueNet, count_parameters, flops_per_patch
from msps_render.models.presets import load_model_config


def gemm_rate(n: int = 2048, reps: int = 10) -> float:
    a, b = torch.rand(n, n), torch.rand(n, n)
    a @ b
    ts = []
    for _ in range(reps):
        t = time.perf_counter()
        a @ b
        ts.append(time.perf_counter() - t)
    return 2 * n ** 3 / statistics.median(ts)


def step_rate(preset: str, steps: int, batch: int = 24, accel=None) -> tuple[float, int, float, float]:
    """(patches/s, parameters, forward FLOPs per patch, seconds of the first two steps)."""
    from msps_render.models.accel import CPU

    accel = accel or CPU
    cfg = load_model_config(preset)
    model = DualCueNet(cfg.net_config())
    fl = flops_per_patch(model)
    model = accel.model(model)
    opt = torch.optim.Adam(model.parameters(), 1e-3)
    x = accel.tensor(torch.rand(batch, 3, 40, 40))
    n = accel.tensor(torch.nn.functional.normalize(torch.randn(batch, 3, 40, 40), dim=1))
    m = accel.tensor(torch.ones(batch, 1, 40, 40))
    sync = torch.cuda.synchronize if accel.is_cuda else (lambda: None)
    ts = []
    for i in range(steps + 2):
        t = time.perf_counter()
        with accel.autocast():
            f, c = model(x, m)
        loss, _ = total_loss(f.float(), None if c is None else c.float(), n, m, cfg.net.mode)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sync()
        ts.append(time.perf_counter() - t)
    return batch / statistics.median(ts[2:]), count_parameters(model), fl, sum(ts[:2])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--device", default="cpu", help="cpu, cuda or auto (models.accel)")
    ap.add_argument("--batch", default="24", help="comma-separated batch sizes")
    ap.add_argument("--presets", default="cpu,paper")
    a = ap.parse_args()
    from msps_render.models.accel import resolve_accel

    torch.set_num_threads(a.threads)
    accel = resolve_accel(a.device)
    if not accel.is_cuda:
        peak = gemm_rate()
        print(f"fp32 GEMM (2048^3, {a.threads} threads): {peak / 1e9:.1f} GFLOP/s")
    print(f"device: {accel.describe()}")
    print("| preset | batch | parameters | GFLOP/patch (fwd) | train patches/s | achieved GFLOP/s (3x fwd) | "
          "first 2 steps (s) |")
    print("|---|---|---|---|---|---|---|")
    for preset in a.presets.split(","):
        for batch in (int(b) for b in a.batch.split(",")):
            steps = a.steps if preset == "cpu" or accel.is_cuda else max(3, a.steps // 5)
            rate, params, fl, first = step_rate(preset, steps, batch, accel)
            print(f"| {preset} | {batch} | {params:,} | {fl / 1e9:.3f} | {rate:.1f} | {3 * fl * rate / 1e9:.1f} | "
                  f"{first:.2f} |", flush=True)


if __name__ == "__main__":
    main()
