"""Mitsuba integrator `msps_multilight`: one camera path per sample, every light sampled at every vertex.

Why: Mitsuba's `path` and `direct` pick ONE emitter at random per next-event
sample, so K differently coloured lights in one render cost K-fold selection
noise; the old remedy was one render per emitter (`emitters.render_emitters_separately`).
This integrator traces each camera path once and, at every vertex, sends one
shadow ray to EVERY delta light (directional, point: `sample_direction` is
deterministic) and samples the environment by MIS (emitter sampling of the
env + BSDF sampling that escapes to it, power heuristic).  Each emitter's
radiance goes to its own AOV channels `<emitter id>.R/.G/.B`, so one render
gives the K per-light images and the environment image.  Everything else is
Mitsuba `path` (max_depth, Russian roulette from `rr_depth` on, hide_emitters;
`direct` = max_depth 2), so every per-emitter image has the same expectation as
rendering that emitter alone with Mitsuba's own integrator.

Spectral variants: a light's spectrum is narrow, so each emitter gets its own
four wavelengths, drawn from its own camera-channel bands (`set_bands`: light k:
E_k(λ)·S_i(λ) with the light emitting a flat unit spectrum; environment: S_i(λ)),
and its own throughput along the shared path; the AOVs are camera channels,
Σ_λ L(λ)·band_i(λ)/pdf(λ) (see `render.spectral`).  A camera of M channels (`channels`
property; narrow-band rigs, `msps_render.rig`) has M bands per emitter and M AOVs
`<emitter id>.C0 .. C{M-1}`; three channels keep the names R, G, B.  All groups reuse the same
random numbers for BSDF sampling, which gives the same direction for every
BSDF kind we render (their lobe choice does not depend on wavelength; checked
in tests/test_multilight.py).

Registered per Mitsuba variant (`register`, idempotent).  Per-scene values
(band tables) are device arrays, never Python scalars, so the kernel is reused
across scenes of the same structure.  Mitsuba is imported lazily.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Sequence

import numpy as np

from msps_render.render.variant import register_plugin

PLUGIN_NAME = "msps_multilight"
RR_DEPTH = 5  # Mitsuba's default for `path`
PART_ATTRIBUTE = "face_part"  # pooled scenes: the material part of each face (render.pool)
_CHANNELS = ("R", "G", "B")


@dataclasses.dataclass
class PathState:
    """The state of one camera path through the `dr.while_loop` of `MultiLightIntegrator.sample`
    (drjit traverses dataclasses field by field).  `beta`: throughput per group (all emitters in
    RGB, one per emitter in spectral variants); `acc`: radiance gathered per emitter; `prev_*`:
    the previous vertex and its BSDF sample, for the environment's MIS weight."""

    sampler: object
    ray: object
    depth: object
    active: object
    valid_ray: object  # the camera ray hit something (or the environment is visible)
    eta: object
    prev_si: object
    prev_pdf: object
    prev_delta: object
    beta: list
    acc: list


@dataclasses.dataclass(frozen=True)
class PartTable:
    """Pooled scenes: the frame's BSDF per material part (kept alive here) and their device pointers."""

    bsdfs: list
    table: object  # mi.BSDFPtr, opaque


@dataclasses.dataclass
class FrameTable:
    """Batched frames (`render.batch`): what each frame of one launch has of its own, as opaque device
    arrays indexed by its slot b: K lights, all directional (direction toward the light in the object
    frame, RGB irradiance) or all point lights (position in the object frame about the cell's centre,
    RGB intensity), the material part of every face of its mesh, and each part's BSDF.
    Orthographic frames of one shape share its mesh (one cell of space per shape); frame b's camera
    stands `distance + b * step` from the cell's centre, so a camera ray's slot is read from how far
    its origin is from the centre of the cell it hits.  Perspective frames each have a cell of their
    own, and `cell_slot` names its frame.  The slot is carried along the path.  Rays after the
    camera's reach at most `reach`, so a path never leaves its cell."""

    n_frames: int
    n_lights: int
    spacing: float  # cells at (0, i * spacing, j * spacing)
    distance: float  # the frames' camera distance
    step: float  # slot b's camera is distance + b * step from its cell's centre
    reach: float
    light_d: tuple  # (x, y, z) mi.Float, (B * K,)
    light_e: tuple  # (r, g, b) mi.Float, (B * K,)
    face_part: object  # mi.UInt32 (B * F): the part of face f of slot b's mesh at b * F + f
    face_stride: object  # opaque mi.UInt32: F
    part_stride: object  # opaque mi.UInt32 P (a literal would compile a kernel per batch's largest part count):
    # slot b's part p has its BSDF at b * P + p
    bsdfs: object  # mi.BSDFPtr (B * P)
    keep: list  # the BSDF objects (alive as long as the table)
    point: bool = False  # point lights: light_d holds positions, light_e intensities
    cell_slot: object = None  # perspective: mi.UInt32 (lattice^2): the slot of the frame in cell (i, j)
    lattice: int = 16  # cells (i, j), -lattice / 2 <= i, j < lattice / 2, at (i + lattice / 2) * lattice + ...


