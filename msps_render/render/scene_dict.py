"""SceneSpec -> the `mi.load_dict` description of a scene (needs the variant set).

Shapes are built from memory (`mi.Mesh` + `mi.traverse` buffers, one Mitsuba
shape per material part), materials go through `render.materials.to_mitsuba`,
the environment becomes an `envmap` emitter over the map's pixels.  Emitters
have fixed ids (`light_key(k)`, `ENV_KEY`) so renderers can switch them and
the one-pass integrator (`render.multilight`) names its channels after them.

Kernel reuse (docs/architecture.md "Kernels reused across scenes"): per-scene
numbers must reach drjit as data, not as literals baked into the kernels, or
every scene compiles its own.  Two scene-level literals are avoided here: the
scene's bounding sphere, which directional and environment emitters bake in
at load time, is pinned by a `BOUND_KEY` helper shape, and the environment's
`scale` is folded into its bitmap (`scale` stays 1).
"""
from __future__ import annotations

import numpy as np

from msps_render.render.materials import to_mitsuba
from msps_render.render.multilight import integrator_dict
from msps_render.render.textures import subdivide_to_edge, vertex_attributes
from msps_render.scene.envmap import envmap_pixels
from msps_render.scene.shapes import build_mesh, face_parts, part_pieces
from msps_render.errors import InputError
from msps_render.scene.spec import CameraSpec, SceneSpec
from msps_render.timing import StageTimer, stage

ENV_KEY = "environment"
BOUND_KEY = "bound"
SCENE_BOUND = 1.5  # half-size of the fixed scene bounding box; objects fit in radius 1


def light_key(k: int) -> str:
    """The scene-dict id of light k."""
    return f"light{k}"


def _rgb(mi, v):
    return {"type": "rgb", "value": [float(x) for x in v]}


def camera_to_world(mi, c: CameraSpec):
    """The sensor's `to_world`: on the +z axis looking at the origin, y up (orthographic: scaled)."""
    T = mi.ScalarTransform4f
    look = T().look_at(origin=[0.0, 0.0, c.distance], target=[0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0])
    return look @ T().scale([c.extent, c.extent, 1.0]) if c.kind == "orthographic" else look


def _sensor(mi, spec: SceneSpec) -> dict:
    c = spec.camera
    film = {"type": "hdrfilm", "width": c.width, "height": c.height, "rfilter": {"type": "box"},
            "pixel_format": "rgb", "component_format": "float32"}
    sampler = {"type": spec.integrator.sampler, "sample_count": spec.integrator.spp, "seed": spec.integrator.seed}
    if c.kind == "orthographic":
        return {"type": "orthographic", "to_world": camera_to_world(mi, c),
                "near_clip": 0.01, "far_clip": 2 * c.distance + 10, "film": film, "sampler": sampler}
    return {"type": "perspective", "to_world": camera_to_world(mi, c), "fov": c.fov_deg, "fov_axis": "smaller",
            "near_clip": 0.01, "far_clip": 2 * c.distance + 10, "film": film, "sampler": sampler}


def _bsdf(mi, spec: SceneSpec, p: int, timer: StageTimer | None):
    """Part p's loaded BSDF (measured tables are read or baked on first use: timed as 'materials')."""
    with stage(timer, "materials"):
        return mi.load_dict(to_mitsuba(spec.materials[p]))


def mitsuba_mesh(mi, name: str, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, props=None):
    """(mi.Mesh, its traversed parameters) of float vertices, faces and vertex normals, built in memory
    (call `params.update()` after adding attributes)."""
    import drjit as dr

    m = mi.Mesh(name, len(vertices), len(faces), props=props if props is not None else mi.Properties(),
                has_vertex_normals=True)
    params = mi.traverse(m)
    params["vertex_positions"] = dr.ravel(mi.TensorXf(vertices))
    params["faces"] = dr.ravel(mi.TensorXu(faces.astype(np.uint32)))
    params["vertex_normals"] = dr.ravel(mi.TensorXf(normals))
    return m, params


