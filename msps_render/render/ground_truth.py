"""Exact ground truth of a loaded scene: normal, depth, mask and part id from one ray per pixel centre.

One ray through each pixel centre (`scene.ray_intersect`) through the same
sensor as the image, so the values are exact at the pixel centre and never
blended with the background (AOV integrators go through the pixel filter).
"""
from __future__ import annotations

import numpy as np

from msps_render.scene.spec import SceneSpec


def ground_truth(mi, scene, spec: SceneSpec):
    """Normal/depth/mask/part from one ray per pixel centre.

    Depth is z-depth: distance from the camera plane along the view axis.
    """
    import drjit as dr

    W, H = spec.camera.width, spec.camera.height
    sensor = scene.sensors()[0]
    shapes = scene.shapes()
    names = [s.id() for s in shapes]
    part_of = [int(n[4:]) if n.startswith("part") else -1 for n in names]
    if dr.is_jit_v(mi.Float):
        mask, normal, depth, part, _, _ = _cast_jit(mi, scene, spec, shapes, part_of, appearance=False)
    else:  # scalar variants: one ray at a time (slow but only a fallback)
        mask = np.zeros(W * H, bool)
        normal = np.zeros((W * H, 3))
        depth = np.zeros(W * H, np.float32)
        part = np.full(W * H, -1, dtype=np.int8)
        for i in range(W * H):
            x, y = i % W, i // W
            ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f((x + 0.5) / W, (y + 0.5) / H), mi.Point2f(0.5, 0.5))
            si = scene.ray_intersect(ray)
            if si.is_valid():
                n = si.sh_frame.n
                if dr.dot(n, ray.d) > 0:
                    n = -n
                mask[i] = True
                normal[i] = (n.x, n.y, n.z)
                depth[i] = spec.camera.distance - si.p.z
                part[i] = part_of[names.index(si.shape.id())]
    return _finish_geometry(normal, mask, depth, part, W, H)


def _finish_geometry(normal, mask, depth, part, W: int, H: int):
    normal = normal.astype(np.float64)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    normal[~mask] = 0.0
    depth[~mask] = 0.0
    return (normal.reshape(H, W, 3).astype(np.float32), mask.reshape(H, W), depth.reshape(H, W),
            part.reshape(H, W))