@dataclasses.dataclass
class BatchPathState:
    """`PathState` of a batched path: the slot of its frame instead of the environment's MIS state."""

    sampler: object
    ray: object
    depth: object
    active: object
    valid_ray: object
    eta: object
    slot: object
    beta: list  # one throughput per group (RGB: one; spectral: one per light)
    acc: list


def channel_names(emitter_id: str, n_channels: int = 3) -> list[str]:
    """The AOV channel names of one emitter's image: R, G, B, or C0 .. C{M-1} for M != 3 camera channels."""
    names = _CHANNELS if n_channels == 3 else tuple(f"C{i}" for i in range(n_channels))
    return [f"{emitter_id}.{c}" for c in names]


def integrator_dict(kind: str, max_depth: int, emitter_ids: Sequence[str], hide_emitters: bool = True,
                    anisotropy: Sequence[float] = (), channels: int = 3) -> dict:
    """`mi.load_dict` description of the one-pass integrator (registers it for the current variant).

    `kind` "direct" is one bounce (Mitsuba `direct` with one emitter and one BSDF sample).
    `anisotropy`: per emitter, the LED exponent mu of a point light (radiant intensity x cos^mu of the
    angle off its axis, the axis toward the scene origin); empty or 0: isotropic, as Mitsuba's `point`.
    `channels`: camera channels per emitter (spectral variants; RGB variants: 3).
    """
    register()
    d = {"type": PLUGIN_NAME, "max_depth": 2 if kind == "direct" else int(max_depth),
         "rr_depth": RR_DEPTH, "hide_emitters": bool(hide_emitters), "emitters": ",".join(emitter_ids)}
    if any(anisotropy):
        d["anisotropy"] = ",".join(f"{float(m):.9g}" for m in anisotropy)
    if channels != 3:
        d["channels"] = int(channels)
    return d


def band_table(grid: np.ndarray, bands: np.ndarray) -> dict[str, np.ndarray]:
    """Sampling table of the wavelength density ∝ Σ_i band_i (piecewise linear, like the bands).

    `bands` (N, M): M camera channels (3: r, g, b).
    Returns float32 arrays: knots `grid` (N,), per-bin inclusive/exclusive CDF `cdf_hi`,
    `cdf_lo` (N-1,), the band sum at each bin's left/right knot `s` (N-1, 2), and per bin the
    bands at its left/right knot times the normalisation, `c0`, `c1` (N-1, M), so that
    band_i(λ)/pdf(λ) = lerp(c0, c1, t)_i / lerp(s0, s1, t) exactly.  (A piecewise-constant pdf
    would let band/pdf vary inside each 1 nm bin: 4x the colour noise on a 20 nm LED's flanks.)
    """
    grid = np.asarray(grid, np.float64)
    bands = np.asarray(bands, np.float64)
    if (grid.ndim != 1 or bands.ndim != 2 or bands.shape[0] != len(grid) or bands.shape[1] < 1 or len(grid) < 2
            or np.any(np.diff(grid) <= 0)):
        raise ValueError(f"bands must be (N, M) on an increasing grid of N >= 2 wavelengths, got {bands.shape}")
    if np.any(~np.isfinite(bands)) or np.any(bands < 0):
        raise ValueError("bands must be finite and >= 0")
    ssum = bands.sum(1)
    mass = 0.5 * (ssum[:-1] + ssum[1:]) * np.diff(grid)
    total = mass.sum()
    if total <= 0:
        raise ValueError("bands are zero everywhere: nothing to sample")
    cdf_hi = np.cumsum(mass) / total
    cdf_hi[-1] = 1.0
    cdf_lo = np.concatenate([[0.0], cdf_hi[:-1]])
    f32 = functools.partial(np.ascontiguousarray, dtype=np.float32)
    return {"grid": f32(grid), "cdf_lo": f32(cdf_lo), "cdf_hi": f32(cdf_hi),
            "s": f32(np.stack([ssum[:-1], ssum[1:]], 1)), "c0": f32(bands[:-1] * total),
            "c1": f32(bands[1:] * total)}


