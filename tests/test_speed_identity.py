"""Corpus speed (issue 21): the faster code paths give bit-identical results to the reference code.

Each test keeps the code as it was before the speed work (`_ref_*`, copied verbatim) and
compares its output with the current function byte for byte on real `paper-train` scenes:
mesh building (cached canonical mesh, `bincount` normals), the part split (centroids, SH
basis), the per-part mesh buffers and attributes, and the ground truth from one ray cast.
"""
from __future__ import annotations

from math import factorial, pi, sqrt

import numpy as np
import pytest

from msps_render.scene import geometry, shapes
from msps_render.scene.spec import SceneSpec


# ------------------------------------------------------------------ reference code (before)
def _ref_vertex_normals(v, f):
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(ln > 0, ln, 1.0)


def _ref_real_sh_basis(dirs, lmax, lmin=1):
    d = np.asarray(dirs, dtype=np.float64)
    ct = np.clip(d[:, 2], -1.0, 1.0)
    st = np.sqrt(np.maximum(1.0 - ct * ct, 0.0))
    phi = np.arctan2(d[:, 1], d[:, 0])
    P = {}
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
    for l in range(lmin, lmax + 1):
        for m in range(-l, l + 1):
            a = abs(m)
            norm = sqrt((2 * l + 1) / (4 * pi) * factorial(l - a) / factorial(l + a))
            if m == 0:
                cols.append(norm * P[l, 0])
            else:
                trig = np.cos(a * phi) if m > 0 else np.sin(a * phi)
                cols.append(sqrt(2) * (-1) ** m * norm * P[l, a] * trig)
    return np.stack(cols, axis=1)


def _ref_build_mesh(shape):
    v, f = shapes.blobby_mesh(tuple(shape.sh_coeffs), shape.subdivisions)
    f = shapes.clean_faces(v, f)
    used = np.unique(f)
    remap = np.full(len(v), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    v, f = v[used], remap[f]
    R = np.asarray(shape.rotation, dtype=np.float64)
    v = shapes.normalise(v, shape.radius) @ R.T
    n = _ref_vertex_normals(v, f)
    return geometry.TriMesh(v.astype(np.float32), f.astype(np.uint32), n.astype(np.float32), None)


def _ref_face_parts(mesh, split):
    c = mesh.vertices[mesh.faces].mean(axis=1).astype(np.float64)
    d = c / np.maximum(np.linalg.norm(c, axis=1, keepdims=True), 1e-12)
    coeffs = np.asarray(split.field_coeffs)
    vals = _ref_real_sh_basis(d, shapes._lmax_from_count(len(coeffs))) @ coeffs
    edges = np.quantile(vals, np.linspace(0, 1, split.n_parts + 1)[1:-1])
    return np.searchsorted(edges, vals)


def _ref_truth(mi, scene, spec):
    """ground_truth + appearance_truth as before: each array converted (and traced) on its own."""
    import drjit as dr

    from msps_render.render.textures import ALBEDO, WEIGHT

    W, H = spec.camera.width, spec.camera.height
    sensor = scene.sensors()[0]
    shapes_ = scene.shapes()
    part_of = [int(s.id()[4:]) if s.id().startswith("part") else -1 for s in shapes_]
    idx = dr.arange(mi.UInt32, W * H)
    pos = mi.Point2f((mi.Float(idx % W) + 0.5) / W, (mi.Float(idx // W) + 0.5) / H)
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(ray)
    valid = si.is_valid()
    n = si.sh_frame.n
    n = dr.select(dr.dot(n, ray.d) > 0, -n, n)
    ids = dr.reinterpret_array(mi.UInt32, si.shape)
    shape_ids = [int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0]) for s in shapes_]
    mask = np.array(valid, dtype=bool)
    normal = np.stack([np.array(n.x), np.array(n.y), np.array(n.z)], -1).astype(np.float64)
    depth = np.array(spec.camera.distance - si.p.z, dtype=np.float32)
    sid = np.array(ids)
    part = np.full(W * H, -1, dtype=np.int8)
    for s_id, p in zip(shape_ids, part_of):
        part[(sid == s_id) & mask] = p
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    normal[~mask] = 0.0
    depth[~mask] = 0.0
    si2 = scene.ray_intersect(sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))[0])
    v2 = si2.is_valid()
    a = si2.shape.eval_attribute_3(ALBEDO, si2, v2)
    w = si2.shape.eval_attribute_1(WEIGHT, si2, v2)
    albedo = np.stack([np.array(a.x), np.array(a.y), np.array(a.z)], -1)
    weight = np.array(w)
    off = ~np.array(v2, dtype=bool)
    albedo[off] = 0.0
    weight[off] = 0.0
    return (normal.reshape(H, W, 3).astype(np.float32), mask.reshape(H, W), depth.reshape(H, W),
            part.reshape(H, W), albedo.reshape(H, W, 3).astype(np.float32),
            weight.reshape(H, W).astype(np.float32))


