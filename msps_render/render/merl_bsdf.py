"""Mitsuba 3 BSDF plugin `merl`: a measured (MERL-format) table evaluated with `dr.gather`.

Registered per Mitsuba variant on first use by `merl_bsdf_dict` (idempotent); the table
file comes from `brdf.library.resolve_table`.
Lookup: nearest bin with MERL's reference semantics (square-root theta_h
bins, linear theta_d / phi_d, phi_d folded by reciprocity), computed from
s = wi + wo and u = wi - wo so that swapping wi and wo gives bit-identical bins
(exact reciprocity; see docs/brdf.md). Sampling: a GGX visible-normal lobe
fitted to the table (`merl.fit_sampling_lobe`) mixed with cosine-weighted
hemisphere sampling; `pdf` is the same mixture, so sample/pdf/eval agree.
Spectral variants: each RGB value is upsampled with Mitsuba's sRGB model
applied to its chromaticity (rgb / (2 max)) and scaled back (x 2 max), as
Mitsuba does for unbounded sRGB spectra; the rgb2spec coefficients are
pre-fetched on its own 3 x 64 x 64 node grid, so bilinear interpolation in
the kernel reproduces `srgb_model_fetch`.

Memory: one table is 3 x 1,458,000 float32 = 17.5 MB, a read-only memory map of
its float32 cache file (LLVM variants use it without a copy; the pages are the OS
page cache, shared by all workers), shared by every scene and shape of the
process; at most $MSPS_TABLE_CACHE (default 8) are kept per process
(`TableCache`, least recently used evicted), so a worker's memory does not grow
with the number of measured materials (docs/benchmarks.md "Worker memory per
measured material").
Mitsuba is imported lazily, inside functions.
"""
from __future__ import annotations

import functools
import hashlib
import json
import logging
import math
import os
from collections import OrderedDict
from pathlib import Path
from typing import NamedTuple

import numpy as np

from msps_render.atomic import write_bytes
from msps_render.brdf import merl
from msps_render.brdf.analytic import cache_dir, cache_writes
from msps_render.brdf.library import resolve_table
from msps_render.errors import InputError, WriteFailed, env_count
from msps_render.render.variant import register_plugin

log = logging.getLogger(__name__)

PLUGIN_NAME = "merl"
_RGB2SPEC_RES = 64  # Mitsuba's srgb.coeff resolution


# ----------------------------------------------------------------- table cache
TABLE_CACHE_ENV = "MSPS_TABLE_CACHE"
DEFAULT_TABLE_CACHE = 8  # tables kept per process: ~17 MiB each (docs/benchmarks.md "Worker memory per material")


def _baked_file(path: str) -> str:
    """The float32 interleaved table file (`merl.write_baked`) behind any table file.

    Baked Neural-BRDF tables already are one; a MERL `.binary` (real or generated) is
    converted once into the cache folder, keyed by its path, size and mtime, so evicting
    and reloading it later costs a memory map instead of a 35 MB float64 read.
    """
    if path.endswith(merl.BAKED_SUFFIX):
        return path
    try:
        st = os.stat(path)
    except OSError as e:
        raise InputError(path, f"cannot read MERL file ({e.strerror})") from None
    key = hashlib.sha1(f"{os.path.realpath(path)}|{st.st_size}|{st.st_mtime_ns}".encode()).hexdigest()[:16]
    out = cache_dir() / f"table-{Path(path).stem}-{key}-v2{merl.BAKED_SUFFIX}"
    if not (out.is_file() and out.stat().st_size == merl.BAKED_FILE_BYTES):
        t = merl.read_merl(path, dtype=np.float32)
        if t.n_negative or t.n_nonfinite:
            log.info("%s: %d negative and %d non-finite entries set to 0", path, t.n_negative, t.n_nonfinite)
        with cache_writes(out.parent):
            merl.write_baked(out, t.rgb)
    return str(out)