def _aligned(a: np.ndarray) -> np.ndarray:
    """`a` flattened into float32 memory aligned to 64 bytes.

    Why: drjit uses a numpy buffer in place and reads `dr.gather(mi.Vector2f, ...)` from it as one packet
    only when the buffer is aligned; numpy's allocations are aligned or not by chance, so the same band
    table compiled one of two kernels (measured: 3 new kernels in 10 launches of a spectral batch, and
    ~1 s of LLVM each)."""
    flat = np.ascontiguousarray(a, np.float32).reshape(-1)
    buf = np.empty(flat.size + 16, np.float32)
    start = (-buf.ctypes.data % 64) // 4
    out = buf[start:start + flat.size]
    out[:] = flat
    return out


def _kept(valid, value):
    """A sample's value where its camera ray counts and the value is finite, else 0.

    Why: a path can reach a numerically failed estimate (measured: a smooth `roughplastic`, alpha 0.05,
    gave one NaN/inf sample in a 64-spp spectral-train frame), and one such sample made the pixel NaN
    and the whole shard fail (float16 storage refuses it).  Dropping it changes no finite sample."""
    import drjit as dr

    return dr.select(valid & dr.isfinite(value), value, 0.0)


def _mis_weight(pdf_a, pdf_b):
    """Power heuristic, as Mitsuba's `path` (0 where undefined)."""
    import drjit as dr

    a2, b2 = pdf_a * pdf_a, pdf_b * pdf_b
    w = a2 / (a2 + b2)
    return dr.select(dr.isfinite(w), w, 0.0)


def _sample_wavelengths(mi, table: dict, u):
    """Four stratified wavelengths from `table` (exact inversion of the piecewise-linear density)
    and, per camera channel, the lane weights band_i(λ_j)/pdf(λ_j)/4 (the channel estimate is
    Σ_j L(λ_j)·weight_ij); as many channels as the table's bands."""
    import drjit as dr

    n_lanes = dr.size_v(mi.UnpolarizedSpectrum)
    n_bins = dr.width(table["cdf_hi"])
    n_ch = dr.width(table["c0"]) // n_bins
    lam, weights = [], [[] for _ in range(n_ch)]
    for j in range(n_lanes):
        uj = u + j / n_lanes
        uj = dr.select(uj >= 1.0, uj - 1.0, uj)
        idx = dr.binary_search(0, n_bins - 1, lambda i: dr.gather(mi.Float, table["cdf_hi"], i) <= uj)
        lo = dr.gather(mi.Float, table["cdf_lo"], idx)
        hi = dr.gather(mi.Float, table["cdf_hi"], idx)
        v = dr.clip((uj - lo) / dr.maximum(hi - lo, 1e-30), 0.0, 1.0)
        s = dr.gather(mi.Vector2f, table["s"], idx)
        # inverse of the linear density s0 + (s1 - s0) t on the bin: s0 t + (s1 - s0) t^2 / 2 = v (s0 + s1) / 2
        num = v * (s.x + s.y)
        t = dr.clip(num / dr.maximum(s.x + dr.sqrt(dr.maximum(s.x * s.x + (s.y - s.x) * num, 0.0)), 1e-30),
                    0.0, 1.0)
        g0 = dr.gather(mi.Float, table["grid"], idx)
        g1 = dr.gather(mi.Float, table["grid"], idx + 1)
        lam.append(dr.lerp(g0, g1, t))
        ssum = dr.lerp(s.x, s.y, t)
        if n_ch == 3:  # r, g, b (the kernel of three-channel cameras, unchanged)
            c = dr.lerp(dr.gather(mi.Vector3f, table["c0"], idx), dr.gather(mi.Vector3f, table["c1"], idx), t)
            w = c * dr.select(ssum > 0, 1.0 / (n_lanes * ssum), 0.0)
            for i in range(3):
                weights[i].append(w[i])
        else:  # M channels: the bin's row of M values, one gather per channel
            scale = dr.select(ssum > 0, 1.0 / (n_lanes * ssum), 0.0)
            for i in range(n_ch):
                k = idx * n_ch + i
                weights[i].append(dr.lerp(dr.gather(mi.Float, table["c0"], k),
                                          dr.gather(mi.Float, table["c1"], k), t) * scale)
    wavelengths = mi.UnpolarizedSpectrum(*lam)
    return wavelengths, [mi.UnpolarizedSpectrum(*w) for w in weights]


def _with_wavelengths(mi, si, wavelengths):
    """A copy of `si` carrying other wavelengths (spectral groups); `si` itself in RGB variants."""
    if wavelengths is None:
        return si
    out = mi.SurfaceInteraction3f(si)
    out.wavelengths = wavelengths
    return out


