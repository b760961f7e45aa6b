"""Markdown table of MAE and fluctuation ratio alpha per condition from `msps eval` outputs.

Used for docs/history.md ("Robustness: darkroom vs robust training"):

    python benchmarks/robust_table.py dual=runs/eval-unseen-robust-env-dual \
        dual-robust=runs/eval-unseen-robust-env-dual-robust lambertian=runs/eval-unseen-robust-env-lambertian
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def table(runs: dict[str, dict]) -> str:
    names = list(runs)
    conds = list(next(iter(runs.values()))["robustness"]["mae_deg"])
    head = "| condition | " + " | ".join(f"{n} MAE | {n} α" for n in names) + " |"
    rows = [head, "|" + "---|" * (1 + 2 * len(names))]
    for c in conds:
        cells = []
        for n in names:
            r = runs[n]["robustness"]
            cells += [f"{r['mae_deg'][c]:.2f}", f"{r['alpha'][c]:.2f}"]
        rows.append(f"| {c} | " + " | ".join(cells) + " |")
    mean = []
    for n in names:
        r = runs[n]["robustness"]
        mean += [f"{sum(r['mae_deg'].values()) / len(conds):.2f}", f"{sum(r['alpha'].values()) / len(conds):.2f}"]
    rows.append("| **mean** | " + " | ".join(f"**{v}**" for v in mean) + " |")
    return "\n".join(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="NAME=eval output directory (holds metrics.json)")
    a = ap.parse_args()
    runs = {}
    for spec in a.runs:
        name, _, d = spec.partition("=")
        runs[name] = json.loads((Path(d) / "metrics.json").read_text())
    print(table(runs))


if __name__ == "__main__":
    main()
