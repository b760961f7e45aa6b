"""The dataset card: what a dataset holds and covers, as one PNG and one JSON (`DIR/card.png`, `DIR/card.json`).

Written by `msps render` when a dataset is complete and by `msps card DIR` for any
dataset, from the shards alone (their `frames/*` records and scene JSON, a sample
of `patches/mask`) and the manifest, so a card always describes the files beside
it.  Per-frame histograms total the number of frames; per-part tables (materials,
textures, albedo) total the material parts.  Both files are written atomically
and hold no paths or times: the same dataset gives the same card bytes.
"""
from __future__ import annotations

import json
import math
from collections import Counter
from pathlib import Path

import numpy as np

from msps_render.atomic import atomic_write
from msps_render.dataset import schema as K
from msps_render.dataset.manifest import Manifest, read_manifest
from msps_render.dataset.reader import has_per_light, has_whole_frames, open_shard, shard_errors
from msps_render.errors import InputError, not_a_dataset

CARD_PNG = "card.png"
CARD_JSON = "card.json"
CARD_FORMAT = "msps-card-1"
MAX_PATCHES = 20000  # patch masks read for the coverage histogram (spread evenly over the shards)
ALBEDO_KEYS = ("reflectance", "diffuse_reflectance", "base_color")  # analytic families' albedo parameter
ALBEDO_SAMPLES = 400  # albedo colours kept in the JSON (and drawn as swatches)
TOP = 15  # categories drawn per bar chart


# ------------------------------------------------------------------ numbers
def histogram(values, bins: int = 20, lo: float | None = None, hi: float | None = None) -> dict:
    """{'edges', 'counts', 'total', 'nan'}: every value is counted (NaN apart), so total = len(values)."""
    v = np.asarray(values, np.float64).ravel()
    ok = v[np.isfinite(v)]
    lo = float(ok.min()) if lo is None and ok.size else (0.0 if lo is None else lo)
    hi = float(ok.max()) if hi is None and ok.size else (1.0 if hi is None else hi)
    if ok.size:
        lo, hi = min(lo, float(ok.min())), max(hi, float(ok.max()))
    if hi - lo < 1e-9:  # one value: one bin around it
        lo, hi, bins = lo - 0.5, hi + 0.5, 1
    counts, edges = np.histogram(ok, bins=bins, range=(lo, hi))
    return {"edges": [round(float(e), 6) for e in edges], "counts": counts.astype(int).tolist(),
            "total": int(v.size), "nan": int(v.size - ok.size),
            "min": round(float(ok.min()), 6) if ok.size else None, "max": round(float(ok.max()), 6) if ok.size else None}


def categories(items) -> dict[str, int]:
    """{name: count}, most frequent first (ties by name), so the JSON is the same for the same data."""
    c = Counter(items)
    return dict(sorted(c.items(), key=lambda kv: (-kv[1], str(kv[0]))))


def tilt_deg(d: np.ndarray) -> np.ndarray:
    """Tilt of light directions (..., 3) in [-5, 355): angle from +x toward +y in the image plane
    (10-degree bins centred on 0, 10, ..., so the usual 0/120/240 sit mid-bin, not on an edge)."""
    return np.mod(np.degrees(np.arctan2(d[..., 1], d[..., 0])) + 5.0, 360.0) - 5.0


def material_family(name: str, kind: str) -> str:
    """'nbrdf:gold-paint' -> 'nbrdf', 'merl:...' -> 'merl'; analytic materials: their kind."""
    return name.split(":", 1)[0] if ":" in name else (kind or name)


