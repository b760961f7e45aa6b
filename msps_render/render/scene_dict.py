"""SceneSpec -> the `mi.load_dict` description of a scene (needs the variant set).

Shapes are built from memory (`mi.Mesh` + `mi.traverse` buffers, one Mitsuba
shape per material part), materials go through `render.materials.to_mitsuba`,
the environment becomes an `envmap` emitter over the map's pixels.  Emitters
have fixed ids (`light_key(k)`, `ENV_KEY`) so renderers can switch them and
the one-pass integrator (`render.multilight`) names its channels after them.
"""
from __future__ import annotations

import numpy as np

from msps_render.render.materials import to_mitsuba
from msps_render.render.multilight import integrator_dict
from msps_render.scene.envmap import envmap_pixels
from msps_render.scene.shapes import build_mesh, face_parts
from msps_render.scene.spec import SceneSpec

ENV_KEY = "environment"


def light_key(k: int) -> str:
    """The scene-dict id of light k."""
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
    e = spec.environment
    img = envmap_pixels(e.source, e.seed)
    return {"type": "envmap", "bitmap": mi.Bitmap(np.array(img, dtype=np.float32, order="C", copy=True)),  # writeable copy: Bitmap refuses read-only arrays
            "scale": float(e.scale), "to_world": mi.ScalarTransform4f().rotate([0, 1, 0], e.rotation_deg)}


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


def build_scene_dict(spec: SceneSpec, mi) -> dict:
    """The `mi.load_dict` description of a SceneSpec (needs the variant set)."""
    integ = spec.integrator
    if one_pass(spec, mi):
        integrator = integrator_dict(integ.kind, integ.max_depth, emitter_ids(spec), hide_emitters=True)
    elif integ.kind == "path":
        integrator = {"type": "path", "max_depth": integ.max_depth, "hide_emitters": True}
    else:
        integrator = {"type": "direct", "hide_emitters": True}
    d = {"type": "scene", "integrator": integrator, "sensor": _sensor(mi, spec)}
    d.update(_shapes(mi, spec))
    for k, l in enumerate(spec.lights):
        if l.kind == "directional":
            d[light_key(k)] = {"type": "directional", "direction": [-c for c in l.direction],
                                "irradiance": _rgb(mi, l.rgb)}
        else:
            d[light_key(k)] = {"type": "point", "position": [c * l.distance for c in l.direction],
                                "intensity": _rgb(mi, l.rgb)}
    if spec.environment is not None:
        d[ENV_KEY] = _envmap(mi, spec)
    return d
