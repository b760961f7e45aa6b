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
    return {"type": "envmap", "bitmap": mi.Bitmap(np.array(img, dtype=np.float32, order="C", copy=True)),  # writeable copy: Bitmap refuses read-only arrays
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


def _emitter_names(params, spec: SceneSpec) -> list[str]:
    """Emitter ids in render order (lights, then environment), checked against `mi.traverse`."""
    names = [_light_key(k) for k in range(len(spec.lights))]
    if spec.environment is not None:
        names.append(ENV_KEY)
    missing = [n for n in names if f"{n}.sampling_weight" not in params]
    if missing:
        raise RuntimeError(f"emitters not found in the loaded scene: {missing}")
    return names


def _ground_truth(mi, scene, spec: SceneSpec):
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
        depth = np.array(spec.camera.distance - si.p.z, dtype=np.float32)
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
                depth[i] = spec.camera.distance - si.p.z
                part[i] = part_of[names.index(si.shape.id())]
    normal = normal.astype(np.float64)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    normal[~mask] = 0.0
    depth[~mask] = 0.0
    return (normal.reshape(H, W, 3).astype(np.float32), mask.reshape(H, W), depth.reshape(H, W),
            part.reshape(H, W))


def render_emitters_separately(mi, scene, spec: SceneSpec) -> list[np.ndarray]:
    """One image per emitter (lights in order, then the environment), from one loaded scene.

    Why: Mitsuba's next-event estimation picks ONE emitter at random per
    sample, so three differently coloured delta lights in one render give
    heavy colour noise (~13% per pixel at 32 spp).  A directional light alone
    is sampled exactly, so rendering each emitter on its own (switching the
    others off through `mi.traverse`, which reuses the compiled kernel) and
    summing gives noise-free direct lighting at the same spp.  Switching an
    emitter off sets its `sampling_weight` to 0, so next-event estimation
    never picks it (zeroing its radiance instead would keep the selection noise).
    """
    spp, seed = spec.integrator.spp, spec.integrator.seed
    params = mi.traverse(scene)
    keys = _emitter_names(params, spec)
    if len(keys) == 1:
        return [np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float32)[..., :3]]
    weight = {k: f"{k}.sampling_weight" for k in keys}
    orig = {k: float(params[w][0] if hasattr(params[w], "__len__") else params[w]) for k, w in weight.items()}
    # BSDF-sampled rays can still hit the environment when it is not sampled, so it is
    # also dimmed (scale 0) while the lights render; delta lights cannot be hit that way.
    env_scale = f"{ENV_KEY}.scale"
    env_orig = float(params[env_scale][0] if hasattr(params[env_scale], "__len__") else params[env_scale]) \
        if env_scale in params else None
    images = []
    for on in keys:
        for k, w in weight.items():
            params[w] = orig[k] if k == on else 0.0
        if env_orig is not None:
            params[env_scale] = env_orig if on == ENV_KEY else 0.0
        params.update()
        images.append(np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float32)[..., :3])
    for k, w in weight.items():  # leave the scene as it was loaded
        params[w] = orig[k]
    if env_orig is not None:
        params[env_scale] = env_orig
    params.update()
    return images


def render_frame(spec: SceneSpec, variant: str | None = None, threads: int | None = None,
                 per_light: bool = False) -> Frame:
    """Render one scene. `variant=None` resolves the best working variant for `spec.mode`."""
    variant = variant or resolve_variant(spec.mode)
    mi = activate(variant, threads)
    if spec.mode == "spectral":
        from msps_render.spectral.render import render_spectral_frame

        return render_spectral_frame(spec, mi, variant, per_light=per_light)
    scene = mi.load_dict(build_scene_dict(spec, mi))
    normal, mask, depth, part = _ground_truth(mi, scene, spec)

    images = render_emitters_separately(mi, scene, spec)
    env_img = images.pop() if spec.environment is not None else None
    per = np.stack(images) if images else np.zeros((0,) + normal.shape, np.float32)
    image = per.sum(axis=0) + (env_img if env_img is not None else 0.0)
    if not per_light:
        per = None
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



def release_frame_memory() -> None:
    """Free what a finished frame left behind; pipeline workers call it after every frame.

    Two sources of unbounded worker growth, both outside our code
    (benchmarks/bench_memory.py, docs/benchmarks.md "Worker memory"):
    drjit keeps every kernel it ever compiled and each new scene compiles a few
    (the bare-Mitsuba `--repro` loop grows ~0.16 MiB per frame too), and glibc
    keeps freed heap in its arenas (a slow creep and ~20 MiB steps once the kernel
    cache is flushed, worst under CPU contention).  Flushing drjit's kernel and
    malloc caches, capping glibc's arenas and `malloc_trim(0)` keep RSS flat for
    ~1-5% of a paper-size frame's time.  `gc.collect()` first so scenes
    held by reference cycles release their buffers.
    """
    import gc

    import drjit as dr

    gc.collect()
    try:
        dr.sync_thread()
        dr.flush_kernel_cache()
        dr.flush_malloc_cache()
    except Exception:  # scalar variants / no JIT backend: nothing cached
        pass
    _malloc_trim()


def _malloc_trim() -> None:
    """Return freed heap to the OS (glibc only; a no-op elsewhere).

    The first call also caps glibc at 2 malloc arenas (M_ARENA_MAX): under CPU
    contention glibc opens a new arena whenever a thread finds the others locked,
    and each arena keeps its own freed memory (RSS steps of ~20 MiB at random moments).
    """
    global _LIBC
    if _LIBC is None:
        import ctypes
        import ctypes.util

        try:
            _LIBC = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            _LIBC.malloc_trim  # noqa: B018 - raises AttributeError off glibc
            _LIBC.mallopt(-8, 2)  # M_ARENA_MAX
        except (OSError, AttributeError):
            _LIBC = False
    if _LIBC:
        _LIBC.malloc_trim(0)


_LIBC = None
