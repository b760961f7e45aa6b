"""Per-light shadow masks of a frame: where each light's direct light is blocked, as ground truth.

Codes per light and pixel centre (`dataset.schema` SHADOW_*): 0 lit (or off the object), 1 attached
shadow (the surface faces away from the light: n . l <= 0 with the stored normal n), 2 cast shadow
(it faces the light, but the ray toward the light hits the object first).  Why: methods that model
shadows (or discard shadowed observations) need to know which of a pixel's N observations are
shadowed, and the images alone cannot say it exactly (a dark material looks like a shadow).

One ray per pixel centre and light, in the world (camera) frame of the spec, from a scene of the
frame's geometry alone (`scene_dict.geometry_shapes` and the sensor: the mesh the renderer builds, no
materials, lights or integrator); lights in chunks so that N = 96 needs no 1.5-million-ray arrays.  Pooled frames
render in their object frame (`render/pool.py`); these masks come from the camera-frame scene, the
same surface up to float rounding (a silhouette pixel may differ from `mask`: such pixels read 0).
"""
from __future__ import annotations

import numpy as np

from msps_render.dataset.schema import SHADOW_ATTACHED, SHADOW_CAST, SHADOW_LIT
from msps_render.errors import InputError
from msps_render.scene.spec import SceneSpec

LIGHTS_PER_LAUNCH = 16  # 16 x 128 x 128 rays per kernel: a few MB of drjit arrays


def light_shadows(mi, spec: SceneSpec) -> np.ndarray:
    """(L, H, W) uint8 shadow code of every light of `spec` at every pixel centre (JIT variants)."""
    import drjit as dr

    from msps_render.render.ground_truth import _centre_hits
    from msps_render.render.scene_dict import _sensor, geometry_shapes

    if not dr.is_jit_v(mi.Float):
        raise InputError("dataset.storage.store_shadows", f"per-light shadow masks need a JIT variant "
                                                          f"(llvm_*/cuda_*); this render uses {mi.variant()}")
    W, H = spec.camera.width, spec.camera.height
    scene = mi.load_dict({"type": "scene", "sensor": _sensor(mi, spec), **geometry_shapes(mi, spec)})
    _, si, valid, n = _centre_hits(mi, scene, scene.sensors()[0], W, H)
    p, ng, n = si.p, mi.Vector3f(si.n), mi.Vector3f(n)
    dr.eval(p, ng, n, valid)
    lights = spec.lights
    out = np.zeros((len(lights), H, W), np.uint8)
    for k0 in range(0, len(lights), LIGHTS_PER_LAUNCH):
        chunk = lights[k0:k0 + LIGHTS_PER_LAUNCH]
        out[k0:k0 + len(chunk)] = _chunk(mi, scene, p, ng, n, valid, chunk, W * H).reshape(len(chunk), H, W)
    return out


def _chunk(mi, scene, p, ng, n, valid, lights, n_pix: int) -> np.ndarray:
    """Shadow codes of `lights` (one launch): every pixel's hit replicated once per light."""
    import drjit as dr

    idx = dr.arange(mi.UInt32, len(lights) * n_pix)
    pix, k = idx % n_pix, idx // n_pix
    dirs = np.array([l.direction for l in lights], np.float32)
    pos = np.array([[c * l.distance for c in l.direction] if l.kind == "point" else [0.0] * 3 for l in lights],
                   np.float32)
    is_point = dr.gather(mi.Bool, mi.Bool(np.array([l.kind == "point" for l in lights])), k)
    d = dr.gather(mi.Vector3f, mi.Vector3f(dirs[:, 0], dirs[:, 1], dirs[:, 2]), k)
    q = dr.gather(mi.Point3f, mi.Point3f(pos[:, 0], pos[:, 1], pos[:, 2]), k)
    x = dr.gather(mi.Point3f, p, pix)
    hit = dr.gather(mi.Bool, valid, pix)
    to = q - x
    dist = dr.norm(to)
    l = dr.select(is_point, to / dr.maximum(dist, 1e-12), d)
    attached = hit & (dr.dot(dr.gather(mi.Vector3f, n, pix), l) <= 0)
    g = dr.gather(mi.Vector3f, ng, pix)
    # the origin offset along the geometric normal to the light's side, as Mitsuba's `spawn_ray`
    mag = (1.0 + dr.maximum(dr.maximum(dr.abs(x.x), dr.abs(x.y)), dr.abs(x.z))) * mi.math.RayEpsilon
    o = dr.fma(dr.mulsign(mag, dr.dot(g, l)), g, x)
    ray = mi.Ray3f(o, l)
    ray.maxt = dr.select(is_point, dist * (1.0 - mi.math.ShadowEpsilon), dr.largest(mi.Float))
    blocked = scene.ray_test(ray, hit & ~attached)
    code = dr.select(attached, SHADOW_ATTACHED, dr.select(blocked, SHADOW_CAST, SHADOW_LIT))
    return np.array(mi.UInt32(code), dtype=np.uint8)


def render_shadows(spec: SceneSpec, variant: str | None = None, threads: int | None = None) -> np.ndarray:
    """`light_shadows` of a spec in the given (or best) variant."""
    from msps_render.render.variant import activate, resolve_variant

    return light_shadows(activate(variant or resolve_variant(spec.mode), threads), spec)
