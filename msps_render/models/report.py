"""What `msps eval` shows: the comparison table, the figures and the lines it prints.

Per-object numbers are the mean of the object's per-frame MAEs (each frame
weighs the same, whatever its pixel count); `per_object_detail` adds the frame
count and the pixel-pooled MAE.  Every figure overlays the methods of the run
(the Lambertian baseline in grey), names them and the dataset in its title,
keeps its legend outside the axes, and shows 95 % CIs as error bars with the
sample counts beside them.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from msps_render.atomic import save_figure, write_text

HIST_BIN_DEG = 2.0  # error histogram bins stored in metrics.json: [0, 2), [2, 4), ... [178, 180]
PER_OBJECT_NOTE = "per-object MAE = mean of the object's per-frame MAEs (each frame weighs the same)"
BASELINE = "lambertian"
DPI = 100


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


# ------------------------------------------------------------------ tables
def _cell(mae, ci) -> str:
    if mae is None:
        return "–"
    if ci is None or not np.all(np.isfinite(ci)):
        return f"{mae:.2f}"
    return f"{mae:.2f} [{ci[0]:.2f}, {ci[1]:.2f}]"


def _n(r: dict) -> str:
    f = f"{r['n_frames']} fr" if r.get("n_frames") is not None else ""
    return f + (f" / {r['n_patches']} p" if r.get("n_patches") is not None else "")


def table_markdown(report: dict) -> str:
    """table.md: the comparison table, every method a column, the lowest MAE of a row in bold."""
    t = report["table"]
    names = t["methods"]
    lines = [f"# MAE (deg) on `{report['dataset']}`: {', '.join(names)}", "",
             f"Data `{report['data']}`. Cells: MAE [{report['ci']}]. Rows per condition: patch pixels "
             "(pooled over every patch), whole frames (pixel-pooled), then each object (mean of its "
             "frames' MAEs); `all` pools every condition. n: frames (fr) / patches (p).", "",
             "| condition | rows | n | " + " | ".join(names) + " |",
             "|---|---|---|" + "---|" * len(names)]
    for r in t["rows"]:
        vals = {n: r["mae_deg"][n] for n in names if r["mae_deg"][n] is not None}
        best = min(vals, key=vals.get) if len(vals) > 1 else None
        cells = [(f"**{c}**" if n == best else c) for n in names
                 for c in [_cell(r["mae_deg"][n], r["ci95_deg"][n])]]
        what = r["object"] if r["what"] == "object" else f"*{r['what']}*"
        lines.append(f"| {r['condition'] or 'all'} | {what} | {_n(r)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_tables(report: dict, out: Path) -> list[Path]:
    """table.md always; per_object.csv when whole frames were evaluated (format 1 with one method)."""
    names = list(report["methods"])
    write_text(out / "table.md", table_markdown(report))
    files = [out / "table.md"]
    rows = []
    first = report["methods"][names[0]]["conditions"]
    for cond, c in first.items():
        for obj, d in c.get("per_object_detail", {}).items():
            vals = [report["methods"][n]["conditions"][cond]["per_object"][obj] for n in names]
            if len(names) == 1:
                rows.append(f"{cond},{obj},{vals[0]:.3f}")
            else:
                rows.append(f"{cond},{obj},{d['n_frames']}," + ",".join(f"{v:.3f}" for v in vals))
    if rows:
        head = "condition,object,mae_deg" if len(names) == 1 else "condition,object,n_frames," + ",".join(names)
        write_text(out / "per_object.csv", head + "\n" + "\n".join(rows) + "\n")
        files.append(out / "per_object.csv")
    return files


# ------------------------------------------------------------------ figures
def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def method_styles(names: list[str]) -> dict[str, dict]:
    """A colour per method, the same in every figure; the baseline grey and dashed."""
    out, k = {}, 0
    for n in names:
        if n == BASELINE:
            out[n] = {"color": "0.45", "ls": "--", "marker": "s", "hatch": "//"}
        else:
            out[n] = {"color": f"C{k % 10}", "ls": "-", "marker": "o", "hatch": None}
            k += 1
    return out


def _title(report: dict, what: str) -> str:
    names = list(report["methods"])
    vs = " vs ".join(names) if len(names) <= 4 else ", ".join(names)
    return f"{what} on {report['dataset']}\n{'methods' if len(names) > 1 else 'method'}: {vs}"


def _legend(ax, **kw) -> None:
    """Outside the axes, right of them: it never covers a bar or a line."""
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, frameon=False, fontsize=8, **kw)


def _yerr(maes, cis) -> np.ndarray:
    lo = [m - c[0] if c is not None and m is not None else 0.0 for m, c in zip(maes, cis)]
    hi = [c[1] - m if c is not None and m is not None else 0.0 for m, c in zip(maes, cis)]
    return np.clip(np.array([lo, hi], np.float64), 0, None)


def write_plots(report: dict, out: Path) -> list[Path]:
    """error_hist.png always; per_object.png with whole frames; robustness.png with several conditions."""
    files = [_error_hist(report, out)]
    if any(p.get("per_object") for p in report["pooled"].values()):
        files.append(_per_object(report, out))
    first = next(iter(report["methods"].values()))
    if len(first["conditions"]) > 1:
        files.append(_robustness(report, out))
    return files


def _error_hist(report: dict, out: Path) -> Path:
    """One line per method (every condition pooled); a single method: one line per condition."""
    plt = _plt()
    names = list(report["methods"])
    styles = method_styles(names)
    curves = []  # (label, hist, style)
    if len(names) > 1:
        for n in names:
            hs = [np.asarray(c["patches"].get("hist_deg", []), np.float64)
                  for c in report["methods"][n]["conditions"].values()]
            hs = [h for h in hs if h.size]
            if hs:
                curves.append((n, np.sum(hs, 0), styles[n]))
    else:
        conds = report["methods"][names[0]]["conditions"]
        for i, (cond, c) in enumerate(conds.items()):
            curves.append((cond if len(conds) > 1 else names[0], np.asarray(c["patches"].get("hist_deg", []),
                                                                             np.float64),
                           {"color": f"C{i % 10}", "ls": "-"}))
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    for label, h, st in curves:
        if not h.size or h.sum() == 0:
            continue
        edges = np.arange(len(h) + 1) * HIST_BIN_DEG
        ax[0].stairs(h / h.sum() * 100, edges, color=st["color"], ls=st["ls"], lw=1.4)
        ax[1].plot(edges[1:], np.cumsum(h) / h.sum() * 100, color=st["color"], ls=st["ls"], lw=1.4,
                   label=label if len(names) > 1 else f"{label} ({int(h.sum()):,} px)")
    ax[0].set(xlabel="angular error (deg)", ylabel="% of object pixels", xlim=(0, 90), title="distribution")
    px = f" ({int(curves[0][1].sum()):,} object pixels each)" if len(names) > 1 and curves else ""
    ax[1].set(xlabel="angular error (deg)", ylabel="% of pixels below", xlim=(0, 90), ylim=(0, 100),
              title="cumulative" + px)
    for a in ax:
        a.grid(alpha=0.3)
        a.title.set_fontsize(9)
    single = len(names) == 1 and len(curves) == 1
    _legend(ax[1], title=None if single else "method" if len(names) > 1 else "condition", title_fontsize=8)
    fig.suptitle(_title(report, "Angular error of patch pixels"), fontsize=10)
    fig.tight_layout()
    save_figure(fig, out / "error_hist.png", dpi=DPI)
    plt.close(fig)
    return out / "error_hist.png"


def _object_groups(report: dict) -> tuple[list[str], list[dict], str]:
    """(group labels, per method {label: cell}, scope): objects over every condition; a one-object
    sweep shows its object per condition too, so the figure still compares something."""
    names = list(report["methods"])
    pooled = report["pooled"]
    objs = sorted({o for n in names for o in pooled[n].get("per_object", {})})
    conds = report["methods"][names[0]]["conditions"]
    if len(objs) == 1 and len(conds) > 1:
        o = objs[0]
        labels, cells = [], {n: {} for n in names}
        for c, v in conds.items():
            if o in v.get("per_object_detail", {}):
                labels.append(f"{o}\n{c}")
                for n in names:
                    cells[n][labels[-1]] = report["methods"][n]["conditions"][c]["per_object_detail"][o]
        labels.append(f"{o}\nall")
        for n in names:
            cells[n][labels[-1]] = pooled[n]["per_object"][o]
        return labels, [cells[n] for n in names], "per condition and pooled"
    scope = f"all {len(conds)} conditions" if len(conds) > 1 else "whole frames"
    return objs, [pooled[n]["per_object"] for n in names], scope


def _per_object(report: dict, out: Path) -> Path:
    """Grouped bars: one group per object, one bar per method (every condition's frames together)."""
    plt = _plt()
    names = list(report["methods"])
    styles = method_styles(names)
    groups, cells, scope = _object_groups(report)
    M, G = len(names), len(groups)
    w = min(0.8 / M, 0.28)
    fig_w = min(max(5.0, 1.2 + G * (w * M + 0.35) * 1.6), 18.0) + 1.8  # + legend
    fig, ax = plt.subplots(figsize=(fig_w, 4.0))
    x = np.arange(G)
    top = 0.0
    for j, n in enumerate(names):
        d = cells[j]
        maes = [d[o]["mae_deg"] if o in d else np.nan for o in groups]
        cis = [d[o].get("ci95_deg") if o in d else None for o in groups]
        xs = x + (j - (M - 1) / 2) * w
        st = styles[n]
        ax.bar(xs, maes, w * 0.92, yerr=_yerr(maes, cis), capsize=3, color=st["color"], hatch=st["hatch"],
               edgecolor="white" if st["hatch"] else None, error_kw={"lw": 1, "ecolor": "0.15"}, label=n)
        top = max(top, np.nanmax([c[1] if c is not None else m for m, c in zip(maes, cis)] + [0.0]))
        if G * M <= 30:
            for xi, m, c in zip(xs, maes, cis):
                if np.isfinite(m):
                    ax.text(xi, (c[1] if c is not None else m) + 0.01 * top + 0.05, f"{m:.1f}", ha="center",
                            va="bottom", fontsize=7)
    n_fr = [cells[0].get(o, {}).get("n_frames", 0) for o in groups]
    many = G > 8
    ax.set_xticks(x, [f"{o}\nn={k} fr" for o, k in zip(groups, n_fr)], fontsize=8,
                  rotation=30 if many else 0, ha="right" if many else "center")
    pad = 0.1 if G == 1 else 0.0
    ax.set_xlim(-0.5 - pad, G - 0.5 + pad)
    ax.set_ylim(0, top * 1.15 + 0.5)
    ax.set_ylabel("MAE (deg), mean of frame MAEs")
    ax.grid(axis="y", alpha=0.3)
    ax.set_axisbelow(True)
    ax.set_title(_title(report, f"Per-object MAE ({scope})"), fontsize=10)
    _legend(ax)
    fig.text(0.01, 0.01, "error bars: 95 % CI, bootstrap over the object's frames; n: frames", fontsize=7,
             color="0.3")
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    save_figure(fig, out / "per_object.png", dpi=DPI)
    plt.close(fig)
    return out / "per_object.png"


def _robustness(report: dict, out: Path) -> Path:
    """MAE (with 95 % CI) and alpha per condition, one line per method; n frames / patches on the axis."""
    plt = _plt()
    names = list(report["methods"])
    styles = method_styles(names)
    first = report["methods"][names[0]]
    conds = list(first["conditions"])
    rb = first.get("robustness") or {}
    values = rb.get("values", {})
    numeric = all(isinstance(values.get(c), (int, float)) and not isinstance(values.get(c), bool) for c in conds)
    xs = np.array([float(values[c]) for c in conds]) if numeric else np.arange(len(conds), dtype=float)
    label = (rb.get("key") or "condition").split(".")[-1]
    ticks = [f"{values[c]:g}" if numeric else (c or "all") for c in conds]
    key_lines = []
    if max(len(t) for t in ticks) > 14:  # e.g. a swept matrix: short tick names, the values in a key below
        key_lines = [f"c{i}: {t}" for i, t in enumerate(ticks)]
        ticks = [f"c{i}" for i in range(len(ticks))]
    ref_label = ticks[conds.index(rb["reference"])] if rb.get("reference") in conds else rb.get("reference")
    counts = [first["conditions"][c]["patches"] for c in conds]
    ticks = [f"{t}\n{p.get('n_frames', '?')} fr\n{p.get('n_patches', '?')} p" for t, p in zip(ticks, counts)]
    span = float(np.ptp(xs)) or 1.0
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.0))
    for j, n in enumerate(names):
        cs = report["methods"][n]["conditions"]
        maes = [cs[c]["patches"].get("mae_deg") for c in conds]
        cis = [cs[c]["patches"].get("ci95_deg") for c in conds]
        st = styles[n]
        off = (j - (len(names) - 1) / 2) * 0.012 * span  # a little apart, so overlapping bars stay visible
        ax[0].errorbar(xs + off, [np.nan if m is None else m for m in maes], yerr=_yerr(maes, cis),
                       color=st["color"], ls=st["ls"], marker=st["marker"], ms=5, capsize=3, lw=1.5, label=n)
        al = report["methods"][n].get("robustness", {}).get("alpha", {})
        ax[1].plot(xs, [al.get(c, np.nan) for c in conds], color=st["color"], ls=st["ls"], marker=st["marker"],
                   ms=5, lw=1.5, label=n)
    ref = rb.get("reference")
    for a in ax:
        a.set_xticks(xs, ticks, fontsize=8)
        a.grid(alpha=0.3)
        if ref in conds:
            a.axvline(xs[conds.index(ref)], color="0.6", lw=0.8, ls=":")
    xlabel = f"{label}   (below each value: n frames, n patches)"
    ax[0].set(xlabel=xlabel, ylabel="MAE of patch pixels (deg)", title="MAE, 95 % CI (bootstrap over frames)")
    ax[0].set_ylim(bottom=0)
    ax[0].title.set_fontsize(9)
    ax[1].set(xlabel=xlabel, ylabel="fluctuation ratio α", title=f"α = |χ − χ′| / χ vs reference {ref_label}")
    ax[1].set_ylim(bottom=0)
    ax[1].title.set_fontsize(9)
    _legend(ax[1])
    fig.suptitle(_title(report, "Robustness"), fontsize=10)
    fig.tight_layout()
    if key_lines:
        fig.subplots_adjust(bottom=0.22 + 0.05 * len(key_lines))
        fig.text(0.01, 0.01, "\n".join(key_lines), fontsize=7, family="monospace", va="bottom")
    save_figure(fig, out / "robustness.png", dpi=DPI)
    plt.close(fig)
    return out / "robustness.png"


