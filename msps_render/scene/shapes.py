"""Geometry: procedural blobby shapes, user meshes, and material parts.

Procedural shape families beyond blobs (detailed, creased, concave, thin,
composite) live in `msps_render.scene.families` (kind "procedural").

Everything here is numpy/trimesh; Mitsuba only sees the final arrays (meshes
go to it from memory, never through temp files).

Blobby shapes follow the spirit of the Blobby Shape Dataset: a sphere whose
radius is r(u) = 1 + Σ a_lm Y_lm(u) for low orders l.  Because r is a positive
function of direction, the surface is star-shaped about the origin and cannot
self-intersect; amplitudes decay with l so it stays smooth.
"""
from __future__ import annotations

from collections import OrderedDict
from pathlib import Path

import numpy as np

from msps_render.errors import InputError
from msps_render.scene.families import crease_normals, procedural_mesh
from msps_render.scene.geometry import (TriMesh, icosphere, icosphere_sh_basis, n_sh_coeffs,  # noqa: F401
                                        real_sh_basis, sample_blobby_coeffs, vertex_normals)
from msps_render.scene.primitives import PRIMITIVES, build_primitive, sample_primitive_params  # noqa: F401
from msps_render.scene.spec import ShapeSpec, SplitSpec

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")


# ------------------------------------------------------------ spherical harmonics
def _lmax_from_count(n: int) -> int:
    lmax = int(round(np.sqrt(n + 1))) - 1
    if n_sh_coeffs(lmax) != n:
        raise InputError("shape.sh_coeffs", f"{n} coefficients is not (lmax+1)^2-1 for any lmax")
    return lmax


def blobby_mesh(coeffs: tuple[float, ...], subdivisions: int = 5) -> tuple[np.ndarray, np.ndarray]:
    dirs, faces = icosphere(subdivisions)
    r = np.ones(len(dirs))
    if coeffs:
        B = icosphere_sh_basis(subdivisions, _lmax_from_count(len(coeffs)))
        r = r + B @ np.asarray(coeffs)
    # Keep radii positive (star-shaped => no self-intersection) with a soft floor.
    r = np.maximum(r, 0.35 + 0.05 * np.tanh(r))
    return dirs * r[:, None], faces


