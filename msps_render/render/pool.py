"""Scenes kept alive across frames: a pooled shape's mesh and BVH are built once per worker, and
each frame only updates the loaded scene in place (`ScenePool`).

Why: `mi.load_dict` of a `paper-train` frame is almost all Embree's BVH build of the
20,480-triangle blob (as long as the render kernel itself; without the mesh the load takes
under a millisecond), and Mitsuba rebuilds the whole BVH whenever a shape's vertices change,
also through `mi.traverse` updates.  `paper-train` draws its objects from 9 blobs; from frame
to frame only the rotation, the material split, the materials and the lights change.  So a
pooled scene holds the shape's canonical (unrotated) mesh and:
- the frame's rotation R turns the camera and the lights instead (by R^T): the same image of
  the same object, up to float rounding (rays are traced in the object's frame);
- the material parts are a face attribute (`PART_ATTRIBUTE`), and the one-pass integrator takes
  each part's BSDF from a table (`set_part_bsdfs`) instead of the shape's own; the BSDFs are made in
  the worker's slots (`render.slots`), so a new mix of kinds the worker has seen keeps the kernel;
- the ground truth reads the part from that attribute and turns normals and depth back into the
  camera frame (`ground_truth.pooled_truth`).

Which frames (`poolable`): JIT variant, RGB, one-pass, directional lights, no environment, no
textures, a blobby or primitive shape (their canonical mesh is a pure function of the spec).
Every other frame is built fresh (`render.render`), as before.

Never a stale scene: the key (`pool_key`) holds everything a loaded scene bakes in (shape
parameters, camera, integrator, sampler, light count); every per-frame value (rotation, lights,
split, BSDFs) is set on every frame, on a new scene as on a reused one, so a frame's pixels do not
depend on which frames the worker rendered before (tests/test_pool.py).
"""
from __future__ import annotations

from collections import OrderedDict
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from msps_render.render.multilight import PART_ATTRIBUTE, integrator_dict
from msps_render.render.slots import BsdfSlots
from msps_render.render.scene_dict import BOUND_KEY, _bound, part_bsdfs, _sensor, camera_to_world, emitter_ids, \
    light_key, one_pass
from msps_render.scene.geometry import vertex_normals
from msps_render.scene.shapes import canonical_mesh, rotated_vertices, split_faces
from msps_render.scene.spec import SceneSpec
from msps_render.timing import StageTimer, stage

OBJECT_KEY = "object"
POOLED_SHAPES = ("blobby", "primitive")  # procedural shapes split vertices at creases after rotating
DEFAULT_MAX_SCENES = 16  # >= the 9 blobs of paper-train; a scene is ~3 MB (mesh + BVH)


def lit_by_table(spec: SceneSpec, mi) -> bool:
    """Can the one-pass integrator take this frame's lights from a table (pooled scenes, frames in
    batches)?  RGB, a JIT variant, directional lights only, no environment."""
    return (spec.mode == "rgb" and one_pass(spec, mi) and spec.environment is None
            and all(l.kind == "directional" for l in spec.lights))


def poolable(spec: SceneSpec, mi) -> bool:
    """Can this frame be rendered from a pooled scene (see the module docstring)?"""
    return (lit_by_table(spec, mi) and spec.shape.kind in POOLED_SHAPES
            and all(m.texture is None and m.blend is None for m in spec.materials))


def pool_key(spec: SceneSpec, variant: str) -> tuple:
    """What a loaded pooled scene bakes in: two frames with the same key can share it."""
    s, i = spec.shape, spec.integrator
    return (variant, s.kind, s.name, tuple(s.sh_coeffs), s.subdivisions, tuple(sorted(s.params.items())),
            float(s.radius), spec.camera, i.kind, i.max_depth, i.spp, i.sampler, len(spec.lights))


@dataclass
class PooledScene:
    """A loaded scene of one pooled shape, its parameters (traversed once) and its integrator."""

    scene: object
    params: object
    integrator: object
    vertices: np.ndarray  # canonical, float64 (the part split needs them rotated every frame)
    faces: np.ndarray
    sensor: object = None  # this frame's camera (turned by R^T); render and ground truth use it


