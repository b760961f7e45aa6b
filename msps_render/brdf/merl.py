"""MERL measured-BRDF tables: binary read/write and the reference nearest-bin lookup.

The MERL format (Matusik et al. 2003, `BRDFRead.cpp`): a header of three int32
(90, 90, 180), then 3 x 1,458,000 float64 (R block, G block, B block) indexed
``[theta_h, theta_d, phi_d]``; the stored raw values are multiplied by
1/1500, 1.15/1500 and 1.66/1500 to give the BRDF (1/sr).  theta_h uses a
square-root (non-linear) bin mapping, theta_d and phi_d are linear, and phi_d
is folded to [0, pi) by reciprocity.

This module is pure numpy (no Mitsuba): it is used for analysis, table
generation and as the reference the Mitsuba plugin is tested against.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from msps_render.atomic import atomic_write, save_array
from msps_render.errors import InputError

RES_THETA_H = 90
RES_THETA_D = 90
RES_PHI_D = 360  # MERL's constant; the table stores half of it (reciprocity)
DIMS = (RES_THETA_H, RES_THETA_D, RES_PHI_D // 2)
N_BINS = RES_THETA_H * RES_THETA_D * RES_PHI_D // 2  # 1,458,000 per channel
SCALE = np.array([1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0])
HEADER_BYTES = 12
FILE_BYTES = HEADER_BYTES + 3 * N_BINS * 8  # 34,992,012


@dataclass(frozen=True)
class MerlTable:
    """A loaded table: `rgb` has shape (3, 90, 90, 180), BRDF values in 1/sr (scale applied).

    `n_negative` / `n_nonfinite` count entries of the file that were below 0
    (MERL's "missing / below horizon" markers, e.g. -1 raw) or NaN/inf; both are
    replaced by 0 in `rgb`, as the reference renderer treats them as no reflection.
    """

    rgb: np.ndarray
    path: str = ""
    n_negative: int = 0
    n_nonfinite: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def nbytes(self) -> int:
        return int(self.rgb.nbytes)


def read_merl(path: str | os.PathLike, dtype=np.float32) -> MerlTable:
    """Read and validate a MERL `.binary` file; raise `InputError` naming the file on any problem.

    float32 by default: rendering needs no more, and it halves the 35 MB per table.
    """
    p = Path(path)
    try:
        size = p.stat().st_size
    except OSError as e:
        raise InputError(p, f"cannot read MERL file ({e.strerror})") from None
    if p.is_dir():
        raise InputError(p, "is a directory, not a MERL .binary file")
    if size < HEADER_BYTES:
        raise InputError(p, f"truncated MERL file: {size} bytes, smaller than the 12-byte header")
    with open(p, "rb") as fh:
        header = np.frombuffer(fh.read(HEADER_BYTES), dtype="<i4")
        dims = tuple(int(d) for d in header)
        if dims != DIMS:
            raise InputError(p, f"not a MERL BRDF: header dims {dims}, expected {DIMS}")
        if size != FILE_BYTES:
            kind = "truncated" if size < FILE_BYTES else "oversized"
            raise InputError(p, f"{kind} MERL file: {size} bytes, expected {FILE_BYTES} "
                                f"(12-byte header + 3 x {N_BINS} float64)")
        raw = np.frombuffer(fh.read(), dtype="<f8").reshape(3, *DIMS)
    finite = np.isfinite(raw)
    n_nonfinite = int(raw.size - np.count_nonzero(finite))
    if n_nonfinite == raw.size:
        raise InputError(p, "MERL file holds no finite values (not a BRDF table)")
    neg = raw < 0
    n_negative = int(np.count_nonzero(neg))
    vals = np.where(finite & ~neg, raw, 0.0) * SCALE[:, None, None, None]
    return MerlTable(rgb=vals.astype(dtype, copy=False), path=str(p), n_negative=n_negative,
                     n_nonfinite=n_nonfinite)


def write_merl(path: str | os.PathLike, rgb: np.ndarray) -> Path:
    """Write BRDF values (shape (3, 90, 90, 180), 1/sr) as a valid MERL file, atomically.

    The raw file values are `rgb / scale` in float64, so read(write(x)) == x to
    float64 rounding (one multiply and one divide: relative error <= 2**-52).
    """
    rgb = np.asarray(rgb, dtype=np.float64)
    if rgb.shape != (3, *DIMS):
        raise ValueError(f"MERL table must have shape {(3, *DIMS)}, got {rgb.shape}")
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(p, unique=True) as tmp, open(tmp, "wb") as fh:  # unique: workers may bake at once
        fh.write(np.asarray(DIMS, dtype="<i4").tobytes())
        fh.write((rgb / SCALE[:, None, None, None]).astype("<f8").tobytes())
    return p


# ------------------------------------------------------- baked float32 tables
BAKED_SUFFIX = ".npy"
BAKED_DTYPE = "<f4"
BAKED_SHAPE = (N_BINS, 3)  # interleaved RGB per bin: the renderer's device layout, so it maps the file as is


def _npy_header_bytes() -> int:
    import io

    b = io.BytesIO()
    np.lib.format.write_array_header_1_0(b, {"descr": BAKED_DTYPE, "fortran_order": False, "shape": BAKED_SHAPE})
    return b.tell()


BAKED_FILE_BYTES = _npy_header_bytes() + 3 * N_BINS * 4  # 17,496,128: half a MERL file


def write_baked(path: str | os.PathLike, rgb: np.ndarray) -> Path:
    """Write BRDF values (3, 90, 90, 180), 1/sr, as a float32 `.npy` table, atomically.

    Why float32: the renderer uses float32 tables anyway, so a float64 MERL file spends
    35 MB of disk per cached table on digits nobody reads.  Why interleaved (N_BINS, 3):
    it is the layout the BSDF gathers from, so the renderer memory-maps the file instead
    of reading and transposing it (`map_baked`).  Non-finite and negative values are
    stored as 0, as `read_merl` returns them.
    """
    rgb = np.asarray(rgb)
    if rgb.shape != (3, *DIMS):
        raise ValueError(f"MERL table must have shape {(3, *DIMS)}, got {rgb.shape}")
    vals = rgb.astype(BAKED_DTYPE)
    vals = np.where(np.isfinite(vals) & (vals >= 0), vals, np.float32(0.0))
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    return save_array(p, np.ascontiguousarray(vals.reshape(3, -1).T), unique=True)  # workers may bake at once


def map_baked(path: str | os.PathLike) -> np.ndarray:
    """The (N_BINS, 3) float32 values of a `write_baked` file, memory-mapped read-only.

    Why mapped: pages come from the OS page cache, shared by every process reading
    the same table, and loading costs no read or copy.  The cache files are only
    ever replaced by rename, never rewritten in place, so a mapping stays valid.
    `InputError` naming the file when it is not such a table.
    """
    p = Path(path)
    try:
        size = p.stat().st_size
        with open(p, "rb") as fh:
            major, _ = np.lib.format.read_magic(fh)
            read_header = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
            shape, fortran, dt = read_header(fh)
            offset = fh.tell()
    except OSError as e:
        raise InputError(p, f"cannot read baked BRDF table ({e.strerror or e})") from None
    except ValueError as e:
        raise InputError(p, f"not a baked BRDF table ({e})") from None
    if shape != BAKED_SHAPE or fortran or dt != np.dtype(BAKED_DTYPE):
        raise InputError(p, f"not a baked BRDF table: {dt} array of shape {shape}, expected {BAKED_DTYPE} "
                            f"{BAKED_SHAPE}")
    if size != offset + 3 * N_BINS * 4:
        raise InputError(p, f"{'truncated' if size < offset + 3 * N_BINS * 4 else 'oversized'} baked table: "
                            f"{size} bytes, expected {offset + 3 * N_BINS * 4}")
    return np.memmap(p, dtype=BAKED_DTYPE, mode="r", offset=offset, shape=BAKED_SHAPE)


def read_baked(path: str | os.PathLike, dtype=np.float32) -> MerlTable:
    """A `write_baked` file as a `MerlTable` (rgb (3, 90, 90, 180), read into memory)."""
    inter = np.array(map_baked(path), dtype=dtype)
    return MerlTable(rgb=inter.T.reshape(3, *DIMS), path=str(path))


def read_table(path: str | os.PathLike, dtype=np.float32) -> MerlTable:
    """Any measured table msps reads: a baked float32 `.npy` or a MERL `.binary`."""
    if str(path).endswith(BAKED_SUFFIX):
        return read_baked(path, dtype)
    return read_merl(path, dtype)


# ----------------------------------------------------------------- coordinates
def _rotate(v: np.ndarray, axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """MERL's `rotate_vector` (Rodrigues), vectorised over the leading axis of v/angle."""
    c = np.cos(angle)[..., None]
    s = np.sin(angle)[..., None]
    out = v * c
    temp = (v @ axis)[..., None] * (1.0 - c)
    out = out + axis * temp
    return out + np.cross(axis, v) * s


def half_diff_angles(wi: np.ndarray, wo: np.ndarray):
    """Rusinkiewicz (theta_h, phi_h, theta_d, phi_d) of unit directions, exactly as MERL computes them.

    `wi` is the vector rotated into the half-vector frame (MERL's "in").
    """
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    half = (wi + wo) / 2.0  # MERL forms the half vector before normalising its inputs
    half = half / np.linalg.norm(half, axis=-1, keepdims=True)
    wi = wi / np.linalg.norm(wi, axis=-1, keepdims=True)
    theta_h = np.arccos(half[..., 2])
    phi_h = np.arctan2(half[..., 1], half[..., 0])
    tmp = _rotate(wi, np.array([0.0, 0.0, 1.0]), -phi_h)
    diff = _rotate(tmp, np.array([0.0, 1.0, 0.0]), -theta_h)
    theta_d = np.arccos(diff[..., 2])
    phi_d = np.arctan2(diff[..., 1], diff[..., 0])
    return theta_h, phi_h, theta_d, phi_d


def theta_half_index(theta_h: np.ndarray) -> np.ndarray:
    """Non-linear theta_h bin: floor(sqrt(theta_h / (pi/2) * 90 * 90)), clamped; 0 for theta_h <= 0."""
    deg = theta_h / (math.pi / 2.0) * RES_THETA_H
    with np.errstate(invalid="ignore"):
        idx = np.sqrt(deg * RES_THETA_H)
    idx = np.where(theta_h <= 0.0, 0.0, idx)
    return np.clip(np.trunc(idx), 0, RES_THETA_H - 1).astype(np.int64)


def theta_diff_index(theta_d: np.ndarray) -> np.ndarray:
    idx = np.trunc(theta_d / (math.pi * 0.5) * RES_THETA_D)
    return np.clip(idx, 0, RES_THETA_D - 1).astype(np.int64)


def phi_diff_index(phi_d: np.ndarray) -> np.ndarray:
    """Fold phi_d by reciprocity (phi_d -> phi_d + pi when negative), then linear bins over [0, pi)."""
    phi = np.where(phi_d < 0.0, phi_d + math.pi, phi_d)
    idx = np.trunc(phi / math.pi * RES_PHI_D / 2)
    return np.clip(idx, 0, RES_PHI_D // 2 - 1).astype(np.int64)


def lookup_index(wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """Flat bin index (into one channel block) of direction pairs, MERL's `lookup_brdf_val` order."""
    th, _, td, pd = half_diff_angles(wi, wo)
    return (phi_diff_index(pd) + theta_diff_index(td) * (RES_PHI_D // 2)
            + theta_half_index(th) * (RES_PHI_D // 2) * RES_THETA_D)


def lookup(table: MerlTable | np.ndarray, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """BRDF values (..., 3) of direction pairs (..., 3) in the local frame (z = normal).

    Nearest bin, no interpolation, as the reference; pairs with either direction
    below the horizon give 0 (the reference prints "Below horizon" instead).
    """
    rgb = table.rgb if isinstance(table, MerlTable) else np.asarray(table)
    flat = rgb.reshape(3, -1)
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    idx = lookup_index(wi, wo)
    out = flat[:, idx].T.astype(np.float64)
    above = (wi[..., 2] > 0) & (wo[..., 2] > 0)
    return np.where(above[..., None], out, 0.0)


def spherical_to_vec(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    st = np.sin(theta)
    return np.stack([st * np.cos(phi), st * np.sin(phi), np.cos(theta)], axis=-1)


def bin_centres():
    """(theta_h, theta_d, phi_d) at the centre of every bin, each shape (90, 90, 180).

    theta_h bins are uniform in sqrt(theta_h), so the centre is ((k+0.5)/90)^2 * pi/2.
    """
    k = np.arange(RES_THETA_H) + 0.5
    th = (k / RES_THETA_H) ** 2 * (math.pi / 2)
    td = (np.arange(RES_THETA_D) + 0.5) / RES_THETA_D * (math.pi / 2)
    pd = (np.arange(RES_PHI_D // 2) + 0.5) / (RES_PHI_D // 2) * math.pi
    return np.meshgrid(th, td, pd, indexing="ij")


def half_diff_to_dirs(theta_h, theta_d, phi_d, phi_h=0.0):
    """Inverse of `half_diff_angles`: (wi, wo) unit vectors for given half/difference angles."""
    theta_h, theta_d, phi_d = np.broadcast_arrays(theta_h, theta_d, phi_d)
    phi_h = np.broadcast_to(phi_h, theta_h.shape)
    d = spherical_to_vec(theta_d, phi_d)
    y = np.array([0.0, 1.0, 0.0])
    z = np.array([0.0, 0.0, 1.0])
    wi = _rotate(_rotate(d, y, theta_h), z, phi_h)
    d_o = d * np.array([-1.0, -1.0, 1.0])  # wo is wi mirrored about the half vector
    wo = _rotate(_rotate(d_o, y, theta_h), z, phi_h)
    return wi, wo


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 / sRGB luminance of linear RGB along the first axis."""
    return 0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]


def fit_sampling_lobe(rgb: np.ndarray, max_theta_d_deg: float = 5.0) -> tuple[float, float]:
    """(alpha, weight) of the GGX lobe the plugin importance-samples, mixed with cosine.

    Fits luminance near the retro-reflection ridge (theta_d < 5 deg, averaged
    over phi_d) with kd + ks * D_ggx(theta_h; alpha) / (4 cos^2 theta_h), grid
    search over alpha with non-negative least squares in relative error.
    `weight` = ks / (ks + pi kd), the lobe's share of normal-incidence albedo,
    clipped to [0, 0.9] so diffuse energy is always cosine-sampled too. Only the
    sampling efficiency depends on this fit, never the estimate's expectation.
    """
    from scipy.optimize import nnls

    n_d = max(1, int(round(max_theta_d_deg / 90.0 * RES_THETA_D)))
    prof = luminance(np.asarray(rgb[:, :, :n_d, :], dtype=np.float64)).mean(axis=(1, 2))
    th = ((np.arange(RES_THETA_H) + 0.5) / RES_THETA_H) ** 2 * (math.pi / 2)
    keep = (th < math.radians(75.0)) & np.isfinite(prof)
    prof, th = prof[keep], th[keep]
    if prof.size == 0 or prof.max() <= 0:
        return 0.5, 0.0
    wts = 1.0 / np.maximum(prof, 1e-3 * prof.max())
    ch = np.cos(th)
    best = (math.inf, 0.5, 0.0, 0.0)
    for alpha in np.geomspace(0.005, 1.0, 64):
        a2 = alpha * alpha
        g = a2 / (math.pi * (ch * ch * (a2 - 1.0) + 1.0) ** 2) / (4.0 * ch * ch)
        A = np.stack([np.ones_like(th), g], axis=1) * wts[:, None]
        coef, res = nnls(A, prof * wts)
        if res < best[0]:
            best = (res, float(alpha), float(coef[0]), float(coef[1]))
    _, alpha, kd, ks = best
    weight = ks / max(ks + math.pi * kd, 1e-12)
    weight = 0.0 if weight < 0.02 else min(weight, 0.9)
    return alpha, float(weight)