def _load_table(path: str) -> tuple[np.ndarray, float, float]:
    """(memory-mapped interleaved (N, 3) float32 table, lobe alpha, lobe weight) of a table file."""
    baked = _baked_file(path)
    inter = merl.map_baked(baked)
    if path not in _LOBES:  # a pure function of the file: reloading an evicted table skips the fit
        _LOBES[path] = _stored_lobe(baked, inter)
    alpha, weight = _LOBES[path]
    return inter, alpha, weight


LOBE_SUFFIX = ".lobe.json"


def _stored_lobe(baked: str, inter: np.ndarray) -> tuple[float, float]:
    """The sampling lobe (`merl.fit_sampling_lobe`) of a baked table, kept beside it in the table cache.

    Why: the fit reads the table's retro-reflection slice (pages all over its 16.7 MiB) and solves 64
    small least squares, 5-20 ms; every worker process paid it once per measured material (80 for the
    shipped catalogue) before its first frames.  The stored values are the fit's own floats (JSON
    round-trips them exactly), so pixels do not change; they count only for the table file of the same
    size and modification time.  Only tables in msps's own cache get one (no file is added beside a
    table a user gave), and a sidecar that cannot be written is skipped: the fit is kept in memory."""
    st = os.stat(baked)
    side = Path(baked + LOBE_SUFFIX)
    stamp = {"size": st.st_size, "mtime_ns": st.st_mtime_ns}
    try:
        d = json.loads(side.read_text(encoding="utf-8"))
        if {k: d.get(k) for k in stamp} == stamp:
            return float(d["alpha"]), float(d["weight"])
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        pass  # none yet, or unreadable: fit again
    alpha, weight = merl.fit_sampling_lobe(inter.T.reshape(3, *merl.DIMS))
    if side.parent == cache_dir():
        try:
            write_bytes(side, json.dumps(dict(stamp, alpha=alpha, weight=weight)).encode(), unique=True)  # workers race
        except WriteFailed as e:  # a full cache disk: the table itself was written, this is only a saving
            log.debug("sampling lobe of %s not stored (%s)", baked, e)
    return alpha, weight


_LOBES: dict[str, tuple[float, float]] = {}  # path -> (alpha, weight): two floats per table, unbounded


def table_cache_size() -> int:
    """Tables kept per process: $MSPS_TABLE_CACHE (>= 1), else `DEFAULT_TABLE_CACHE`."""
    n = env_count(TABLE_CACHE_ENV, "tables kept per process")
    return DEFAULT_TABLE_CACHE if n is None else n


class CacheInfo(NamedTuple):
    hits: int
    misses: int
    maxsize: int
    currsize: int


class TableCache:
    """LRU of device tables by (path, variant), at most `table_cache_size()` of them.

    Why bounded: a table is 16.7 MiB on the device and a corpus may draw from any
    number of measured materials, so an unbounded cache made a worker's memory grow
    with the catalogue (64 materials: ~1.5 GiB).  Evicting drops the cache's
    reference only; the drjit array (a memory map of the float32 table file, shared
    with every process mapping it) is released as soon as no live scene holds it, and
    a later scene maps the same float32 values again (pixels do not change).
    """

    def __init__(self) -> None:
        self._tables: OrderedDict[tuple[str, str], tuple] = OrderedDict()
        self.hits = self.misses = 0

    def __call__(self, path: str, variant: str):
        """The table as a drjit Float (JIT variants) or numpy array (scalar variants), with lobe (alpha, weight)."""
        key = (path, variant)
        if key in self._tables:
            self.hits += 1
            self._tables.move_to_end(key)
            return self._tables[key]
        self.misses += 1
        entry = _device_table(path)
        limit = table_cache_size()
        while len(self._tables) >= limit:
            self._tables.popitem(last=False)
        self._tables[key] = entry
        return entry

    def trim(self, keep: int) -> None:
        """Keep only the `keep` most recently used tables (`render/memory.py` `frame_budget`)."""
        while len(self._tables) > max(0, keep):
            self._tables.popitem(last=False)

    def cache_info(self) -> CacheInfo:
        return CacheInfo(self.hits, self.misses, table_cache_size(), len(self._tables))

    def cache_clear(self) -> None:
        self._tables.clear()
        self.hits = self.misses = 0


