"""What `msps eval` shows: the plots it promises and the per-object table it prints.

Per-object numbers are the mean of the object's per-frame MAEs (each frame
weighs the same, whatever its pixel count); `per_object_detail` adds the frame
count and the pixel-pooled MAE.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

HIST_BIN_DEG = 2.0  # error histogram bins stored in metrics.json: [0, 2), [2, 4), ... [178, 180]
PER_OBJECT_NOTE = "per-object MAE = mean of the object's per-frame MAEs (each frame weighs the same)"


def error_histogram(err: np.ndarray) -> list[int]:
    return np.histogram(np.asarray(err, np.float64), bins=int(180 / HIST_BIN_DEG), range=(0.0, 180.0))[0].tolist()


def per_object_detail(rows: list[tuple[str, float, int, float]]) -> dict:
    """rows: (object, frame MAE, frame pixels, frame error sum) -> {object: {mae_deg, n_frames, pixel_mae_deg}}."""
    out: dict = {}
    for obj in sorted({r[0] for r in rows}):
        mine = [r for r in rows if r[0] == obj]
        out[obj] = {"mae_deg": float(np.mean([r[1] for r in mine])), "n_frames": len(mine),
                    "pixel_mae_deg": float(sum(r[3] for r in mine) / max(sum(r[2] for r in mine), 1))}
    return out


def write_plots(report: dict, out: Path) -> list[Path]:
    """error_hist.png always; per_object.png when whole frames were evaluated. Returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    conds = report["conditions"]
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
    for i, (cond, r) in enumerate(conds.items()):
        h = np.asarray(r["patches"].get("hist_deg", []), np.float64)
        if not h.size or h.sum() == 0:
            continue
        edges = np.arange(len(h) + 1) * HIST_BIN_DEG
        label = cond or "all"
        ax[0].stairs(h / h.sum() * 100, edges, label=label, color=f"C{i % 10}")
        ax[1].plot(edges[1:], np.cumsum(h) / h.sum() * 100, label=label, color=f"C{i % 10}")
    ax[0].set(xlabel="angular error (deg)", ylabel="% of object pixels", xlim=(0, 90),
              title=f"{report['method']}: patch pixels")
    ax[1].set(xlabel="angular error (deg)", ylabel="% of pixels below", xlim=(0, 90), ylim=(0, 100))
    if len(conds) > 1:
        ax[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "error_hist.png", dpi=90)
    plt.close(fig)
    files.append(out / "error_hist.png")
    with_obj = {c: r["per_object"] for c, r in conds.items() if r.get("per_object")}
    if with_obj:
        objs = sorted({o for v in with_obj.values() for o in v})
        fig, ax = plt.subplots(figsize=(max(4.0, 0.6 * len(objs) * len(with_obj) + 2), 3.4))
        w = 0.8 / len(with_obj)
        for i, (cond, v) in enumerate(with_obj.items()):
            ax.bar(np.arange(len(objs)) + i * w, [v.get(o, np.nan) for o in objs], w, label=cond or "all")
        ax.set_xticks(np.arange(len(objs)) + 0.4 - w / 2, objs, rotation=30, ha="right", fontsize=8)
        ax.set(ylabel="MAE (deg), mean of frames", title=f"{report['method']}: per object")
        if len(with_obj) > 1:
            ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "per_object.png", dpi=90)
        plt.close(fig)
        files.append(out / "per_object.png")
    return files


def summary_lines(report: dict) -> list[str]:
    """The lines `msps eval` prints: patch statistics, whole-frame statistics and the per-object table."""
    lines = []
    for cond, v in report["conditions"].items():
        p = v["patches"]
        name = cond or "all"
        if not p.get("n_pixels"):
            lines.append(f"{name}: no patches")
            continue
        lines.append(f"{name}: MAE {p['mae_deg']:.2f} deg, median {p['median_deg']:.2f}, <10deg "
                     f"{p['pct_under_10']:.1f}%, SSIM {p['ssim']:.4f} ({p['n_patches']} patches)")
        f = v.get("frames")
        if f and f.get("n_pixels"):
            n = sum(d["n_frames"] for d in v.get("per_object_detail", {}).values())
            lines.append(f"  whole frames: MAE {f['mae_deg']:.2f} deg, median {f['median_deg']:.2f} ({n} frames)")
        det = v.get("per_object_detail")
        if det:
            width = max(len(o) for o in det)
            lines.append(f"  {'object':<{width}}  MAE deg  frames")
            for o, d in det.items():
                lines.append(f"  {o:<{width}}  {d['mae_deg']:7.2f}  {d['n_frames']:6d}")
    if any(v.get("per_object_detail") for v in report["conditions"].values()):
        lines.append(PER_OBJECT_NOTE)
    rb = report.get("robustness")
    if rb:
        lines.append(f"robustness (reference {rb['reference']}): " + ", ".join(
            f"{c}: {m:.2f} deg, alpha {rb['alpha'][c]:.3f}" for c, m in rb["mae_deg"].items()))
    return lines