# ------------------------------------------------------------------ scenes
@pytest.fixture(scope="module")
def paper_specs() -> list[SceneSpec]:
    """The 16 scenes of the first two `paper-train` shards (blobby, field split, 2-3 materials)."""
    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.plan import frame_rngs, frame_seed, plan
    from msps_render.scene.sample import sample_scene

    cfg = load_config("paper-train", ["dataset.n_shards=2"])
    fps = cfg.dataset.frames_per_shard
    return [sample_scene(cfg.scene, rng, seed=frame_seed(t, j), frame_index=t.shard_in_condition * fps + j)
            for t in plan(cfg) for j, rng in enumerate(frame_rngs(t, fps))]


def test_vertex_normals_bincount_equals_add_at():
    rng = np.random.default_rng(3)
    v = rng.normal(size=(500, 3))
    f = rng.integers(0, 500, size=(1500, 3))
    assert np.array_equal(geometry.vertex_normals(v, f), _ref_vertex_normals(v, f))
    v32 = v.astype(np.float32)  # float32 input keeps its float32 accumulation
    out = geometry.vertex_normals(v32, f)
    assert out.dtype == np.float32 and np.array_equal(out, _ref_vertex_normals(v32, f))


def test_real_sh_basis_equals_reference():
    rng = np.random.default_rng(4)
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for lmax in (1, 3, 4):
        assert np.array_equal(geometry.real_sh_basis(d, lmax), _ref_real_sh_basis(d, lmax))


def test_mesh_and_parts_bit_identical(paper_specs):
    shapes._CANONICAL.clear()
    built = []
    for rep in range(2):  # the second pass is served from the canonical-mesh cache
        for spec in paper_specs:
            new, ref = shapes.build_mesh(spec.shape), _ref_build_mesh(spec.shape)
            for name in ("vertices", "faces", "normals"):
                a, b = getattr(new, name), getattr(ref, name)
                assert a.dtype == b.dtype and np.array_equal(a, b), name
            assert np.array_equal(shapes.face_parts(new, spec.split), _ref_face_parts(ref, spec.split))
        built.append(len(shapes._CANONICAL))
    n_shapes = len({s.shape.name for s in paper_specs})
    assert built == [n_shapes, n_shapes] and n_shapes <= 9  # paper-train draws from 9 shapes


def test_canonical_cache_is_bounded(paper_specs, monkeypatch):
    shapes._CANONICAL.clear()
    one = shapes.build_mesh(paper_specs[0].shape)
    monkeypatch.setattr(shapes, "CANONICAL_CACHE_BYTES", 1.5 * (one.vertices.size * 8 + one.faces.size * 8))
    for spec in paper_specs:
        shapes.build_mesh(spec.shape)
    assert len(shapes._CANONICAL) == 1  # a second blob would pass the bound: the older one went


def test_cached_canonical_mesh_is_read_only(paper_specs):
    shape = paper_specs[0].shape
    args = (shape.kind, shape.name, tuple(shape.sh_coeffs), shape.subdivisions, tuple(shape.params.items()),
            float(shape.radius))
    v, f, _ = shapes._canonical_cached(*args)
    with pytest.raises(ValueError):
        v[0, 0] = 0.0
    assert shapes._canonical_cached(*args)[0] is v


def test_part_meshes_carry_the_same_buffers(rgb_variant, paper_specs):
    """Part meshes built with the O(n) vertex selection and list-fed attributes hold exactly the
    arrays of the reference construction (np.unique, drjit Float attributes)."""
    import mitsuba as mi

    from msps_render.render.scene_dict import _shapes
    from msps_render.render.textures import vertex_attributes

    for spec in paper_specs[:4]:
        mesh = shapes.build_mesh(spec.shape)
        parts = shapes.face_parts(mesh, spec.split)
        R = np.asarray(spec.shape.rotation, dtype=np.float64)
        built = _shapes(mi, spec)
        for key, m in built.items():
            p = int(key[4:])
            faces = mesh.faces[parts == p]
            used = np.unique(faces)
            remap = np.zeros(len(mesh.vertices), dtype=np.uint32)
            remap[used] = np.arange(len(used), dtype=np.uint32)
            params = mi.traverse(m)
            assert np.array_equal(np.array(params["vertex_positions"]), mesh.vertices[used].ravel())
            assert np.array_equal(np.array(params["faces"]), remap[faces].ravel())
            assert np.array_equal(np.array(params["vertex_normals"]), mesh.normals[used].ravel())
            attrs = vertex_attributes(spec.materials[p], mesh.vertices[used] @ R, mesh.normals[used] @ R, None)
            for name, a in attrs.items():
                assert np.array_equal(np.array(params[name]), a.astype(np.float32).ravel()), name


def test_frame_truth_equals_separate_casts(rgb_variant, paper_specs):
    """One ray cast with every output evaluated together == the per-array conversions of before."""
    import mitsuba as mi

    from msps_render.render.ground_truth import frame_truth
    from msps_render.render.scene_dict import build_scene_dict

    for spec in paper_specs[:4]:
        scene = mi.load_dict(build_scene_dict(spec, mi))
        new, ref = frame_truth(mi, scene, spec), _ref_truth(mi, scene, spec)
        for name, a, b in zip(("normal", "mask", "depth", "part", "albedo", "blend"), new, ref):
            assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b), name
        assert new[1].mean() > 0.2  # the object covers the frame: the comparison means something