# ------------------------------------------------------------------ printed
def summary_lines(report: dict) -> list[str]:
    """The lines `msps eval` prints: one method as before (statistics and per-object table); several:
    the comparison table."""
    if len(report["methods"]) > 1:
        return [_what_ran(report)] + _compare_lines(report)
    lines = [_what_ran(report)]
    for cond, v in report["conditions"].items():
        p = v["patches"]
        name = cond or "all"
        if not p.get("n_pixels"):
            lines.append(f"{name}: no patches")
            continue
        lines.append(f"{name}: MAE {p['mae_deg']:.2f} deg, median {p['median_deg']:.2f}, <10deg "
                     f"{p['pct_under_10']:.1f}%, SSIM {p['ssim']:.4f} ({p['n_patches']} patches, "
                     f"{p.get('n_frames', '?')} frames, 95% CI {p['ci95_deg'][0]:.2f}-{p['ci95_deg'][1]:.2f})")
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


def _what_ran(report: dict) -> str:
    """The summary's first line: which methods with which steps, on which data (issue 44)."""
    parts = []
    for name, m in report["methods"].items():
        ck = m.get("checkpoint")
        parts.append(f"{name} = {m.get('kind', 'method')}{f' ({ck})' if ck else ''}, steps {m.get('steps', 'none')}")
    return f"{report.get('dataset', '')} ({report.get('data', '')}): " + "; ".join(parts)


def _compare_lines(report: dict) -> list[str]:
    t = report["table"]
    names = t["methods"]
    head = ["condition", "rows", "n"] + names
    body = [[r["condition"] or "all", r["object"] if r["what"] == "object" else r["what"], _n(r)] +
            [f"{r['mae_deg'][n]:.2f}" if r["mae_deg"][n] is not None else "-" for n in names] for r in t["rows"]]
    widths = [max(len(str(x)) for x in col) for col in zip(head, *body)]
    fmt = lambda cells: "  ".join(f"{c:<{w}}" if i < 3 else f"{c:>{w}}" for i, (c, w) in enumerate(zip(cells, widths)))
    lines = [f"MAE (deg) on {report['dataset']}, every method on the same patches and frames:", fmt(head)]
    lines += [fmt(b) for b in body]
    has_obj = any(r["what"] == "object" for r in t["rows"])
    lines.append((PER_OBJECT_NOTE + "; " if has_obj else "") + "95 % CIs in table.md and metrics.json")
    for n in names:
        rb = report["methods"][n].get("robustness")
        if rb:
            lines.append(f"robustness {n} (reference {rb['reference']}): " + ", ".join(
                f"{c}: alpha {a:.3f}" for c, a in rb["alpha"].items()))
    return lines
