"""Textures on meshes: per-vertex appearance attributes and the BSDF inputs that read them.

Why vertex attributes (Mitsuba's `mesh_attribute` texture) and not a Python
texture plugin: attribute buffers are data, so every textured scene shares the
compiled kernels (a per-scene texture parameter in a Python plugin would be a
kernel literal), and the ground truth reads the very same interpolated values
back with `Shape.eval_attribute` (`render.ground_truth.appearance_truth`).  The
price is resolution: a texture is sampled at the vertices, so textured meshes
are first subdivided until no edge is longer than `TextureSpec.max_edge`
(default 0.03, ~3.7 px at 256 px; `subdivide_to_edge`).

Every part mesh carries the three attributes (constant where the part is not
textured), so the ground truth can evaluate them on any hit:
  vertex_albedo (3): diffuse albedo (0 where the material has none: measured, conductor)
  vertex_weight (1): weight of the second material of a measured blend (0 elsewhere)
  vertex_roughness (1): roughness/alpha where a texture drives it
"""
from __future__ import annotations

import numpy as np

from msps_render.scene.geometry import TriMesh
from msps_render.scene.spec import MaterialSpec
from msps_render.scene.textures import texture_fields

ALBEDO_PARAM = {"diffuse": "reflectance", "plastic": "diffuse_reflectance",
                "roughplastic": "diffuse_reflectance", "principled": "base_color"}
ROUGHNESS_PARAM = {"roughconductor": "alpha", "principled": "roughness"}  # texturable in Mitsuba
ALBEDO, WEIGHT, ROUGHNESS = "vertex_albedo", "vertex_weight", "vertex_roughness"
MAX_FACES = 320_000  # subdivision stops before a mesh exceeds this (memory, BVH time)


def constant_albedo(m: MaterialSpec) -> tuple[float, float, float]:
    """The uniform diffuse albedo of a material (0 where it has none: measured, conductors)."""
    key = ALBEDO_PARAM.get(m.kind)
    v = m.params.get(key, 0.0) if key else 0.0
    return (float(v),) * 3 if isinstance(v, (int, float)) else tuple(float(x) for x in v)


PLUGIN_NAME = "msps_attribute"
_REGISTERED: set[str] = set()


def _plugin_class(variant: str):
    import drjit as dr
    import mitsuba as mi

    class AttributeTexture(mi.Texture):
        """Mitsuba's `mesh_attribute` lookup with a `mean()`: plastic/roughplastic ask their
        diffuse texture for its mean when built (for their sampling weight) and the built-in
        plugin has none.  The mean is a fixed 0.5: a per-scene value would be a kernel literal,
        and the sampling weight changes noise only, never the expectation."""

        def __init__(self, props):
            super().__init__(props)
            self.name = props["name"]
            self.channels = int(props["channels"]) if "channels" in props else 3

        def eval(self, si, active=True):
            if self.channels == 1:
                return mi.Color3f(si.shape.eval_attribute_1(self.name, si, active))
            return mi.Color3f(si.shape.eval_attribute_3(self.name, si, active))

        def eval_1(self, si, active=True):
            if self.channels == 1:
                return si.shape.eval_attribute_1(self.name, si, active)
            return dr.mean(si.shape.eval_attribute_3(self.name, si, active))

        def eval_3(self, si, active=True):
            return self.eval(si, active)

        def mean(self):
            return 0.5

        def max(self):
            return 1.0

        def is_spatially_varying(self):
            return True

        def traverse(self, callback):
            pass

        def parameters_changed(self, keys):
            pass

        def to_string(self):
            return f"AttributeTexture[name='{self.name}', channels={self.channels}]"

    return AttributeTexture


def attribute(name: str, channels: int = 3) -> dict:
    """A texture that reads the mesh attribute `name` (interpolated at the hit point)."""
    from msps_render.render.variant import register_plugin

    register_plugin("texture", PLUGIN_NAME, _plugin_class, _REGISTERED)
    return {"type": PLUGIN_NAME, "name": name, "channels": channels}


def textured_bsdf(m: MaterialSpec, d: dict) -> dict:
    """The BSDF dict `d` of material m with its textured inputs reading the mesh attributes."""
    if m.texture is None:
        return d
    d = dict(d)
    if m.kind in ALBEDO_PARAM:
        d[ALBEDO_PARAM[m.kind]] = attribute(ALBEDO)
    if m.texture.roughness is not None and m.kind in ROUGHNESS_PARAM:
        d[ROUGHNESS_PARAM[m.kind]] = attribute(ROUGHNESS, 1)
    return d