def _hue_sat_lum(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """HSV hue (deg), saturation, and Rec. 709 luminance of linear RGB rows."""
    mx, mn = rgb.max(1), rgb.min(1)
    c = mx - mn
    r, g, b = rgb.T
    safe = np.where(c > 0, c, 1.0)
    h = np.where(mx == r, ((g - b) / safe) % 6, np.where(mx == g, (b - r) / safe + 2, (r - g) / safe + 4))
    hue = np.where(c > 0, h * 60.0, 0.0)
    sat = np.where(mx > 0, c / np.where(mx > 0, mx, 1.0), 0.0)
    return hue, sat, rgb @ np.array([0.2126, 0.7152, 0.0722])


class _Acc:
    """What the card needs from the shards, gathered shard by shard."""

    def __init__(self):
        self.slant, self.env, self.cond, self.obj, self.shape_kind = [], [], [], [], []
        self.dirs, self.xtalk, self.spp, self.n_parts = [], [], [], []
        self.mat_names, self.mat_fams, self.textures = [], [], []
        self.albedo, self.tex_colors = [], []
        self.coverage, self.patches_per_frame = [], []
        self.n_patches_total = 0
        self.versions: dict[str, set] = {"toolkit_version": set(), "mitsuba_version": set(), "variant": set()}
        self.whole_frames, self.per_light = [], []

    def add_shard(self, path: Path, quota: int, rng: np.random.Generator) -> None:
        with shard_errors(path), open_shard(path) as h:
            for k in self.versions:
                if k in h.attrs:
                    self.versions[k].add(str(h.attrs[k]))
            self.whole_frames.append(has_whole_frames(h))
            self.per_light.append(has_per_light(h))
            self.slant += h[K.FRAME_SLANT_DEG][()].tolist()
            self.env += h[K.FRAME_ENV_RATIO][()].tolist()
            self.dirs.append(h[K.FRAME_LIGHT_DIRS][()])
            self.xtalk.append(h[K.FRAME_CROSSTALK][()])
            self.spp += h[K.FRAME_SPP][()].tolist()
            self.cond += h[K.FRAME_CONDITION].asstr()[()].tolist()
            self.obj += h[K.FRAME_OBJECT].asstr()[()].tolist()
            names = h[K.FRAME_MATERIALS].asstr()[()].tolist()
            scenes = h[K.FRAME_SCENE_JSON].asstr()[()].tolist()
            fidx = h[K.PATCH_FRAME_INDEX][()]
            self.patches_per_frame += np.bincount(fidx, minlength=len(names)).tolist() if len(names) else []
            n = len(fidx)
            self.n_patches_total += n
            if n:
                idx = np.arange(n) if n <= quota else np.sort(rng.choice(n, size=quota, replace=False))
                # the whole array, then the rows: h5py's fancy read of a compressed dataset was 33x slower
                m = h[K.PATCH_MASK][()][idx]
                self.coverage += m.reshape(len(m), -1).mean(1).tolist()
        for joined, sj in zip(names, scenes):
            self._add_scene(joined, sj)

    def _add_scene(self, joined: str, scene_json: str) -> None:
        try:
            scene = json.loads(scene_json)
        except ValueError:
            scene = {}
        self.shape_kind.append(str((scene.get("shape") or {}).get("kind", "?")))
        mats = scene.get("materials") or []
        names = [s for s in joined.split(";") if s] or [str(m.get("name", "?")) for m in mats]
        self.n_parts.append(len(names))
        for i, name in enumerate(names):
            m = mats[i] if i < len(mats) else {}
            self.mat_names.append(name)
            self.mat_fams.append(material_family(name, str(m.get("kind", ""))))
            tex = m.get("texture")
            self.textures.append(str(tex.get("kind", "?")) if isinstance(tex, dict) else "none")
            if isinstance(tex, dict):
                self.tex_colors += [c for c in tex.get("colors") or [] if _is_rgb(c)]
                continue
            params = m.get("params") or {}
            for key in ALBEDO_KEYS:
                if _is_rgb(params.get(key)):
                    self.albedo.append([float(x) for x in params[key]])
                    break


def _is_rgb(v) -> bool:
    return isinstance(v, (list, tuple)) and len(v) == 3 and all(isinstance(x, (int, float)) for x in v)


def _samples(rows: list, n: int) -> list:
    """At most `n` rows, evenly spaced (deterministic)."""
    if len(rows) <= n:
        return rows
    return [rows[i] for i in np.linspace(0, len(rows) - 1, n).round().astype(int)]


def card_data(root: str | Path, max_patches: int = MAX_PATCHES) -> dict:
    """The card of dataset `root` as a JSON-ready dict (counts, versions, coverage histograms)."""
    root = Path(root)
    raw = read_manifest(root)
    if raw is None:
        raise not_a_dataset(root)
    man = Manifest.from_dict(root, raw)
    shards = man.shards_of()
    if not shards:
        raise InputError(root, "dataset has no rendered shard yet")
    acc = _Acc()
    rng = np.random.default_rng(0)
    quota = max(1, math.ceil(max_patches / len(shards)))
    for e in shards:
        acc.add_shard(man.shard_path(e.name), quota, rng)
    F = len(acc.slant)
    dirs = np.concatenate(acc.dirs) if F else np.zeros((0, 3, 3))  # (F, N, 3)
    M = np.concatenate(acc.xtalk) if F else np.zeros((0, 3, 3))  # (F, M, N) channels x lights
    three = dirs.shape[1:] == (3, 3) and M.shape[1:] == (3, 3)  # the three-light rig: per-light histograms
    asym = np.abs(M - np.swapaxes(M, 1, 2)).reshape(len(M), -1).max(1) if len(M) and three else np.zeros(0)
    tilts = ({f"light{k}": histogram(tilt_deg(dirs[:, k]), 36, -5.0, 355.0) for k in range(dirs.shape[1])}
             if three else {"all lights": histogram(tilt_deg(dirs.reshape(-1, 3)), 36, -5.0, 355.0)})
    conds = {}
    for c in [c.name for c in man.conditions]:
        es = man.shards_of(c)
        conds[c] = {"shards": len(es), "frames": sum(x.n_frames for x in es), "patches": sum(x.n_patches for x in es)}
    cfg = raw.get("config") or {}
    cam = ((cfg.get("scene") or {}).get("camera") or {})
    alb = np.asarray(acc.albedo, np.float64).reshape(-1, 3)
    hue, sat, lum = _hue_sat_lum(alb)
    return {
        "format": CARD_FORMAT,
        "dataset": {"name": (cfg.get("dataset") or {}).get("name", root.name), "config_hash": raw.get("config_hash"),
                    "seed": raw.get("seed"), "complete": bool(raw.get("complete")),
                    "versions": raw.get("versions") or {},
                    "shard_versions": {k: sorted(v) for k, v in acc.versions.items()},
                    "resolution": [cam.get("width"), cam.get("height")],
                    "whole_frames": all(acc.whole_frames), "per_light_images": all(acc.per_light)},
        "counts": {"shards": len(shards), "planned_shards": len(man.planned_shards), "frames": F,
                   "patches": acc.n_patches_total, "material_parts": len(acc.mat_names), "conditions": conds},
        "frames": {  # one value per frame: each totals `counts.frames`
            "condition": categories(acc.cond),
            "slant_deg": histogram(acc.slant, 20),
            "tilt_deg": tilts,
            "env_ratio": histogram(acc.env, 20, 0.0),
            "crosstalk_diagonal": {f"channel{i}": histogram(M[:, i, i], 20) for i in range(M.shape[1])} if three else {},
            "crosstalk_asymmetry": histogram(asym, 20, 0.0),
            "spp": categories(str(s) for s in acc.spp),
            "shape_kind": categories(acc.shape_kind),
            "object": categories(acc.obj),
            "materials_per_frame": categories(str(n) for n in acc.n_parts),
            "patches_per_frame": histogram(acc.patches_per_frame, 20, 0.0),
        },
        "parts": {  # one value per material part: each totals `counts.material_parts`
            "material_family": categories(acc.mat_fams),
            "material": categories(acc.mat_names),
            "texture": categories(acc.textures),
        },
        "albedo": {  # analytic untextured parts (their reflectance / diffuse_reflectance / base_color)
            "parts": int(len(alb)), "textured_parts": int(sum(t != "none" for t in acc.textures)),
            "mean": alb.mean(0).round(6).tolist() if len(alb) else None,
            "luminance": histogram(lum, 20, 0.0, 1.0), "saturation": histogram(sat, 10, 0.0, 1.0),
            "hue_deg": histogram(hue[sat > 0.05], 12, 0.0, 360.0),
            "samples": [[round(x, 4) for x in c] for c in _samples(acc.albedo, ALBEDO_SAMPLES)],
            "texture_colors": [[round(float(x), 4) for x in c] for c in _samples(acc.tex_colors, ALBEDO_SAMPLES)],
        },
        "patches": {"coverage": {**histogram(acc.coverage, 20, 0.0, 1.0), "sampled": len(acc.coverage),
                                 "of": acc.n_patches_total}},
    }


# ------------------------------------------------------------------ picture
def _bars(ax, cats: dict[str, int], title: str, color: str) -> None:
    items = list(cats.items())
    shown = items[:TOP]
    names = [str(k) or "(none)" for k, _ in shown][::-1]
    ax.barh(names, [v for _, v in shown][::-1], color=color)
    more = f" (top {TOP} of {len(items)})" if len(items) > TOP else ""
    ax.set_title(f"{title}{more}", fontsize=11)
    ax.tick_params(axis="y", labelsize=8 if len(shown) > 8 else 9)
    for i, (_, v) in enumerate(shown[::-1]):
        ax.text(v, i, f" {v}", va="center", fontsize=8)
    ax.margins(x=0.15)


def _hist(ax, h: dict, title: str, color: str = "C0") -> None:
    _series(ax, {"": h}, title, [color])


def _series(ax, hs: dict[str, dict], title: str, colors) -> None:
    """Histograms on one axis (filled if one, steps if several); a series of one value is written out
    instead ("all 8 = 0.92"), since a one-bin histogram says nothing about where it sits."""
    notes, drawn = [], 0
    for (name, h), color in zip(hs.items(), colors):
        label = f"{name}: " if name else ""
        if h["min"] is None:
            notes.append((f"{label}no values", color))
        elif h["min"] == h["max"]:
            notes.append((f"{label}all {h['total'] - h['nan']} = {h['min']:g}", color))
        else:
            e, c = np.asarray(h["edges"]), np.asarray(h["counts"])
            if len(hs) == 1:
                ax.stairs(c, e, fill=True, color=color, alpha=0.85)
            else:
                ax.stairs(c, e, color=color, label=name, linewidth=1.8)
            drawn += 1
        if h.get("nan"):
            notes.append((f"{label}{h['nan']} undefined (NaN)", color))
    if drawn > 1:
        ax.legend(fontsize=8)
    for i, (t, color) in enumerate(notes):
        ax.text(0.5, 0.62 - 0.12 * i if not drawn else 0.95 - 0.1 * i, t, ha="center", va="top",
                transform=ax.transAxes, fontsize=11, color=color if len(hs) > 1 else "0.2")
    if not drawn:
        ax.set_yticks([])
        ax.set_xticks([])
    ax.set_title(title, fontsize=11)


def _axes_note(ax, text: str) -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, fontsize=10, color="0.4")
    ax.set_xticks([])
    ax.set_yticks([])


