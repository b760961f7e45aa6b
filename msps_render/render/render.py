"""SceneSpec -> Frame.  The only stage that talks to Mitsuba.

The image is `mi.render` with a box pixel filter (a pixel is the mean radiance
over its footprint).  Ground truth (normal, depth, mask, part) comes from one
ray through each pixel centre with `scene.ray_intersect`, so it is exact and
never blended with the background.  Per-light images are rendered from the
same compiled scene by switching the other emitters off with `mi.traverse`,
and then the full image is their sum: linearity makes that exact, and it keeps
`image == Σ per_light + env` bit-for-bit consistent.
"""
from __future__ import annotations



import numpy as np

from msps_render.frame import Frame
from msps_render.render.variant import activate, resolve_variant
from msps_render.scene.materials import to_mitsuba
from msps_render.scene.shapes import build_mesh, face_parts
from msps_render.scene.spec import SceneSpec

ENV_KEY = "environment"


def _light_key(k: int) -> str:
    return f"light{k}"


def _rgb(mi, v):
    return {"type": "rgb", "value": [float(x) for x in v]}


def _sensor(mi, spec: SceneSpec) -> dict:
    c = spec.camera
    T = mi.ScalarTransform4f
    look = T().look_at(origin=[0.0, 0.0, c.distance], target=[0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0])
    film = {"type": "hdrfilm", "width": c.width, "height": c.height, "rfilter": {"type": "box"},
            "pixel_format": "rgb", "component_format": "float32"}
    sampler = {"type": "independent", "sample_count": spec.integrator.spp, "seed": spec.integrator.seed}
    if c.kind == "orthographic":
        return {"type": "orthographic", "to_world": look @ T().scale([c.extent, c.extent, 1.0]),
                "near_clip": 0.01, "far_clip": 2 * c.distance + 10, "film": film, "sampler": sampler}
    return {"type": "perspective", "to_world": look, "fov": c.fov_deg, "fov_axis": "smaller",
            "near_clip": 0.01, "far_clip": 2 * c.distance + 10, "film": film, "sampler": sampler}


def _shapes(mi, spec: SceneSpec) -> dict:
    """Mitsuba shapes (one per material part), built from memory."""
    import drjit as dr

    if spec.shape.kind == "sphere":
        return {"part0": {"type": "sphere", "radius": spec.shape.radius, "bsdf": to_mitsuba(spec.materials[0])}}
    mesh = build_mesh(spec.shape)
    parts = face_parts(mesh, spec.split)
    out = {}
    for p in range(int(parts.max()) + 1):
        faces = mesh.faces[parts == p]
        if len(faces) == 0:
            continue
        used = np.unique(faces)
        remap = np.zeros(len(mesh.vertices), dtype=np.uint32)
        remap[used] = np.arange(len(used), dtype=np.uint32)
        props = mi.Properties()
        props["bsdf"] = mi.load_dict(to_mitsuba(spec.materials[p]))
        m = mi.Mesh(f"part{p}", len(used), len(faces), props=props, has_vertex_normals=True)
        params = mi.traverse(m)
        params["vertex_positions"] = dr.ravel(mi.TensorXf(mesh.vertices[used]))
        params["faces"] = dr.ravel(mi.TensorXu(remap[faces]))
        params["vertex_normals"] = dr.ravel(mi.TensorXf(mesh.normals[used]))
        params.update()
        out[f"part{p}"] = m
    return out


def _envmap(mi, spec: SceneSpec) -> dict:
    from msps_render.scene.envmap import envmap_pixels

    e = spec.environment
    img = envmap_pixels(e.source, e.seed)
    return {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(img, dtype=np.float32)),
            "scale": float(e.scale), "to_world": mi.ScalarTransform4f().rotate([0, 1, 0], e.rotation_deg)}


def build_scene_dict(spec: SceneSpec, mi) -> dict:
    """The `mi.load_dict` description of a SceneSpec (needs the variant set)."""
    integ = spec.integrator
    if integ.kind == "path":
        integrator = {"type": "path", "max_depth": integ.max_depth, "hide_emitters": True}
    else:
        integrator = {"type": "direct", "hide_emitters": True}
    d = {"type": "scene", "integrator": integrator, "sensor": _sensor(mi, spec)}
    d.update(_shapes(mi, spec))
    for k, l in enumerate(spec.lights):
        if l.kind == "directional":
            d[_light_key(k)] = {"type": "directional", "direction": [-c for c in l.direction],
                                "irradiance": _rgb(mi, l.rgb)}
        else:
            d[_light_key(k)] = {"type": "point", "position": [c * l.distance for c in l.direction],
                                "intensity": _rgb(mi, l.rgb)}
    if spec.environment is not None:
        d[ENV_KEY] = _envmap(mi, spec)
    return d