def _centre_hits(mi, scene, sensor, W: int, H: int):
    """One ray per pixel centre (JIT variants): (ray, surface interaction, hit mask, shading normal
    turned to face the camera) -- what every ground-truth path reads."""
    import drjit as dr

    idx = dr.arange(mi.UInt32, W * H)
    pos = mi.Point2f((mi.Float(idx % W) + 0.5) / W, (mi.Float(idx // W) + 0.5) / H)
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(ray)
    valid = si.is_valid()
    n = si.sh_frame.n
    return ray, si, valid, dr.select(dr.dot(n, ray.d) > 0, -n, n)


def _cast_jit(mi, scene, spec: SceneSpec, shapes, part_of, appearance: bool):
    """One ray per pixel centre, every output evaluated in ONE kernel launch (`dr.eval` of all of
    them together): converting them to numpy one at a time re-traced the rays once per array.
    Returns flat numpy arrays (mask, normal, depth, part, albedo, weight); the last two None
    unless `appearance`."""
    import drjit as dr

    from msps_render.render.textures import ALBEDO, WEIGHT

    W, H = spec.camera.width, spec.camera.height
    ray, si, valid, n = _centre_hits(mi, scene, scene.sensors()[0], W, H)
    ids = dr.reinterpret_array(mi.UInt32, si.shape)
    z = spec.camera.distance - si.p.z
    outs = [valid, n, z, ids]
    if appearance:
        outs += [si.shape.eval_attribute_3(ALBEDO, si, valid), si.shape.eval_attribute_1(WEIGHT, si, valid)]
    dr.eval(*outs)
    shape_ids = [int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0]) for s in shapes]
    mask = np.array(valid, dtype=bool)
    normal = np.stack([np.array(n.x), np.array(n.y), np.array(n.z)], -1)
    depth = np.array(z, dtype=np.float32)
    sid = np.array(ids)
    part = np.full(W * H, -1, dtype=np.int8)
    for s_id, p in zip(shape_ids, part_of):
        part[(sid == s_id) & mask] = p
    albedo = weight = None
    if appearance:
        a, w = outs[4], outs[5]
        albedo = np.stack([np.array(a.x), np.array(a.y), np.array(a.z)], -1)
        weight = np.array(w)
        albedo[~mask] = 0.0
        weight[~mask] = 0.0
    return mask, normal, depth, part, albedo, weight


def frame_truth(mi, scene, spec: SceneSpec):
    """`ground_truth` and `appearance_truth` of a loaded scene from one shared ray cast (JIT
    variants; the same values as calling both): (normal, mask, depth, part, albedo, blend)."""
    import drjit as dr

    from msps_render.render.textures import ALBEDO

    shapes = scene.shapes()
    parts = [s for s in shapes if s.id().startswith("part")]
    if not dr.is_jit_v(mi.Float) or not parts or not all(s.has_attribute(ALBEDO) for s in parts):
        return (*ground_truth(mi, scene, spec), *appearance_truth(mi, scene, spec))
    W, H = spec.camera.width, spec.camera.height
    part_of = [int(s.id()[4:]) if s.id().startswith("part") else -1 for s in shapes]
    mask, normal, depth, part, albedo, weight = _cast_jit(mi, scene, spec, shapes, part_of, appearance=True)
    return (*_finish_geometry(normal, mask, depth, part, W, H),
            albedo.reshape(H, W, 3).astype(np.float32), weight.reshape(H, W).astype(np.float32))


def appearance_truth(mi, scene, spec: SceneSpec) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel diffuse albedo (H, W, 3) and blend weight (H, W) at the pixel centres.

    Read back from the part meshes' appearance attributes (`render.textures`) with
    `Shape.eval_attribute`, i.e. the very values the renderer interpolated; 0 where the
    material has no diffuse albedo (measured, conductors) and off the object.  The
    analytic sphere has no attributes: its one material's constant albedo.
    """
    import drjit as dr

    from msps_render.render.textures import ALBEDO, WEIGHT

    W, H = spec.camera.width, spec.camera.height
    parts = [s for s in scene.shapes() if s.id().startswith("part")]
    if not parts or not all(s.has_attribute(ALBEDO) for s in parts):
        return constant_appearance(spec, ground_truth(mi, scene, spec)[3])
    sensor = scene.sensors()[0]
    if dr.is_jit_v(mi.Float):
        _, si, valid, _ = _centre_hits(mi, scene, sensor, W, H)
        a = si.shape.eval_attribute_3(ALBEDO, si, valid)
        w = si.shape.eval_attribute_1(WEIGHT, si, valid)
        albedo = np.stack([np.array(a.x), np.array(a.y), np.array(a.z)], -1)
        weight = np.array(w)
        off = ~np.array(valid, dtype=bool)
    else:  # scalar variants: one ray at a time (slow but only a fallback)
        albedo, weight, off = np.zeros((W * H, 3)), np.zeros(W * H), np.ones(W * H, bool)
        for i in range(W * H):
            ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f((i % W + 0.5) / W, (i // W + 0.5) / H),
                                       mi.Point2f(0.5, 0.5))
            si = scene.ray_intersect(ray)
            if si.is_valid():
                a = si.shape.eval_attribute_3(ALBEDO, si)
                albedo[i], weight[i], off[i] = (a[0], a[1], a[2]), si.shape.eval_attribute_1(WEIGHT, si), False
    albedo[off] = 0.0
    weight[off] = 0.0
    return albedo.reshape(H, W, 3).astype(np.float32), weight.reshape(H, W).astype(np.float32)


def pooled_truth(mi, scene, sensor, spec: SceneSpec, part_attribute: str):
    """`frame_truth` of a pooled scene (`render.pool`): the mesh lies in its object frame and the
    camera turned by R^T, so normals and points come back to the camera frame through R; the
    part is the face attribute `part_attribute`; the albedo is each part's constant one (pooled
    scenes carry no textures) and the blend weight 0.  (normal, mask, depth, part, albedo, blend)."""
    import drjit as dr

    W, H = spec.camera.width, spec.camera.height
    _, si, valid, n = _centre_hits(mi, scene, sensor, W, H)
    part_f = si.shape.eval_attribute_1(part_attribute, si, valid)
    dr.eval(valid, n, si.p, part_f)
    R = np.asarray(spec.shape.rotation, dtype=np.float64)
    mask = np.array(valid, dtype=bool)
    normal = np.stack([np.array(n.x), np.array(n.y), np.array(n.z)], -1) @ R.T
    p = np.stack([np.array(si.p.x), np.array(si.p.y), np.array(si.p.z)], -1).astype(np.float64)
    depth = (spec.camera.distance - p @ R[2]).astype(np.float32)
    part = np.where(mask, np.rint(np.array(part_f)), -1).astype(np.int8)
    normal, mask, depth, part = _finish_geometry(normal, mask, depth, part, W, H)
    albedo, blend = constant_appearance(spec, part)
    return normal, mask, depth, part, albedo, blend


def constant_appearance(spec: SceneSpec, part: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Albedo (H, W, 3) and blend weight (H, W) of untextured materials from the part map."""
    from msps_render.render.textures import constant_albedo

    albedo = np.zeros(part.shape + (3,), np.float32)
    for p, m in enumerate(spec.materials):
        albedo[part == p] = constant_albedo(m)
    return albedo, np.zeros(part.shape, np.float32)


def pixel_points(camera, depth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W, 3) surface point of each pixel centre, camera frame (0 off the object), from the z-depth.

    Why: near lights light each pixel from its own direction, l(x) = (p - x)/|p - x|; the point x is
    exact from the pixel-centre ray (the same one the depth came from).  Orthographic: x, y are the
    pixel centre on the view plane (the width spans +-`extent`, pixels square: Mitsuba's orthographic
    film); perspective: along the pixel-centre ray (field of view on the smaller side)."""
    H, W = depth.shape
    s = W if camera.kind == "orthographic" else min(H, W)  # orthographic: the width spans +-extent
    u = (2.0 * (np.arange(W) + 0.5) - W) / s  # image right, in units of half that side
    v = (H - 2.0 * (np.arange(H) + 0.5)) / s  # image up
    z = camera.distance - depth.astype(np.float64)
    if camera.kind == "orthographic":
        x = np.broadcast_to(u[None, :] * camera.extent, (H, W))
        y = np.broadcast_to(v[:, None] * camera.extent, (H, W))
    else:
        t = np.tan(np.radians(camera.fov_deg) / 2.0)
        x = u[None, :] * t * depth
        y = v[:, None] * t * depth
    p = np.stack([x, y, z], axis=-1)
    return np.where(mask[..., None], p, 0.0).astype(np.float32)