def object_mesh(spec: SceneSpec, timer: StageTimer | None = None):
    """The object's mesh as the renderer uses it (camera frame): built, then, for vertex-sampled
    textures, subdivided so that its triangles are small (timed as 'texture')."""
    mesh = build_mesh(spec.shape)
    textures = [m.texture for m in spec.materials if m.texture is not None]
    if textures:
        with stage(timer, "texture"):
            mesh = subdivide_to_edge(mesh, min(t.max_edge for t in textures))
    return mesh


def geometry_shapes(mi, spec: SceneSpec) -> dict:
    """The object's surface as `_shapes` builds it (same mesh, textures' subdivision included), as one
    shape without BSDFs or attributes: for rays that only ask where the surface is (`render/shadows.py`)."""
    if spec.shape.kind == "sphere":
        return {"object": {"type": "sphere", "radius": spec.shape.radius}}
    mesh = object_mesh(spec)
    m, params = mitsuba_mesh(mi, "object", mesh.vertices, mesh.faces, mesh.normals)
    params.update()
    return {"object": m}


def part_bsdfs(mi, spec: SceneSpec, parts, timer: StageTimer | None, slots) -> dict:
    """{part: loaded BSDF} for the parts used, made in the order of their (slot) kind: drjit numbers
    instances in creation order and the kernel depends on that order, so [merl, diffuse] and
    [diffuse, merl] would compile two kernels; sorted, they share one.  With the worker's `slots`
    (`render.slots`) a new mix of kinds it has seen keeps the kernel too."""
    if slots is None:
        return {p: _bsdf(mi, spec, p, timer) for p in sorted(parts, key=lambda p: (spec.materials[p].kind, p))}
    from msps_render.render.slots import slot_kind

    wanted = sorted((slot_kind(spec.materials[p]), p) for p in parts)
    made = slots.fill([(kind, lambda p=p: _bsdf(mi, spec, p, timer)) for kind, p in wanted])
    return {p: b for (_, p), b in zip(wanted, made)}


def _shapes(mi, spec: SceneSpec, timer: StageTimer | None = None, slots=None) -> dict:
    """Mitsuba shapes (one per material part), built from memory (BSDFs in `slots` when given)."""
    if spec.shape.kind == "sphere":
        return {"part0": {"type": "sphere", "radius": spec.shape.radius,
                          "bsdf": part_bsdfs(mi, spec, [0], timer, slots)[0]}}
    with stage(timer, "mesh"):  # the BSDFs inside are timed apart (nested stage)
        mesh = object_mesh(spec, timer)
        R = np.asarray(spec.shape.rotation, dtype=np.float64)  # world = object @ R.T
        pieces = list(part_pieces(mesh.faces, face_parts(mesh, spec.split), len(mesh.vertices)))
        bsdfs = part_bsdfs(mi, spec, [p for p, _, _ in pieces], timer, slots)
        out = {}
        for p, used, faces in pieces:
            props = mi.Properties()
            props["bsdf"] = bsdfs[p]
            m, params = mitsuba_mesh(mi, f"part{p}", mesh.vertices[used], faces, mesh.normals[used], props)
            with stage(timer, "texture"):
                attrs = vertex_attributes(spec.materials[p], mesh.vertices[used] @ R, mesh.normals[used] @ R,
                                          None if mesh.uv is None else mesh.uv[used])
            for name, a in attrs.items():
                # a list, not a drjit Float: `add_attribute` takes a Python sequence and reads a
                # Float element by element (~1 ms per 4k vertices); the values are the same float32s
                m.add_attribute(name, a.shape[1], np.ascontiguousarray(a, np.float32).ravel().tolist())
            params.update()
            out[f"part{p}"] = m
        return out


def _envmap(mi, spec: SceneSpec, factor: float = 1.0) -> dict:
    """The environment emitter with `scale * factor` folded into the bitmap (its `scale` literal stays 1)."""
    e = spec.environment
    img = np.array(envmap_pixels(e.source, e.seed), dtype=np.float32, order="C", copy=True)  # writeable: Bitmap refuses read-only arrays
    img *= np.float32(float(e.scale) * factor)
    return {"type": "envmap", "bitmap": mi.Bitmap(img), "scale": 1.0,
            "to_world": mi.ScalarTransform4f().rotate([0, 1, 0], e.rotation_deg)}


