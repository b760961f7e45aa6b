"""Training throughput of the model presets and their FLOP rate vs this CPU's fp32 GEMM rate.

Usage: .venv/bin/python benchmarks/bench_train.py [--threads 2] [--steps 20]

For each preset: median time of a full training step (forward, paper losses,
backward, Adam) on random 40x40 batches of 24 -> patches/s; model FLOPs per
patch (forward conv multiply-adds x2, counted by hooks) x 3 (forward +
backward ~ 3x forward) x patches/s -> achieved FLOP/s; divided by the
measured fp32 GEMM rate (torch.matmul 2048x2048, same threads).
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


def step_rate(preset: str, steps: int, batch: int = 24) -> tuple[float, int, float]:
    cfg = load_model_config(preset)
    model = DualCueNet(cfg.net_config())
    opt = torch.optim.Adam(model.parameters(), 1e-3)
    x = torch.rand(batch, 3, 40, 40)
    n = torch.nn.functional.normalize(torch.randn(batch, 3, 40, 40), dim=1)
    m = torch.ones(batch, 1, 40, 40)
    ts = []
    for i in range(steps + 2):
        t = time.perf_counter()
        f, c = model(x, m)
        loss, _ = total_loss(f, c, n, m, cfg.net.mode)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if i >= 2:
            ts.append(time.perf_counter() - t)
    return batch / statistics.median(ts), count_parameters(model), flops_per_patch(model)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--steps", type=int, default=20)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    peak = gemm_rate()
    print(f"fp32 GEMM (2048^3, {a.threads} threads): {peak / 1e9:.1f} GFLOP/s")
    print("| preset | parameters | GFLOP/patch (fwd) | train patches/s | achieved GFLOP/s (3x fwd) | share of GEMM rate |")
    print("|---|---|---|---|---|---|")
    for preset, steps in (("cpu", a.steps), ("paper", max(3, a.steps // 5))):
        rate, params, fl = step_rate(preset, steps)
        achieved = 3 * fl * rate
        print(f"| {preset} | {params:,} | {fl / 1e9:.3f} | {rate:.1f} | {achieved / 1e9:.1f} | {achieved / peak:.0%} |")


if __name__ == "__main__":
    main()