# ----------------------------------------------------------------- user meshes
def load_mesh_file(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a mesh with trimesh; reject files that do not give a usable triangle mesh."""
    v, f, _ = load_mesh_file_uv(path)
    return v, f


def load_mesh_file_uv(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """`load_mesh_file` plus the per-vertex UVs where the file has them (else None)."""
    import trimesh

    p = Path(path)
    if not p.is_file():
        raise InputError(p, "mesh file not found")
    if p.suffix.lower() not in MESH_SUFFIXES:
        raise InputError(p, f"unsupported mesh format '{p.suffix}' (supported: {', '.join(MESH_SUFFIXES)})")
    try:
        loaded = trimesh.load(str(p), force="mesh", process=False)
    except Exception as e:  # trimesh raises many types on garbage
        raise InputError(p, f"cannot parse mesh ({type(e).__name__}: {str(e)[:120]})") from None
    if isinstance(loaded, trimesh.Scene):  # empty scene => no geometry
        raise InputError(p, "mesh has no faces")
    v = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64)
    f = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int64)
    if f.size == 0 or v.size == 0:
        raise InputError(p, "mesh has no faces")
    if not np.isfinite(v).all():
        raise InputError(p, f"mesh has {int((~np.isfinite(v)).any(axis=1).sum())} vertices with NaN/inf coordinates")
    if f.min() < 0 or f.max() >= len(v):
        raise InputError(p, "mesh faces index vertices that do not exist")
    uv = getattr(getattr(loaded, "visual", None), "uv", None)
    uv = np.asarray(uv, np.float64) if uv is not None and len(uv) == len(v) else None
    return (*orient_outward(v, f), uv)


def mesh_has_uv(path: str | Path) -> bool:
    """Does the mesh file carry per-vertex texture coordinates?"""
    return load_mesh_file_uv(path)[2] is not None


def orient_outward(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Consistent winding with outward normals (why: Mitsuba BSDFs are one-sided,
    so an inward-wound mesh would render black while its normals look fine)."""
    import trimesh

    m = trimesh.Trimesh(v, f, process=False, validate=False)
    # Weld vertices split only by UV/normal seams so smooth normals do not crease there.
    m.merge_vertices(merge_tex=True, merge_norm=True)
    trimesh.repair.fix_winding(m)
    v = np.asarray(m.vertices, dtype=np.float64)
    faces = np.asarray(m.faces, dtype=np.int64)
    # Signed volume about the centroid: negative => wound inward (also a fair
    # heuristic for open meshes such as the teapot).
    c = v.mean(axis=0)
    a, b, d = v[faces[:, 0]] - c, v[faces[:, 1]] - c, v[faces[:, 2]] - c
    if np.einsum("ij,ij->i", a, np.cross(b, d)).sum() < 0:
        faces = faces[:, ::-1]
    return v, np.ascontiguousarray(faces)


def clean_faces(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Drop degenerate (zero-area or repeated-index) faces."""
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    area2 = np.linalg.norm(cross, axis=1)
    scale = max(float(np.ptp(v, axis=0).max()), 1e-12)
    ok = (area2 > 1e-12 * scale * scale) & (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    return f[ok]


def normalise(v: np.ndarray, radius: float = 1.0) -> np.ndarray:
    """Centre on the bounding-box centre and scale into a sphere of `radius`."""
    c = 0.5 * (v.min(axis=0) + v.max(axis=0))
    v = v - c
    r = float(np.linalg.norm(v, axis=1).max())
    return v * (radius / max(r, 1e-12))


def random_rotation(rng: np.random.Generator) -> tuple:
    """Uniform random rotation matrix (as nested tuples for SceneSpec)."""
    from scipy.spatial.transform import Rotation

    R = Rotation.random(random_state=rng).as_matrix()
    return tuple(tuple(float(x) for x in row) for row in R)


GENERATED_KINDS = ("blobby", "primitive", "procedural")  # pure functions of their parameters: cached


def canonical_mesh(shape: ShapeSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The mesh before its rotation (float64 vertices, int64 faces, UVs or None); generated shapes
    come from the per-process cache (read-only arrays)."""
    if shape.kind == "sphere":
        raise ValueError("the analytic sphere has no mesh; the renderer uses Mitsuba's sphere")
    if shape.kind in GENERATED_KINDS:
        return _canonical_cached(shape.kind, shape.name, tuple(shape.sh_coeffs), shape.subdivisions,
                                 tuple(shape.params.items()), float(shape.radius))
    return _canonical(shape)


def rotated_vertices(shape: ShapeSpec, v: np.ndarray) -> np.ndarray:
    """Canonical vertices in the camera/world frame (float64): world = object @ R.T."""
    return v @ np.asarray(shape.rotation, dtype=np.float64).T


def build_mesh(shape: ShapeSpec) -> TriMesh:
    """ShapeSpec -> triangle mesh in the camera/world frame, inside radius `shape.radius`."""
    v, f, uv = canonical_mesh(shape)
    v = rotated_vertices(shape, v)
    if shape.kind == "procedural":  # keep creases sharp: split vertices across sharp edges
        v, f, n = crease_normals(v, f)
    else:
        n = vertex_normals(v, f)
    return TriMesh(v.astype(np.float32), f.astype(np.uint32), n.astype(np.float32), uv)


def _canonical(shape: ShapeSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The mesh before its rotation: built, degenerate faces dropped, unused vertices removed,
    normalised into radius `shape.radius` (float64 vertices, int64 faces, float32 UVs or None)."""
    uv = None
    if shape.kind == "blobby":
        v, f = blobby_mesh(tuple(shape.sh_coeffs), shape.subdivisions)
    elif shape.kind == "mesh":
        v, f, uv = load_mesh_file_uv(shape.path)
    elif shape.kind == "primitive":
        v, f = orient_outward(*build_primitive(shape.name, dict(shape.params)))
    else:
        v, f = procedural_mesh(shape.name, dict(shape.params))
    f = clean_faces(v, f)
    if len(f) == 0:
        raise InputError(shape.path or shape.name, "mesh has only degenerate faces")
    used = np.unique(f)
    remap = np.full(len(v), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    v, f = v[used], remap[f]
    uv = uv[used].astype(np.float32) if uv is not None else None
    return normalise(v, shape.radius), f, uv


CANONICAL_CACHE_BYTES = 32 << 20  # canonical meshes kept per process (a paper-train blob is 0.7 MB)
_CANONICAL: OrderedDict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray | None]] = OrderedDict()


def _canonical_cached(kind: str, name: str, sh_coeffs: tuple, subdivisions: int, params: tuple,
                      radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """`_canonical` of a generated shape, kept per process: a corpus draws its objects from a small
    pool (paper-train: 9 blobs) and only the rotation changes from frame to frame, so the mesh
    before the rotation is built once per shape (the same arrays as building it again).  Least
    recently used meshes are dropped beyond `CANONICAL_CACHE_BYTES` (flat worker memory); mesh
    files are not cached (they may change on disk)."""
    key = (kind, name, sh_coeffs, subdivisions, params, radius)
    hit = _CANONICAL.get(key)
    if hit is not None:
        _CANONICAL.move_to_end(key)
        return hit
    shape = ShapeSpec(kind=kind, name=name, sh_coeffs=sh_coeffs, subdivisions=subdivisions,
                      params=dict(params), radius=radius)
    v, f, uv = _canonical(shape)
    for a in (v, f):
        a.setflags(write=False)
    _CANONICAL[key] = (v, f, uv)
    trim_canonical_cache(CANONICAL_CACHE_BYTES, keep=1)
    return v, f, uv


def trim_canonical_cache(max_bytes: int, keep: int = 0) -> None:
    """Drop least recently used canonical meshes until the cache holds at most `max_bytes` (or only
    `keep` meshes); `render/memory.py` shrinks it after frames of many lights."""
    while len(_CANONICAL) > keep and sum(a.nbytes for m in _CANONICAL.values() for a in m[:2]) > max_bytes:
        _CANONICAL.popitem(last=False)


# ------------------------------------------------------------------- parts
def face_parts(mesh: TriMesh, split: SplitSpec) -> np.ndarray:
    """Part index per face (int), spatially coherent by construction."""
    return split_faces(mesh.vertices, mesh.faces, split)


def part_pieces(faces: np.ndarray, parts: np.ndarray, n_vertices: int):
    """Each non-empty part p of a mesh as (p, used, local): the vertices its faces use (ascending) and its
    faces renumbered into them.  One Mitsuba shape (or one block of a batch's own mesh) per part, each
    with its own vertex copies: a part's material reads its own attribute values at them."""
    for p in range(int(parts.max()) + 1 if len(parts) else 0):
        f = faces[parts == p]
        if not len(f):
            continue
        seen = np.zeros(n_vertices, dtype=bool)  # = np.unique(f), in O(n)
        seen[f] = True
        used = np.flatnonzero(seen)
        remap = np.zeros(n_vertices, dtype=np.int64)
        remap[used] = np.arange(len(used))
        yield p, used, remap[f]


def split_faces(v: np.ndarray, f: np.ndarray, split: SplitSpec) -> np.ndarray:
    """`face_parts` of the mesh (v, f): vertices in the frame the split is defined in (the world)."""
    F = len(f)
    if split.kind == "none" or split.n_parts == 1:
        return np.zeros(F, dtype=np.int64)
    # face centroids: the float32 sum of the three corners in order, divided by 3 -- the same
    # operations `mesh.vertices[mesh.faces].mean(axis=1)` performs, without the (F, 3, 3) copy
    c = ((v[f[:, 0]] + v[f[:, 1]] + v[f[:, 2]]) / v.dtype.type(3)).astype(np.float64)
    if split.kind == "planes":
        nrm = np.asarray(split.normals, dtype=np.float64)
        off = np.asarray(split.offsets, dtype=np.float64)
        side = (c @ nrm.T > off[None, :]).astype(np.int64)
        # Binary code of the cells -> part ids; consecutive cells share a material cyclically.
        code = (side * (1 << np.arange(side.shape[1]))).sum(axis=1)
        return code % split.n_parts
    # field: bin a smooth SH field evaluated at the face direction into equal-area quantiles
    d = c / np.maximum(np.linalg.norm(c, axis=1, keepdims=True), 1e-12)
    coeffs = np.asarray(split.field_coeffs)
    vals = real_sh_basis(d, _lmax_from_count(len(coeffs))) @ coeffs
    edges = np.quantile(vals, np.linspace(0, 1, split.n_parts + 1)[1:-1])
    return np.searchsorted(edges, vals)


def sample_split(rng: np.random.Generator, n_parts: int, kind: str = "field") -> SplitSpec:
    if n_parts <= 1:
        return SplitSpec()
    if kind == "planes":
        k = max(1, int(np.ceil(np.log2(n_parts))))
        nrm = rng.normal(size=(k, 3))
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        off = rng.uniform(-0.3, 0.3, size=k)
        return SplitSpec(kind="planes", n_parts=n_parts, normals=tuple(tuple(map(float, x)) for x in nrm),
                         offsets=tuple(map(float, off)))
    coeffs = sample_blobby_coeffs(rng, lmax=3, amplitude=1.0)
    return SplitSpec(kind="field", n_parts=n_parts, field_coeffs=coeffs)