def emitter_ids(spec: SceneSpec) -> list[str]:
    """Emitter ids in render order: the lights, then the environment."""
    return [light_key(k) for k in range(len(spec.lights))] + ([ENV_KEY] if spec.environment is not None else [])


def one_pass(spec: SceneSpec, mi) -> bool:
    """Render with the one-pass integrator?  Asked for, and a JIT variant: in scalar variants a
    Python integrator is called per sample (~50-450x slower), so they keep per-light renders."""
    import drjit as dr

    return spec.integrator.lights == "one-pass" and dr.is_jit_v(mi.Float)


def with_lights(spec: SceneSpec, mode: str) -> SceneSpec:
    """`spec` rendered with `integrator.lights = mode` ("one-pass" or "per-light")."""
    return spec.model_copy(update={"integrator": spec.integrator.model_copy(update={"lights": mode})})


def _bound(mi) -> "mi.Mesh":
    """An invisible mesh whose bounding box is [-SCENE_BOUND, SCENE_BOUND]^3.

    Why: directional and environment emitters store the scene's bounding sphere
    when the scene is loaded and drjit bakes it into the kernels as literals, so
    objects with different bounding boxes compiled their own kernels.  With this
    shape every scene whose object lies inside the box has the same bounding
    sphere.  Its two faces are points (all three corners on one vertex, at two
    opposite corners of the box): zero area, never hit by a ray, no BSDF needed.
    Shadow rays of directional lights only get longer (they start outside the
    larger sphere), so images are unchanged.
    """
    import drjit as dr

    b = SCENE_BOUND
    m = mi.Mesh(BOUND_KEY, 2, 2, has_vertex_normals=False)
    params = mi.traverse(m)
    params["vertex_positions"] = dr.ravel(mi.TensorXf(np.array([[-b, -b, -b], [b, b, b]], np.float32)))
    params["faces"] = dr.ravel(mi.TensorXu(np.array([[0, 0, 0], [1, 1, 1]], np.uint32)))
    params.update()
    return m


def build_scene_dict(spec: SceneSpec, mi, timer: StageTimer | None = None, env_factor: float = 1.0,
                     slots=None) -> dict:
    """The `mi.load_dict` description of a SceneSpec (needs the variant set).

    `env_factor` multiplies the environment's radiance (spectral mode's RGB->spectrum
    correction); `timer` times mesh building and material loading apart from the rest
    ('scene dict'); `slots`: the worker's `render.slots.BsdfSlots` for the part BSDFs (None: new ones).
    """
    with stage(timer, "scene dict"):
        return _scene_dict(spec, mi, timer, env_factor, slots)


def _scene_dict(spec: SceneSpec, mi, timer: StageTimer | None, env_factor: float, slots=None) -> dict:
    integ = spec.integrator
    if one_pass(spec, mi):
        mus = list(spec.rig.anisotropy) if spec.rig is not None and spec.rig.anisotropy else []
        integrator = integrator_dict(integ.kind, integ.max_depth, emitter_ids(spec), hide_emitters=True,
                                     anisotropy=mus + [0.0] * (len(emitter_ids(spec)) - len(mus)) if mus else ())
    elif spec.rig is not None and any(spec.rig.anisotropy):
        raise InputError("scene.rig.anisotropy_mu", f"anisotropic LEDs need the one-pass integrator in a JIT "
                                                    f"variant (llvm_*/cuda_*); this render uses {mi.variant()}")
    elif integ.kind == "path":
        integrator = {"type": "path", "max_depth": integ.max_depth, "hide_emitters": True}
    else:
        integrator = {"type": "direct", "hide_emitters": True}
    d = {"type": "scene", "integrator": integrator, "sensor": _sensor(mi, spec)}
    d.update(_shapes(mi, spec, timer, slots))
    d[BOUND_KEY] = _bound(mi)
    for k, l in enumerate(spec.lights):
        if l.kind == "directional":
            d[light_key(k)] = {"type": "directional", "direction": [-c for c in l.direction],
                                "irradiance": _rgb(mi, l.rgb)}
        else:
            d[light_key(k)] = {"type": "point", "position": [c * l.distance for c in l.direction],
                                "intensity": _rgb(mi, l.rgb)}
    if spec.environment is not None:
        d[ENV_KEY] = _envmap(mi, spec, env_factor)
    return d