def _device_table(path: str):
    import drjit as dr
    import mitsuba as mi

    inter, alpha, weight = _load_table(path)
    if dr.is_jit_v(mi.Float):
        data = mi.Float(inter.reshape(-1))  # LLVM: no copy, drjit keeps the mapping alive while in use
        dr.make_opaque(data)
        return data, alpha, weight
    return inter, alpha, weight


device_table = TableCache()  # read-only tables shared by every BSDF instance of the process (the only global state)


@functools.lru_cache(maxsize=None)
def _coeff_grid(variant: str):
    """rgb2spec coefficients at the nodes of its own grid for colours with max component 1/2.

    Node (i, yi, xi): rgb[i] = 0.5, rgb[(i+1)%3] = 0.5 xi/63, rgb[(i+2)%3] = 0.5 yi/63.
    """
    import drjit as dr
    import mitsuba as mi

    r = _RGB2SPEC_RES
    grid = np.zeros((3, r, r, 3), dtype=np.float32)
    for i in range(3):
        for yi in range(r):
            for xi in range(r):
                c = [0.0, 0.0, 0.0]
                c[i] = 0.5
                c[(i + 1) % 3] = 0.5 * xi / (r - 1)
                c[(i + 2) % 3] = 0.5 * yi / (r - 1)
                grid[i, yi, xi] = np.array(mi.srgb_model_fetch(mi.ScalarColor3f(*c)), dtype=np.float32)
    if dr.is_jit_v(mi.Float):
        g = mi.Float(grid.reshape(-1))
        dr.make_opaque(g)
        return g
    return grid.reshape(-1, 3)