def vertex_attributes(m: MaterialSpec, points: np.ndarray, normals: np.ndarray,
                      uv: np.ndarray | None) -> dict[str, np.ndarray]:
    """The three attributes of one part's vertices (object-frame points/normals)."""
    V = len(points)
    albedo = np.tile(np.asarray(constant_albedo(m), np.float32), (V, 1))
    weight = np.zeros((V, 1), np.float32)
    rough = np.zeros((V, 1), np.float32)
    if m.texture is not None:
        rgb, w = texture_fields(m.texture, points, normals, uv)
        if m.kind in ALBEDO_PARAM:
            albedo = rgb
        if m.blend is not None:
            weight = w[:, None]
        if m.texture.roughness is not None:
            lo, hi = m.texture.roughness
            rough = (lo + (hi - lo) * w)[:, None].astype(np.float32)
    return {ALBEDO: albedo, WEIGHT: weight, ROUGHNESS: rough}


def _split_pass(v: np.ndarray, f: np.ndarray, attrs: dict, max_edge: float):
    """One crack-free refinement pass: every edge longer than max_edge gets its midpoint (shared
    by both faces on it), and each face is re-triangulated by how many of its edges were split
    (1 -> 2, 2 -> 3, 3 -> 4 triangles, winding kept).  Returns (v, f, attrs, any split)."""
    F = len(f)
    i, j = f.reshape(-1), f[:, [1, 2, 0]].reshape(-1)  # edge k of face t is row 3t + k
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    long_edge = np.linalg.norm(v[i] - v[j], axis=1) > max_edge
    if not long_edge.any():
        return v, f, attrs, False
    key = lo[long_edge] * len(v) + hi[long_edge]  # one int64 per undirected edge: fast unique
    uniq, inv = np.unique(key, return_inverse=True)
    mid_of_row = np.full(len(i), -1, np.int64)
    mid_of_row[long_edge] = len(v) + inv.reshape(-1)
    ends = np.stack([uniq // len(v), uniq % len(v)], 1)
    v = np.concatenate([v, 0.5 * (v[ends[:, 0]] + v[ends[:, 1]])])
    attrs = {k: np.concatenate([a, 0.5 * (a[ends[:, 0]] + a[ends[:, 1]])]) for k, a in attrs.items()}
    m = mid_of_row.reshape(F, 3)  # midpoint of edges (01, 12, 20) per face, -1 = kept
    split = m >= 0
    # rotate each face so its split edges come first: 1 split -> edge 01; 2 splits -> 01 and 12
    rot = np.zeros(F, np.int64)
    one, two = split.sum(1) == 1, split.sum(1) == 2
    rot[one] = np.argmax(split[one], 1)
    rot[two] = (np.argmin(split[two], 1) + 1) % 3
    idx = (np.arange(3)[None, :] + rot[:, None]) % 3
    fr = np.take_along_axis(f, idx, 1)
    mr = np.take_along_axis(m, idx, 1)
    a, b, c = fr.T
    m01, m12, m20 = mr.T
    n_split = split.sum(1)
    out = [fr[n_split == 0]]
    s1 = n_split == 1
    out += [np.stack([a, m01, c], 1)[s1], np.stack([m01, b, c], 1)[s1]]
    s2 = n_split == 2
    out += [np.stack([a, m01, m12], 1)[s2], np.stack([m01, b, m12], 1)[s2], np.stack([a, m12, c], 1)[s2]]
    s3 = n_split == 3
    out += [np.stack([a, m01, m20], 1)[s3], np.stack([m01, b, m12], 1)[s3], np.stack([m20, m12, c], 1)[s3],
            np.stack([m01, m12, m20], 1)[s3]]
    return v, np.concatenate(out), attrs, True


def subdivide_to_edge(mesh: TriMesh, max_edge: float, max_faces: int = MAX_FACES) -> TriMesh:
    """Split long edges until none is longer than max_edge (or the mesh would pass max_faces).

    Only long edges are split (a dense scan keeps its small triangles; a prism's big faces get
    small ones), each at its midpoint shared by both faces, so no crack opens; normals and UVs
    are interpolated at the midpoints (normals renormalised)."""
    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    attrs = {"n": np.asarray(mesh.normals, np.float64)}
    if mesh.uv is not None:
        attrs["uv"] = np.asarray(mesh.uv, np.float64)
    while len(f) < max_faces:
        v2, f2, attrs2, changed = _split_pass(v, f, attrs, max_edge)
        if not changed or len(f2) > max_faces:
            break
        v, f, attrs = v2, f2, attrs2
    n = attrs["n"] / np.maximum(np.linalg.norm(attrs["n"], axis=1, keepdims=True), 1e-12)
    uv = attrs["uv"].astype(np.float32) if "uv" in attrs else None
    return TriMesh(v.astype(np.float32), f.astype(np.uint32), n.astype(np.float32), uv)