def _emitter_params(params, spec: SceneSpec) -> dict[str, str]:
    """Parameter key of each emitter's strength in `mi.traverse(scene)`."""
    keys = {}
    for k, l in enumerate(spec.lights):
        name = "irradiance" if l.kind == "directional" else "intensity"
        keys[_light_key(k)] = f"{_light_key(k)}.{name}.value"
    if spec.environment is not None:
        keys[ENV_KEY] = f"{ENV_KEY}.scale"
    missing = [v for v in keys.values() if v not in params]
    if missing:
        raise RuntimeError(f"emitter parameters not found in scene: {missing}")
    return keys


def _ground_truth(mi, scene, spec: SceneSpec):
    """Normal/depth/mask/part from one ray per pixel centre."""
    import drjit as dr

    W, H = spec.camera.width, spec.camera.height
    sensor = scene.sensors()[0]
    shapes = scene.shapes()
    names = [s.id() for s in shapes]
    part_of = [int(n[4:]) if n.startswith("part") else -1 for n in names]
    if dr.is_jit_v(mi.Float):
        idx = dr.arange(mi.UInt32, W * H)
        x, y = idx % W, idx // W
        pos = mi.Point2f((mi.Float(x) + 0.5) / W, (mi.Float(y) + 0.5) / H)
        ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
        si = scene.ray_intersect(ray)
        valid = si.is_valid()
        n = si.sh_frame.n
        n = dr.select(dr.dot(n, ray.d) > 0, -n, n)  # face the camera
        ids = dr.reinterpret_array(mi.UInt32, si.shape)
        shape_ids = [int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0]) for s in shapes]
        mask = np.array(valid, dtype=bool)
        normal = np.stack([np.array(n.x), np.array(n.y), np.array(n.z)], -1)
        depth = np.array(si.t, dtype=np.float32)
        sid = np.array(ids)
        part = np.full(W * H, -1, dtype=np.int8)
        for s_id, p in zip(shape_ids, part_of):
            part[(sid == s_id) & mask] = p
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
                depth[i] = si.t
                part[i] = part_of[names.index(si.shape.id())]
    normal = normal.astype(np.float64)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    normal[~mask] = 0.0
    depth[~mask] = 0.0
    return (normal.reshape(H, W, 3).astype(np.float32), mask.reshape(H, W), depth.reshape(H, W),
            part.reshape(H, W))


def render_frame(spec: SceneSpec, variant: str | None = None, threads: int | None = None,
                 per_light: bool = False) -> Frame:
    """Render one scene. `variant=None` resolves the best working variant for `spec.mode`."""
    variant = variant or resolve_variant(spec.mode)
    mi = activate(variant, threads)
    if spec.mode == "spectral":
        from msps_render.spectral.render import render_spectral_frame

        return render_spectral_frame(spec, mi, variant, per_light=per_light)
    scene = mi.load_dict(build_scene_dict(spec, mi))
    spp, seed = spec.integrator.spp, spec.integrator.seed
    normal, mask, depth, part = _ground_truth(mi, scene, spec)

    per, env_img = None, None
    if per_light:
        params = mi.traverse(scene)
        keys = _emitter_params(params, spec)
        orig = {k: type(params[v])(params[v]) for k, v in keys.items()}
        images = []
        for on in keys:
            for k, v in keys.items():
                params[v] = orig[k] if k == on else orig[k] * 0.0
            params.update()
            images.append(np.array(mi.render(scene, params, spp=spp, seed=seed), dtype=np.float32))
        if spec.environment is not None:
            env_img = images.pop()
        per = np.stack(images)
        image = per.sum(axis=0) + (env_img if env_img is not None else 0.0)
    else:
        image = np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float32)
    return Frame(image=np.ascontiguousarray(image[..., :3], dtype=np.float32), normal=normal, mask=mask,
                 depth=depth, part=part, spec=spec, variant=variant, per_light=per, env_image=env_img,
                 meta={"mitsuba_version": mi.__version__})


def analytic_sphere_normals(width: int, height: int, extent: float, radius: float):
    """Analytic normals/mask of an orthographic sphere at the pixel centres (for tests)."""
    xs = ((np.arange(width) + 0.5) / width * 2 - 1) * extent * (width / height if width > height else 1)
    ys = (1 - (np.arange(height) + 0.5) / height * 2) * extent
    X, Y = np.meshgrid(xs, ys)
    r2 = (X ** 2 + Y ** 2) / radius ** 2
    mask = r2 < 1
    Z = np.sqrt(np.clip(1 - r2, 0, None))
    n = np.stack([X / radius, Y / radius, Z], -1)
    n[~mask] = 0
    return n, mask


__all__ = ["render_frame", "build_scene_dict", "analytic_sphere_normals"]

