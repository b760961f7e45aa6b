"""Weight-space interpolation of two checkpoints of one network (WiSE-FT, Wortsman et al. 2022).

A fine-tune that starts from a checkpoint stays in its basin, so the straight line between
the two often holds the best of both: here, v0.4's grey prior and the colour fine-tune's
chroma. Writes a checkpoint whose floating-point weights are ``(1 - alpha) * A + alpha * B``
(integer buffers such as BatchNorm counters are taken from B) and whose metadata records
both parents and alpha; it loads wherever a checkpoint does.

    python experiments/interpolate_checkpoints.py models/dualcue-cpu-v0.4.pt runs/colour/last.pt \
        --alpha 0.5 --out runs/soup-0.5.pt
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch


def interpolate(a: dict, b: dict, alpha: float) -> dict:
    """The mixed state dict; the two must hold the same tensors (same architecture)."""
    if a.keys() != b.keys():
        raise ValueError(f"the checkpoints hold different weights: {sorted(a.keys() ^ b.keys())[:5]}")
    out = {}
    for k, vb in b.items():
        va = a[k]
        if va.shape != vb.shape:
            raise ValueError(f"{k}: shapes differ ({tuple(va.shape)} vs {tuple(vb.shape)})")
        out[k] = torch.lerp(va.float(), vb.float(), alpha).to(vb.dtype) if vb.is_floating_point() else vb.clone()
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a", type=Path, help="checkpoint at alpha = 0 (e.g. the warm start)")
    ap.add_argument("b", type=Path, help="checkpoint at alpha = 1 (e.g. the fine-tune)")
    ap.add_argument("--alpha", type=float, required=True)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    if not 0.0 <= args.alpha <= 1.0:
        ap.error(f"--alpha must lie in [0, 1], got {args.alpha}")
    ca = torch.load(args.a, map_location="cpu", weights_only=False)
    cb = torch.load(args.b, map_location="cpu", weights_only=False)
    if ca.get("format") != cb.get("format") or ca["config"]["net"] != cb["config"]["net"]:
        raise SystemExit(f"{args.a} and {args.b}: different network configs, cannot interpolate")
    out = {k: v for k, v in cb.items() if k not in ("optimizer", "torch_rng")}
    out["model"] = interpolate(ca["model"], cb["model"], args.alpha)
    out["val_mae_deg"] = None
    out["state"] = dict(cb.get("state", {}), interpolated={"a": str(args.a), "b": str(args.b), "alpha": args.alpha})
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_name(args.out.name + ".tmp")
    torch.save(out, tmp)
    tmp.replace(args.out)
    print(f"{args.out}: (1 - {args.alpha}) * {args.a} + {args.alpha} * {args.b}")


if __name__ == "__main__":
    main()
