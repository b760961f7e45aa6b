"""Mesh basics shared by the shape builders: `TriMesh`, icospheres, real spherical
harmonics, smooth vertex normals (numpy/trimesh only)."""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np


@dataclass(frozen=True)
class TriMesh:
    """Plain triangle mesh: float32 vertices/normals (V,3), uint32 faces (F,3)."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    uv: np.ndarray | None = None  # (V, 2) texture coordinates of a mesh file that has them


def real_sh_basis(dirs: np.ndarray, lmax: int, lmin: int = 1) -> np.ndarray:
    """Real spherical harmonics Y_lm(dirs) for lmin <= l <= lmax, shape (N, n_coeffs).

    Associated Legendre functions by the standard three-term recurrence (Condon-Shortley phase,
    as scipy's `sph_harm_y`, which this equals to ~1e-15; tests/test_scene.py): the part split
    evaluates it on every face of every frame, where scipy's per-(l, m) calls took ~35 ms."""
    from math import factorial, pi, sqrt

    d = np.asarray(dirs, dtype=np.float64)
    ct = np.clip(d[:, 2], -1.0, 1.0)
    st = np.sqrt(np.maximum(1.0 - ct * ct, 0.0))
    phi = np.arctan2(d[:, 1], d[:, 0])
    P: dict[tuple[int, int], np.ndarray] = {}
    pmm = np.ones_like(ct)
    for m in range(lmax + 1):
        if m > 0:
            pmm = -(2 * m - 1) * st * pmm
        P[m, m] = pmm
        if m + 1 <= lmax:
            P[m + 1, m] = (2 * m + 1) * ct * pmm
        for l in range(m + 2, lmax + 1):
            P[l, m] = ((2 * l - 1) * ct * P[l - 1, m] - (l + m - 1) * P[l - 2, m]) / (l - m)
    cols = []
    trig: dict[int, np.ndarray] = {}  # cos(a phi) for m = a > 0, sin(a phi) for m = -a: once per m
    for l in range(lmin, lmax + 1):
        for m in range(-l, l + 1):
            a = abs(m)
            norm = sqrt((2 * l + 1) / (4 * pi) * factorial(l - a) / factorial(l + a))
            if m == 0:
                cols.append(norm * P[l, 0])
            else:
                if m not in trig:
                    trig[m] = np.cos(a * phi) if m > 0 else np.sin(a * phi)
                cols.append(sqrt(2) * (-1) ** m * norm * P[l, a] * trig[m])
    return np.stack(cols, axis=1)


def n_sh_coeffs(lmax: int, lmin: int = 1) -> int:
    return (lmax + 1) ** 2 - lmin ** 2


def sample_blobby_coeffs(rng: np.random.Generator, lmax: int = 4, amplitude: float = 0.3) -> tuple[float, ...]:
    """Random SH coefficients with a 1/l^2 spectrum so the shape stays smooth."""
    c = []
    for l in range(1, lmax + 1):
        c.extend(rng.normal(0.0, amplitude / l ** 1.5, size=2 * l + 1))
    return tuple(float(v) for v in c)


@lru_cache(maxsize=8)
def icosphere(subdivisions: int):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)


@lru_cache(maxsize=8)
def icosphere_sh_basis(subdivisions: int, lmax: int) -> np.ndarray:
    """SH basis at the icosphere vertices: fixed per level, so computed once per process."""
    B = real_sh_basis(icosphere(subdivisions)[0], lmax)
    B.setflags(write=False)
    return B


def vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Area-weighted smooth vertex normals.

    Always recomputed, also for files that carry normals: formats disagree
    (STL has none, OBJ normals are often split at UV seams), and the ground
    truth must describe exactly the surface Mitsuba shades.
    """
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # length = 2*area
    if fn.dtype == np.float64:
        # per coordinate one float64 `bincount` over the corners in the order (corner 0 of every
        # face, then corner 1, then corner 2): the same additions in the same order as `np.add.at`
        # corner by corner, so bit-identical, and ~3x faster
        idx = np.asarray(f, dtype=np.intp).T.reshape(-1)
        n = np.empty_like(v)
        for c in range(v.shape[1]):
            n[:, c] = np.bincount(idx, weights=np.tile(fn[:, c], 3), minlength=len(v))
    else:  # bincount sums in float64: other dtypes keep their own accumulation
        n = np.zeros_like(v)
        for k in range(3):
            np.add.at(n, f[:, k], fn)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(ln > 0, ln, 1.0)