def _draw(card: dict, png: Path) -> None:
    from matplotlib.figure import Figure

    d, n, fr, pa, al = card["dataset"], card["counts"], card["frames"], card["parts"], card["albedo"]
    fig = Figure(figsize=(16, 16.5), dpi=100)
    grid = fig.add_gridspec(5, 4, height_ratios=[0.42, 1, 1, 1, 1], hspace=0.5, wspace=0.42,
                            left=0.08, right=0.98, top=0.985, bottom=0.035)
    head = fig.add_subplot(grid[0, :])
    head.axis("off")
    v = d["versions"]
    head.text(0, 0.95, f"dataset card: {d['name']}", fontsize=18, weight="bold", va="top")
    lines = [
        f"{n['shards']} shards (of {n['planned_shards']} planned{'' if d['complete'] else ', INCOMPLETE'}), "
        f"{n['frames']} frames, {n['patches']} patches, {n['material_parts']} material parts, "
        f"{len(n['conditions'])} condition(s); frames {d['resolution'][0]}x{d['resolution'][1]} px"
        + ("; whole frames stored" if d["whole_frames"] else "")
        + (" with per-light images" if d["per_light_images"] else ""),
        f"config {str(d['config_hash'])[:16]}, seed {d['seed']}; msps {v.get('msps', '?')}, "
        f"Mitsuba {v.get('mitsuba', '?')} ({v.get('variant', '?')})",
        "per-frame plots total the frames; material plots total the material parts",
    ]
    for i, t in enumerate(lines):
        head.text(0, 0.55 - i * 0.27, t, fontsize=12, va="top")
    ax = [fig.add_subplot(grid[1 + i // 4, i % 4]) for i in range(16)]

    conds = n["conditions"]
    names = [c or "(no sweep)" for c in conds][::-1]
    frames = [c["frames"] for c in conds.values()][::-1]
    ax[0].barh(names, frames, color="C0")
    for i, c in enumerate(list(conds.values())[::-1]):
        ax[0].text(0, i, f" {c['frames']} frames, {c['patches']} patches, {c['shards']} shards", va="center",
                   fontsize=9, color="white" if c["frames"] > 0.6 * max(frames) else "black")
    ax[0].tick_params(axis="y", labelsize=9)
    ax[0].set_title("conditions (frames)", fontsize=11)
    _hist(ax[1], fr["slant_deg"], "slant (deg), mean of the lights")
    rgb = ("tab:red", "tab:green", "tab:blue")
    _series(ax[2], fr["tilt_deg"], "light tilt (deg)", rgb)
    if any(h["min"] != h["max"] for h in fr["tilt_deg"].values()):
        ax[2].set_xlim(-5, 355)
        ax[2].set_xticks(range(0, 360, 60))
    _hist(ax[3], fr["env_ratio"], "environment ratio (0 = dark room)", "C4")
    _series(ax[4], fr["crosstalk_diagonal"], "crosstalk diagonal M[i,i]", rgb)
    _hist(ax[5], fr["crosstalk_asymmetry"], "crosstalk asymmetry max|M[i,k]-M[k,i]|", "C5")
    _bars(ax[6], fr["shape_kind"], "shape kinds (frames)", "C2")
    _bars(ax[7], fr["object"], "objects (frames)", "C2")
    _bars(ax[8], pa["material_family"], "material families (parts)", "C1")
    _bars(ax[9], pa["material"], "materials (parts)", "C1")
    _bars(ax[10], {f"{k} parts": c for k, c in sorted(fr["materials_per_frame"].items())}, "materials per frame",
          "C1")
    _bars(ax[11], pa["texture"], "textures (parts)", "C6")
    _swatches(ax[12], al)
    if al["parts"]:
        _hist(ax[13], al["luminance"], f"albedo luminance ({al['parts']} analytic parts)", "0.45")
    else:
        _axes_note(ax[13], "no analytic albedo")
        ax[13].set_title("albedo luminance", fontsize=11)
    cv = card["patches"]["coverage"]
    _hist(ax[14], cv, f"patch mask coverage ({cv['sampled']} of {cv['of']} patches)", "C2")
    _hist(ax[15], fr["patches_per_frame"], "patches per frame", "C3")
    for i, unit in ((1, "frames"), (2, "frames"), (3, "frames"), (4, "frames"), (5, "frames"), (13, "parts"),
                    (14, "patches"), (15, "frames")):
        ax[i].tick_params(labelsize=9)
        ax[i].set_ylabel(unit, fontsize=9)
    with atomic_write(png) as tmp:
        fig.savefig(tmp, format="png", metadata={"Software": None})  # no version/time chunks: same bytes


def _swatches(ax, al: dict) -> None:
    """Albedo colours sorted by hue (sRGB-encoded for display), textured palettes below them."""
    from msps_render.preview import srgb8

    rows = []
    for key in ("samples", "texture_colors"):
        c = np.asarray(al[key], np.float64).reshape(-1, 3)
        if len(c):
            hue, sat, lum = _hue_sat_lum(c)
            order = np.lexsort((lum, np.where(sat > 0.05, hue, -1.0)))
            rows.append((key, c[order]))
    ax.set_title(f"albedo colours ({al['parts']} parts; {al['textured_parts']} textured)", fontsize=11)
    if not rows:
        _axes_note(ax, "no analytic albedo\n(measured materials only)")
        return
    cols = 20
    blocks = []
    for _, c in rows:
        r = -(-len(c) // cols)
        pad = np.ones((r * cols, 3))
        pad[:len(c)] = c
        blocks.append(srgb8(pad.reshape(r, cols, 3).astype(np.float32)))
    gap = np.full((1, cols, 3), 255, np.uint8)
    img = np.concatenate([b if i == 0 else np.concatenate([gap, b]) for i, b in enumerate(blocks)])
    ax.imshow(img, interpolation="nearest", aspect="auto")
    ax.set_xticks([])
    ticks = [0]
    for b in blocks[:-1]:
        ticks.append(ticks[-1] + len(b) + 1)
    ax.set_yticks(ticks, ["constant" if k == "samples" else "texture palettes" for k, _ in rows], fontsize=8)


# ------------------------------------------------------------------ files
def write_card(root: str | Path, png: str | Path | None = None, max_patches: int = MAX_PATCHES) -> tuple[Path, Path]:
    """Write the card of dataset `root`: PNG at `png` (default DIR/card.png) and JSON beside it."""
    root = Path(root)
    png = Path(png) if png is not None else root / CARD_PNG
    js = png.with_suffix(".json") if png != root / CARD_PNG else root / CARD_JSON
    card = card_data(root, max_patches)
    png.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(js) as tmp:
        Path(tmp).write_text(json.dumps(card, indent=1) + "\n")
    _draw(card, png)
    return png, js