@functools.lru_cache(maxsize=None)
def _plugin_class(variant: str):
    """The `mi.SamplingIntegrator` subclass bound to `variant` (Python plugins are per-variant classes)."""
    import drjit as dr
    import mitsuba as mi

    class MultiLightIntegrator(mi.SamplingIntegrator):
        """All emitters per vertex, one AOV triple per emitter (see the module docstring)."""

        def __init__(self, props: "mi.Properties"):
            mi.SamplingIntegrator.__init__(self, props)
            self.max_depth = int(props.get("max_depth", -1))
            self.rr_depth = int(props.get("rr_depth", RR_DEPTH))
            self.hide_emitters = bool(props.get("hide_emitters", False))
            self.emitter_ids = [s for s in str(props.get("emitters", "")).split(",") if s]
            if not self.emitter_ids:
                raise ValueError(f"{PLUGIN_NAME}: property 'emitters' (comma-separated emitter ids) is required")
            mus = [float(m) for m in str(props.get("anisotropy", "")).split(",") if m]
            if mus and len(mus) != len(self.emitter_ids):
                raise ValueError(f"{PLUGIN_NAME}: {len(mus)} anisotropy exponents for {len(self.emitter_ids)} emitters")
            self.anisotropy = mus or [0.0] * len(self.emitter_ids)
            self.n_channels = int(props.get("channels", 3))
            if self.n_channels < 1 or (self.n_channels != 3 and not mi.is_spectral):
                raise ValueError(f"{PLUGIN_NAME}: {self.n_channels} camera channels; RGB variants write R, G, B "
                                 f"(3), spectral variants 1 or more")
            if self.max_depth < 0:
                self.max_depth = 2 ** 31 - 1
            self.tables: dict[str, dict] = {}
            self.parts: PartTable | None = None
            self.batch: FrameTable | None = None

        # ---- configuration
        def set_bands(self, grid: np.ndarray, bands: dict[str, np.ndarray]) -> None:
            """Spectral variants: camera-channel bands (N, M) on `grid` for every emitter id (M = `channels`)."""
            missing = [e for e in self.emitter_ids if e not in bands]
            if missing:
                raise ValueError(f"{PLUGIN_NAME}: no bands for emitters {missing}")
            wrong = [e for e in self.emitter_ids if np.shape(bands[e])[1:] != (self.n_channels,)]
            if wrong:
                raise ValueError(f"{PLUGIN_NAME}: bands of {wrong[0]} have shape {np.shape(bands[wrong[0]])}, "
                                 f"expected (N, {self.n_channels}) (the integrator's channels)")
            self.tables = {}
            for e in self.emitter_ids:
                t = band_table(grid, bands[e])
                dev = {k: mi.Float(_aligned(v)) for k, v in t.items()}
                for v in dev.values():
                    dr.make_opaque(v)
                self.tables[e] = dev

        def set_part_bsdfs(self, bsdfs: Sequence | None) -> None:
            """Pooled scenes (`render.pool`): the BSDF of part p is `bsdfs[p]`, looked up through the
            hit face's `PART_ATTRIBUTE`, not the shape's own BSDF (None: the shape's BSDF, as Mitsuba).
            The table is an opaque device array, so new BSDFs every frame keep the kernel."""
            if bsdfs is None:
                self.parts = None
                return
            bsdfs = list(bsdfs)
            table = dr.zeros(mi.BSDFPtr, max(len(bsdfs), 1))
            live = [p for p, b in enumerate(bsdfs) if b is not None]
            if live:  # one scatter of all pointers as data (`render.batch._frame_table`)
                dr.scatter(table, mi.BSDFPtr([bsdfs[p] for p in live]), mi.UInt32(live))
            dr.make_opaque(table)
            self.parts = PartTable(bsdfs, table)

        def set_batch(self, table: FrameTable | None) -> None:
            """Batched frames (`render.batch`): lights and materials per frame from `table`, not from
            the scene's emitters and shapes (None: back to one frame per launch)."""
            self.batch = table

        def _bsdf(self, si, ray, active):
            """The BSDF at `si`: the shape's own, or its face's part's in a pooled scene."""
            if self.parts is None:
                return si.bsdf(ray)
            part = mi.UInt32(si.shape.eval_attribute_1(PART_ATTRIBUTE, si, active))
            return dr.gather(mi.BSDFPtr, self.parts.table, part, active & si.is_valid())

        def aov_names(self):
            return [c for e in self.emitter_ids for c in channel_names(e, self.n_channels)]

        def to_string(self):
            return (f"MultiLightIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}, "
                    f"emitters={self.emitter_ids}]")

        # ---- the estimator
        def _emitters(self, scene):
            by_id = {e.id(): e for e in scene.emitters()}
            missing = [e for e in self.emitter_ids if e not in by_id]
            if missing:
                raise RuntimeError(f"{PLUGIN_NAME}: emitters not found in the scene: {missing}")
            ems = [by_id[e] for e in self.emitter_ids]
            delta = [mi.has_flag(e.flags(), mi.EmitterFlags.Delta) for e in ems]
            infinite = [mi.has_flag(e.flags(), mi.EmitterFlags.Infinite) for e in ems]
            bad = [self.emitter_ids[i] for i in range(len(ems)) if not (delta[i] or infinite[i])]
            if bad:
                raise ValueError(f"{PLUGIN_NAME}: only delta lights and environment emitters are supported, "
                                 f"not {bad}")
            env = [i for i in range(len(ems)) if infinite[i] and not delta[i]]  # directional is infinite too
            if len(env) > 1:
                raise ValueError(f"{PLUGIN_NAME}: at most one environment emitter, got {len(env)}")
            return ems, delta, infinite, (env[0] if env else None)

        def sample(self, scene, sampler, ray, medium=None, active=True):
            if self.batch is not None:
                return self._sample_batch(scene, sampler, ray, active)
            ems, delta, infinite, env = self._emitters(scene)
            n = len(ems)
            spectral = bool(mi.is_spectral)
            if spectral and set(self.tables) != set(self.emitter_ids):
                raise RuntimeError(f"{PLUGIN_NAME}: spectral variants need set_bands() before rendering")
            # Groups share a throughput and wavelengths: all emitters in RGB, one per emitter in spectral.
            groups = [[e] for e in range(n)] if spectral else [list(range(n))]
            group_of = {e: g for g, members in enumerate(groups) for e in members}
            lead = group_of[env] if env is not None else 0  # its BSDF sample steers the path
            wavelengths, lane_w = [None] * len(groups), [None] * len(groups)
            if spectral:
                for g, (e,) in enumerate(groups):
                    wavelengths[g], lane_w[g] = _sample_wavelengths(mi, self.tables[self.emitter_ids[e]],
                                                                    sampler.next_1d(active))
            # Light-only groups need their throughput past the first vertex only if there is a second one.
            continues = self.max_depth > 2
            update_group = [g == lead or continues for g in range(len(groups))]
            needs_bsdf_sample = env is not None or continues
            ctx = mi.BSDFContext()

            def body(st: PathState) -> tuple[PathState]:
                sampler, ray, depth, active = st.sampler, st.ray, st.depth, st.active
                prev_si, prev_pdf, prev_delta = st.prev_si, st.prev_pdf, st.prev_delta
                si = scene.ray_intersect(ray, mi.RayFlags.All, depth == 0, active)
                acc = list(st.acc)
                beta = list(st.beta)
                # ---- environment hit by the previous BSDF sample (MIS against env sampling)
                if env is not None:
                    hit = active & ~si.is_valid()
                    if self.hide_emitters:
                        hit &= depth > 0
                    si_e = _with_wavelengths(mi, si, wavelengths[group_of[env]])
                    ds = dr.zeros(mi.DirectionSample3f)  # the env's pdf needs only the direction
                    ds.d = -si.wi  # an escaped ray's wi is -ray.d (world)
                    em_pdf = dr.select(prev_delta, 0.0, ems[env].pdf_direction(prev_si, ds, hit & ~prev_delta))
                    le = ems[env].eval(si_e, hit & (prev_pdf > 0)) * _mis_weight(prev_pdf, em_pdf)
                    acc[env] = dr.select(hit, acc[env] + beta[group_of[env]] * le, acc[env])

                active_next = active & (depth + 1 < self.max_depth) & si.is_valid()
                bsdf = self._bsdf(si, ray, active)
                flags = bsdf.flags()
                active_em = active_next & mi.has_flag(flags, mi.BSDFFlags.Smooth)
                transmits = mi.has_flag(flags, mi.BSDFFlags.Transmission)
                # ---- next-event estimation: every emitter, one shadow ray each
                # One 2D sample per vertex, as Mitsuba's `path` draws for its emitter sample (used by the
                # environment; delta lights ignore it): with the same seed, each light's image then uses
                # the same random numbers as its per-light render (RGB `path`: identical up to rounding).
                u_em = sampler.next_2d()
                si_g = [_with_wavelengths(mi, si, wavelengths[g]) for g in range(len(groups))]
                for e in range(n):
                    s = si_g[group_of[e]]
                    ds, em_w = ems[e].sample_direction(s, mi.Point2f(0.5, 0.5) if delta[e] else u_em, active_em)
                    ok = active_em & (ds.pdf != 0.0)
                    # A reflecting BSDF is 0 for light below the shading horizon: skip the shadow ray.
                    ok &= (mi.Frame3f.cos_theta(si.to_local(ds.d)) > 0) | transmits
                    # Directional and environment: a ray to infinity (their ds.p depends on the scene's
                    # bounding sphere, a per-scene literal that would recompile the kernel every scene).
                    shadow = si.spawn_ray(ds.d) if infinite[e] else si.spawn_ray_to(ds.p)
                    ok &= ~scene.ray_test(shadow, ok)
                    wo = si.to_local(ds.d)
                    if self.anisotropy[e] and delta[e] and not infinite[e]:
                        # an LED: intensity x cos^mu of the angle between its axis (toward the origin) and
                        # the direction to this point, cos = ds.d . p/|p| (ds.d points from here to the LED)
                        cos_axis = dr.dot(ds.d, dr.normalize(mi.Vector3f(ds.p)))
                        em_w = em_w * dr.power(dr.maximum(cos_axis, 0.0), self.anisotropy[e])
                    if delta[e]:
                        val = bsdf.eval(ctx, s, wo, ok)
                        mis = mi.Float(1.0)
                    else:
                        val, pdf = bsdf.eval_pdf(ctx, s, wo, ok)
                        mis = _mis_weight(ds.pdf, pdf)
                    acc[e] = dr.select(ok, acc[e] + beta[group_of[e]] * val * em_w * mis, acc[e])

                st.valid_ray = st.valid_ray | (active & si.is_valid())
                st.beta, st.acc = beta, acc
                if not needs_bsdf_sample:
                    st.active = active & False
                    return (st,)
                # ---- BSDF sampling: the lead group picks the direction; the others reuse its random numbers
                u1, u2 = sampler.next_1d(), sampler.next_2d()
                bs, w_lead = bsdf.sample(ctx, si_g[lead], u1, u2, active_next)
                for g in range(len(groups)):
                    if g == lead:
                        beta[g] = beta[g] * w_lead
                    elif update_group[g]:
                        beta[g] = beta[g] * bsdf.sample(ctx, si_g[g], u1, u2, active_next)[1]
                st.ray = si.spawn_ray(si.to_world(bs.wo))
                st.eta = eta = st.eta * bs.eta
                st.prev_si = mi.Interaction3f(si.t, si.time, si.wavelengths, si.p, si.n)
                st.prev_pdf = bs.pdf
                st.prev_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
                # ---- Russian roulette on the largest throughput of any group (one decision per path)
                depth = dr.select(si.is_valid(), depth + 1, depth)
                beta_max = dr.max(mi.unpolarized_spectrum(beta[0]))
                for g in range(1, len(groups)):
                    if update_group[g]:
                        beta_max = dr.maximum(beta_max, dr.max(mi.unpolarized_spectrum(beta[g])))
                rr_prob = dr.minimum(beta_max * eta * eta, 0.95)
                rr_active = depth >= self.rr_depth
                rr_continue = sampler.next_1d() < rr_prob
                st.beta = [dr.select(rr_active, b / rr_prob, b) for b in beta]
                st.depth = depth
                st.active = active_next & (~rr_active | rr_continue) & (beta_max != 0.0)
                return (st,)

            # as Mitsuba's `path`: a camera ray that escapes counts only if the environment is visible
            start = PathState(sampler=sampler, ray=mi.Ray3f(ray), depth=mi.UInt32(0), active=mi.Bool(active),
                              valid_ray=mi.Bool(not self.hide_emitters and env is not None), eta=mi.Float(1.0),
                              prev_si=dr.zeros(mi.Interaction3f), prev_pdf=mi.Float(1.0), prev_delta=mi.Bool(True),
                              beta=[mi.Spectrum(1.0) for _ in groups], acc=[mi.Spectrum(0.0) for _ in range(n)])
            (end,) = dr.while_loop(state=(start,), cond=lambda st: st.active, body=body, labels=("path",),
                                   label=PLUGIN_NAME)
            valid_ray, acc = end.valid_ray, end.acc
            aovs = []
            for e in range(n):
                if spectral:
                    g = group_of[e]
                    a = mi.unpolarized_spectrum(acc[e])
                    rgb = [dr.sum(a * lane_w[g][i]) for i in range(self.n_channels)]
                else:
                    rgb = [acc[e][i] for i in range(3)]
                aovs.extend(_kept(valid_ray, c) for c in rgb)
            if spectral:  # the film's own channels are not used: camera channels are the AOVs
                main = mi.Spectrum(0.0)
            else:
                main = mi.Spectrum(0.0)
                for e in range(n):
                    main = main + acc[e]
                main = _kept(valid_ray, main)
            return main, valid_ray, aovs

        def _sample_batch(self, scene, sampler, ray, active):
            """`sample` for batched frames (directional or point lights from the frame table, no
            environment): the same estimator -- every light at every vertex, BSDF-sampled bounces,
            Russian roulette -- with the frame's slot read at the camera ray's hit (`FrameTable`)
            and every ray after the camera's limited to the table's reach.  Spectral variants: as
            `sample`, one group per light (its own wavelengths from its bands and its own throughput;
            the first light's BSDF sample steers the path), the table's light value a scale on the
            light's flat unit emission."""
            tb = self.batch
            K, B, P = tb.n_lights, tb.n_frames, tb.part_stride
            continues = self.max_depth > 2
            ctx = mi.BSDFContext()
            spectral = bool(mi.is_spectral)
            G = K if spectral else 1  # throughput groups
            wavelengths, lane_w = [None], None
            if spectral:
                if set(self.tables) != set(self.emitter_ids):
                    raise RuntimeError(f"{PLUGIN_NAME}: spectral variants need set_bands() before rendering")
                drawn = [_sample_wavelengths(mi, self.tables[self.emitter_ids[k]], sampler.next_1d(active))
                         for k in range(K)]
                wavelengths, lane_w = [w for w, _ in drawn], [lw for _, lw in drawn]

            def body(st: BatchPathState) -> tuple[BatchPathState]:
                sampler, ray, depth, active = st.sampler, st.ray, st.depth, st.active
                si = scene.ray_intersect(ray, mi.RayFlags.All, depth == 0, active)
                hit = active & si.is_valid()
                # the camera ray: its slot from how far its origin is from the centre of the cell it hit
                # (orthographic), or from that cell (perspective)
                ci, cj = dr.round(si.p.y / tb.spacing), dr.round(si.p.z / tb.spacing)
                centre = mi.Point3f(0.0, ci * tb.spacing, cj * tb.spacing)
                if tb.cell_slot is None:
                    b = dr.round((dr.dot(centre - ray.o, ray.d) - tb.distance) / tb.step)
                    first = mi.UInt32(dr.clip(b, 0.0, float(B - 1)))
                else:
                    half, n_cells = tb.lattice // 2, tb.lattice * tb.lattice
                    cell = mi.UInt32(dr.clip((ci + half) * tb.lattice + cj + half, 0.0, float(n_cells - 1)))
                    first = dr.gather(mi.UInt32, tb.cell_slot, cell, hit & (depth == 0))
                slot = dr.select(depth == 0, first, st.slot)
                part = dr.gather(mi.UInt32, tb.face_part, slot * tb.face_stride + si.prim_index, hit)
                bsdf = dr.gather(mi.BSDFPtr, tb.bsdfs, slot * P + part, hit)
                acc, beta = list(st.acc), list(st.beta)
                si_g = [_with_wavelengths(mi, si, wavelengths[g]) for g in range(G)]
                active_next = active & (depth + 1 < self.max_depth) & si.is_valid()
                flags = bsdf.flags()
                active_em = active_next & mi.has_flag(flags, mi.BSDFFlags.Smooth)
                transmits = mi.has_flag(flags, mi.BSDFFlags.Transmission)
                sampler.next_2d()  # drawn as the unbatched path draws its emitter sample (unused by delta lights)
                for k in range(K):
                    i = slot * K + k
                    d = mi.Vector3f(*(dr.gather(mi.Float, c, i, active_em) for c in tb.light_d))
                    if spectral:  # the scale of the light's flat unit emission
                        e = dr.gather(mi.Float, tb.light_e[0], i, active_em)
                    else:
                        e = mi.Color3f(*(dr.gather(mi.Float, c, i, active_em) for c in tb.light_e))
                    if tb.point:  # as Mitsuba's `point`: intensity / r^2 toward the light's position
                        at = d  # about the cell's centre, object frame
                        to = centre + at - si.p
                        r2 = dr.squared_norm(to)
                        d, e = to * dr.rsqrt(r2), e * dr.rcp(r2)
                        shadow = si.spawn_ray_to(centre + at)
                        if self.anisotropy[k]:  # an LED: x cos^mu of the angle off its axis (`sample`)
                            e = e * dr.power(dr.maximum(dr.dot(d, dr.normalize(at)), 0.0), self.anisotropy[k])
                        shadow.maxt = dr.minimum(shadow.maxt, tb.reach)
                    else:
                        shadow = si.spawn_ray(d)
                        shadow.maxt = tb.reach
                    wo = si.to_local(d)
                    ok = active_em & ((mi.Frame3f.cos_theta(wo) > 0) | transmits)
                    ok &= ~scene.ray_test(shadow, ok)
                    g = k if spectral else 0
                    val = bsdf.eval(ctx, si_g[g], wo, ok)
                    acc[k] = dr.select(ok, acc[k] + beta[g] * val * e, acc[k])
                st.valid_ray = st.valid_ray | hit
                st.slot = slot
                st.acc = acc
                if not continues:
                    st.active = active & False
                    return (st,)
                u1, u2 = sampler.next_1d(), sampler.next_2d()
                bs, w = bsdf.sample(ctx, si_g[0], u1, u2, active_next)
                beta[0] = beta[0] * w
                for g in range(1, G):  # the other groups reuse its random numbers (`sample`)
                    beta[g] = beta[g] * bsdf.sample(ctx, si_g[g], u1, u2, active_next)[1]
                nxt = si.spawn_ray(si.to_world(bs.wo))
                nxt.maxt = tb.reach
                st.ray = nxt
                st.eta = eta = st.eta * bs.eta
                depth = dr.select(si.is_valid(), depth + 1, depth)
                beta_max = dr.max(mi.unpolarized_spectrum(beta[0]))
                for g in range(1, G):
                    beta_max = dr.maximum(beta_max, dr.max(mi.unpolarized_spectrum(beta[g])))
                rr_prob = dr.minimum(beta_max * eta * eta, 0.95)
                rr_active = depth >= self.rr_depth
                rr_continue = sampler.next_1d() < rr_prob
                st.beta = [dr.select(rr_active, b / rr_prob, b) for b in beta]
                st.depth = depth
                st.active = active_next & (~rr_active | rr_continue) & (beta_max != 0.0)
                return (st,)

            start = BatchPathState(sampler=sampler, ray=mi.Ray3f(ray), depth=mi.UInt32(0), active=mi.Bool(active),
                                   valid_ray=mi.Bool(False), eta=mi.Float(1.0), slot=mi.UInt32(0),
                                   beta=[mi.Spectrum(1.0) for _ in range(G)], acc=[mi.Spectrum(0.0) for _ in range(K)])
            (end,) = dr.while_loop(state=(start,), cond=lambda st: st.active, body=body, labels=("path",),
                                   label=PLUGIN_NAME + "_batch")
            aovs, main = [], mi.Spectrum(0.0)
            if spectral:  # camera channels are the AOVs (`sample`); the film's own channels stay 0
                for k in range(K):
                    a = mi.unpolarized_spectrum(end.acc[k])
                    aovs.extend(_kept(end.valid_ray, dr.sum(a * lane_w[k][i])) for i in range(self.n_channels))
                return main, end.valid_ray, aovs
            for k in range(K):
                aovs.extend(_kept(end.valid_ray, end.acc[k][c]) for c in range(3))
                main = main + end.acc[k]
            return _kept(end.valid_ray, main), end.valid_ray, aovs

    return MultiLightIntegrator