# ------------------------------------------------------------- lookup (drjit)
def merl_index(wi, wo):
    """Flat MERL bin index of local-frame direction pairs (drjit arrays; symmetric in wi, wo)."""
    import drjit as dr
    import mitsuba as mi

    s = wi + wo
    u = wi - wo
    r2 = s.x * s.x + s.y * s.y
    slen = dr.norm(s)
    theta_h = dr.atan2(dr.sqrt(r2), s.z)
    theta_d = dr.atan2(dr.norm(u), slen)
    # u expressed in the half-vector frame (Rz(-phi_h) then Ry(-theta_h)), scaled by r |s| > 0.
    X = s.z * (s.x * u.x + s.y * u.y) - r2 * u.z
    Y = slen * (s.x * u.y - s.y * u.x)
    degenerate = r2 == 0  # half vector on the normal: MERL takes phi_h = 0, theta_h = 0
    X = dr.select(degenerate, u.x, X)
    Y = dr.select(degenerate, u.y, Y)
    flip = (Y < 0) | ((Y == 0) & (X < 0))  # phi_d -> phi_d + pi (reciprocity fold)
    X = dr.select(flip, -X, X)
    Y = dr.select(flip, -Y, Y)
    phi_d = dr.atan2(Y, X)
    i_h = mi.Int32(dr.floor(dr.sqrt(dr.maximum(theta_h, 0.0) * (merl.RES_THETA_H * merl.RES_THETA_H * 2.0 / math.pi))))
    i_d = mi.Int32(dr.floor(theta_d * (merl.RES_THETA_D * 2.0 / math.pi)))
    i_p = mi.Int32(dr.floor(phi_d * ((merl.RES_PHI_D // 2) / math.pi)))
    i_h = dr.clip(i_h, 0, merl.RES_THETA_H - 1)
    i_d = dr.clip(i_d, 0, merl.RES_THETA_D - 1)
    i_p = dr.clip(i_p, 0, merl.RES_PHI_D // 2 - 1)
    n_p = merl.RES_PHI_D // 2
    return mi.UInt32(i_p + n_p * (i_d + merl.RES_THETA_D * i_h))


def _gather_rgb(table, idx, active):
    import drjit as dr
    import mitsuba as mi

    if dr.is_jit_v(mi.Float):
        return dr.gather(mi.Color3f, table, idx, active)
    if not active:
        return mi.Color3f(0.0)
    v = table[int(idx)]
    return mi.Color3f(float(v[0]), float(v[1]), float(v[2]))


def _rgb_to_spectrum(rgb, wavelengths, grid):
    """Unbounded sRGB upsampling: srgb_model(rgb / (2 max)) * 2 max, bilinear in the rgb2spec grid."""
    import drjit as dr
    import mitsuba as mi

    scale = 2.0 * dr.maximum(dr.maximum(rgb.x, rgb.y), rgb.z)
    c = rgb / dr.select(scale > 0, scale, 1.0)
    # argmax, ties to the later component (as rgb2spec_fetch)
    i = dr.select(c.y >= c.x, 1, 0)
    ci = dr.select(i == 1, c.y, c.x)
    i = dr.select(c.z >= ci, 2, i)
    ci = dr.maximum(dr.select(i == 2, c.z, ci), 1e-20)
    a = dr.select(i == 0, c.y, dr.select(i == 1, c.z, c.x))  # rgb[(i+1)%3]
    b = dr.select(i == 0, c.z, dr.select(i == 1, c.x, c.y))  # rgb[(i+2)%3]
    r1 = _RGB2SPEC_RES - 1
    x = dr.clip(a / ci * r1, 0.0, float(r1))
    y = dr.clip(b / ci * r1, 0.0, float(r1))
    xi = dr.minimum(mi.UInt32(x), r1 - 1)
    yi = dr.minimum(mi.UInt32(y), r1 - 1)
    x1 = x - mi.Float(xi)
    y1 = y - mi.Float(yi)
    base = (mi.UInt32(i) * _RGB2SPEC_RES + yi) * _RGB2SPEC_RES + xi

    def node(off):
        if dr.is_jit_v(mi.Float):
            return dr.gather(mi.Vector3f, grid, base + off)
        v = grid[int(base + off)]
        return mi.Vector3f(float(v[0]), float(v[1]), float(v[2]))

    coeff = ((node(0) * (1 - x1) + node(1) * x1) * (1 - y1)
             + (node(_RGB2SPEC_RES) * (1 - x1) + node(_RGB2SPEC_RES + 1) * x1) * y1)
    spec = mi.srgb_model_eval(coeff, wavelengths)
    return mi.UnpolarizedSpectrum(spec) * scale


# ----------------------------------------------------------------- the plugin
@functools.lru_cache(maxsize=None)
def _plugin_class(variant: str):
    """The `mi.BSDF` subclass bound to `variant` (Python plugins are per-variant classes)."""
    import drjit as dr
    import mitsuba as mi

    flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide

    class MerlBSDF(mi.BSDF):
        """Measured isotropic BRDF from a MERL `.binary` (property `filename`)."""

        def __init__(self, props: "mi.Properties"):
            mi.BSDF.__init__(self, props)
            self.filename = str(props["filename"])
            self.table, alpha, weight = device_table(self.filename, variant)
            if "lobe_alpha" in props:
                alpha = float(props["lobe_alpha"])
            if "lobe_weight" in props:
                weight = float(props["lobe_weight"])
            self.lobe = (float(min(max(alpha, 1e-3), 1.0)), float(min(max(weight, 0.0), 1.0)))
            # Opaque per-scene scalars (JIT variants): a Python float would be baked into the
            # kernel as a literal, so every table (own alpha and weight) would compile its own
            # megakernel; as opaque Floats they are kernel inputs and scenes share kernels.
            self.alpha, self.weight = ((dr.opaque(mi.Float, v) for v in self.lobe) if dr.is_jit_v(mi.Float)
                                       else self.lobe)
            self.spectral = mi.is_spectral
            self.grid = _coeff_grid(variant) if self.spectral else None
            self.m_components = [flags]
            self.m_flags = flags

        def _value(self, si, wo, active):
            idx = merl_index(si.wi, wo)
            rgb = _gather_rgb(self.table, idx, active)
            if self.spectral:
                return _rgb_to_spectrum(rgb, si.wavelengths, self.grid)
            return mi.Spectrum(rgb)

        def _pdf(self, wi, wo):
            cos_o = dr.maximum(mi.Frame3f.cos_theta(wo), 0.0)
            pdf = (1.0 - self.weight) * cos_o * (1.0 / math.pi)
            # No Python `if` on the weight: the lobe is always traced (and selected away at
            # weight 0), so tables with and without a lobe share one kernel.
            distr = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, self.alpha, True)
            m = dr.normalize(wi + wo)
            dwo = dr.dot(wo, m)
            p_m = distr.pdf(wi, m)
            lobe = dr.select(dwo > 0, p_m / (4.0 * dr.maximum(dwo, 1e-12)), 0.0)
            return pdf + dr.select(self.weight > 0.0, self.weight * lobe, 0.0)

        def _eval_pdf(self, ctx, si, wo, active):
            cos_i = mi.Frame3f.cos_theta(si.wi)
            cos_o = mi.Frame3f.cos_theta(wo)
            active = active & (cos_i > 0) & (cos_o > 0)
            if not ctx.is_enabled(mi.BSDFFlags.GlossyReflection):
                active = active & False
            value = self._value(si, wo, active) * cos_o
            pdf = self._pdf(si.wi, wo)
            return dr.select(active, value, 0.0), dr.select(active, pdf, 0.0)

        def eval(self, ctx, si, wo, active=True):
            return self._eval_pdf(ctx, si, wo, active)[0]

        def pdf(self, ctx, si, wo, active=True):
            cos_i = mi.Frame3f.cos_theta(si.wi)
            cos_o = mi.Frame3f.cos_theta(wo)
            ok = active & (cos_i > 0) & (cos_o > 0)
            return dr.select(ok, self._pdf(si.wi, wo), 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self._eval_pdf(ctx, si, wo, active)

        def sample(self, ctx, si, sample1, sample2, active=True):
            cos_i = mi.Frame3f.cos_theta(si.wi)
            active = active & (cos_i > 0)
            wo = mi.warp.square_to_cosine_hemisphere(sample2)
            distr = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, self.alpha, True)
            m, _ = distr.sample(si.wi, sample2)
            wo = dr.select(sample1 < self.weight, mi.reflect(si.wi, m), wo)  # never at weight 0
            value, pdf = self._eval_pdf(ctx, si, wo, active)
            active = active & (pdf > 0)
            bs = dr.zeros(mi.BSDFSample3f)
            bs.wo = wo
            bs.pdf = dr.select(active, pdf, 0.0)
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
            bs.sampled_component = mi.UInt32(0)
            weight = value / dr.select(active, pdf, 1.0)
            return bs, dr.select(active, weight, 0.0)

        def traverse(self, callback):
            pass

        def parameters_changed(self, keys):
            pass

        def to_string(self):
            return (f"MerlBSDF[filename='{self.filename}', lobe_alpha={self.lobe[0]:.4f}, "
                    f"lobe_weight={self.lobe[1]:.3f}]")

    return MerlBSDF


def register(variant: str | None = None) -> str:
    """Register the `merl` plugin for the current (or given, must be current) variant; idempotent."""
    return register_plugin("bsdf", PLUGIN_NAME, _plugin_class, _REGISTERED, variant)


_REGISTERED: set[str] = set()


def merl_bsdf_dict(m) -> dict:
    """`mi.load_dict` description of a measured material (kind 'merl'; registers the plugin)."""
    variant = register()
    path = resolve_table(m)
    device_table(str(path), variant)  # load (once) here, so a bad file raises InputError, not a Mitsuba error
    d = {"type": PLUGIN_NAME, "filename": str(path)}
    for k in ("lobe_alpha", "lobe_weight"):
        if k in m.params:
            d[k] = float(m.params[k])
    return d


def table_memory_bytes() -> int:
    """Device memory of one loaded table (float32 RGB)."""
    return 3 * merl.N_BINS * 4