class ScenePool:
    """Loaded scenes by `pool_key`, least recently used dropped beyond `max_scenes`.

    One per worker process, passed down explicitly (`render_frame(..., scenes=)`); counts
    `built` and `reused` for benchmarks and tests.
    """

    def __init__(self, max_scenes: int = DEFAULT_MAX_SCENES):
        self.max_scenes = max(1, int(max_scenes))
        self._scenes: OrderedDict[tuple, PooledScene] = OrderedDict()
        self._blank = None  # one BSDF for every pooled mesh (never evaluated: the part table is)
        self.bsdfs = BsdfSlots()  # the frames' part BSDFs (`render.slots`): kernels repeat across mixes
        self.batches = None  # the worker's `render.batch.BatchScenes` (frames in batches), made on first use
        self.built = 0
        self.reused = 0

    def __len__(self) -> int:
        return len(self._scenes)

    def clear(self) -> None:
        """Drop everything the pool keeps alive: scenes, batches and the BSDFs in its slots."""
        self._scenes.clear()
        self.bsdfs = BsdfSlots()
        self.batches = None

    def trim(self, keep: int | None) -> None:
        """Keep only the `keep` most recently used scenes (None: `max_scenes`; `render/memory.py`)."""
        limit = self.max_scenes if keep is None else max(0, keep)
        while len(self._scenes) > limit:
            self._scenes.popitem(last=False)

    @contextmanager
    def frame(self, spec: SceneSpec, mi, timer: StageTimer | None = None) -> Iterator[PooledScene]:
        """The pooled scene set up for `spec` (built on first use); its BSDFs are released after."""
        pooled = self._get(spec, mi, timer)
        try:
            _update(mi, pooled, spec, timer, self.bsdfs)
            yield pooled
        finally:
            pooled.integrator.set_part_bsdfs(None)  # the frame's BSDFs die now, before the next frame's
            pooled.sensor = None

    def _get(self, spec: SceneSpec, mi, timer: StageTimer | None) -> PooledScene:
        key = pool_key(spec, mi.variant())
        hit = self._scenes.get(key)
        if hit is not None:
            self._scenes.move_to_end(key)
            self.reused += 1
            return hit
        with stage(timer, "mesh"):
            v, f, _ = canonical_mesh(spec.shape)
            n = vertex_normals(v, f)
        if self._blank is None:
            self._blank = mi.load_dict({"type": "diffuse"})
        with stage(timer, "scene load"):
            pooled = _build(mi, spec, v, f, n, self._blank)
        self._scenes[key] = pooled
        self.built += 1
        self.trim(None)
        return pooled


def _build(mi, spec: SceneSpec, v: np.ndarray, f: np.ndarray, n: np.ndarray, blank) -> PooledScene:
    """Load the scene of `spec`'s shape in its object frame; per-frame values come from `_update`."""
    import drjit as dr

    props = mi.Properties()
    props["bsdf"] = blank
    m = mi.Mesh(OBJECT_KEY, len(v), len(f), props=props, has_vertex_normals=True)
    m.add_attribute(PART_ATTRIBUTE, 1, [0.0] * len(f))
    mp = mi.traverse(m)
    mp["vertex_positions"] = dr.ravel(mi.TensorXf(v.astype(np.float32)))
    mp["faces"] = dr.ravel(mi.TensorXu(f.astype(np.uint32)))
    mp["vertex_normals"] = dr.ravel(mi.TensorXf(n.astype(np.float32)))
    mp.update()
    integ = spec.integrator
    d = {"type": "scene", "sensor": _sensor(mi, spec), OBJECT_KEY: m, BOUND_KEY: _bound(mi),
         "integrator": integrator_dict(integ.kind, integ.max_depth, emitter_ids(spec), hide_emitters=True)}
    for k in range(len(spec.lights)):
        d[light_key(k)] = {"type": "directional", "direction": [0.0, 0.0, -1.0],
                           "irradiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}
    scene = mi.load_dict(d)
    return PooledScene(scene, mi.traverse(scene), scene.integrator(), v, f)


def _rotation(mi, R: np.ndarray):
    """The 4x4 `mi.ScalarTransform4f` of the rotation matrix R (3x3)."""
    M = np.eye(4)
    M[:3, :3] = R
    return mi.ScalarTransform4f(M.tolist())


def _toward(mi, d: np.ndarray):
    """A directional emitter's `to_world` for travel direction d (what Mitsuba builds from `direction`)."""
    d = d / np.linalg.norm(d)
    a = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    up = np.cross(d, a)
    return mi.ScalarTransform4f().look_at(origin=mi.ScalarPoint3f(0.0, 0.0, 0.0), target=mi.ScalarPoint3f(*d),
                                          up=mi.ScalarVector3f(*(up / np.linalg.norm(up))))


def _update(mi, pooled: PooledScene, spec: SceneSpec, timer: StageTimer | None, slots: BsdfSlots) -> None:
    """Set every per-frame value of `spec` on the pooled scene: the camera (a new sensor) and the
    lights turned by R^T, light irradiance, the part of each face and the part BSDFs (made in the
    worker's `slots`)."""
    R = np.asarray(spec.shape.rotation, dtype=np.float64)
    with stage(timer, "mesh"):  # the split is defined on the rotated mesh, exactly as `build_mesh` gives it
        v32 = rotated_vertices(spec.shape, pooled.vertices).astype(np.float32)
        parts = split_faces(v32, pooled.faces.astype(np.uint32), spec.split)
        used = np.flatnonzero(np.bincount(parts, minlength=len(spec.materials)))
    made = part_bsdfs(mi, spec, used.tolist(), timer, slots)  # in the worker's slots, as a fresh scene's
    bsdfs = [made.get(p) for p in range(len(spec.materials))]
    with stage(timer, "scene update"):
        # a new sensor every frame, not an update: its sampler's seed is set when it is created
        # (Mitsuba's samplers mix that seed with the one `mi.render` gets)
        d = _sensor(mi, spec)
        d["to_world"] = _rotation(mi, R.T) @ camera_to_world(mi, spec.camera)
        pooled.sensor = mi.load_dict(d)
        P = pooled.params
        for k, l in enumerate(spec.lights):
            P[f"{light_key(k)}.to_world"] = _toward(mi, R.T @ -np.asarray(l.direction, dtype=np.float64))
            P[f"{light_key(k)}.irradiance.value"] = mi.Color3f(*[float(c) for c in l.rgb])
        P[f"{OBJECT_KEY}.{PART_ATTRIBUTE}"] = mi.Float(parts.astype(np.float32))
        P.update()
        pooled.integrator.set_part_bsdfs(bsdfs)