def register(variant: str | None = None) -> str:
    """Register `msps_multilight` for the current (or given, must be current) variant; idempotent."""
    return register_plugin("integrator", PLUGIN_NAME, _plugin_class, _REGISTERED, variant)


_REGISTERED: set[str] = set()


def read_emitter_images(image, aov_names: Sequence[str], emitter_ids: Sequence[str]) -> np.ndarray:
    """Every emitter's image, read by AOV channel name from the developed film (the tensor `mi.render`
    returns: the film's base channels, then `aov_names`), as ONE (K, H, W, C) float32 array (image k =
    emitter k; C = 3, or M when the integrator wrote M != 3 camera channels `<id>.C0 ..`).
    Why the tensor and not `film.bitmap()`: the same float32 values (tested), without developing the
    film twice (with 96 lights a bitmap is two more 291-channel copies, ~50 MB of a worker's peak); and
    one block: each extra copy of the per-light images is 19 MB."""
    data = np.array(image, dtype=np.float32, copy=False)
    aovs = list(aov_names)
    base = data.shape[-1] - len(aovs)
    if base < 0:
        raise RuntimeError(f"film has {data.shape[-1]} channels, fewer than the integrator's {len(aovs)} AOVs")
    names = [f"_base{i}" for i in range(base)] + aovs
    cols = []
    for e in emitter_ids:
        m = 0
        while f"{e}.C{m}" in names:
            m += 1
        try:
            cols.append([names.index(c) for c in (channel_names(e, m) if m and m != 3 else channel_names(e))])
        except ValueError:
            raise RuntimeError(f"film has no channels for emitter '{e}' (channels: {aovs})") from None
    if len({len(c) for c in cols}) > 1:
        raise RuntimeError(f"emitters wrote different numbers of channels: {[len(c) for c in cols]}")
    out = np.empty((len(cols),) + data.shape[:2] + (len(cols[0]) if cols else 3,), np.float32)
    for k, idx in enumerate(cols):
        out[k] = data[..., idx]
    return out
