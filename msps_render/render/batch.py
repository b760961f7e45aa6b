"""Frames in batches: B pooled frames from ONE kernel launch (`dataset.batch_frames`, issue 45).

Why: a `paper-train` frame's render kernel is short (~25 ms on a CPU core, ~3 ms on a GPU) and each
launch has a fixed cost, so one launch per frame leaves the device waiting on per-frame Python work.

How (one-pass, no environment; all lights directional or all point lights; orthographic or perspective
cameras; generated or mesh-file shapes; RGB or spectral):
- one loaded scene holds every shape of the batch once, canonical (unrotated), each in its own cell
  of space (`placement`: a cell from the shape alone).  It stays loaded while its shapes suffice, so
  a fixed pool (paper-train's 9 blobs) builds its BVHs a few times per worker, then never again.
  Plain meshes, not instances: drjit traces a call over shapes for every shape alive, so B
  instances per shape made every kernel slower;
- frame b is seen by its own orthographic camera aimed at its shape's cell, turned by R_b^T as in the
  pooled scene (`render.pool`), standing `distance + b * STEP` from the cell's centre (an orthographic
  image does not depend on that distance): the B cameras form one `batch` sensor (a film B frames
  wide), and a camera ray's slot is read back from that distance (`multilight.FrameTable`).  A
  perspective image does depend on it: there every frame has a cell of its own (a shape seen twice in
  one batch is a copy, `slot_keys`) at its true distance, and the cell a camera ray hits names its slot;
- point lights (near LEDs) are positions in the frame's object frame about its cell's centre, with
  1/r^2 and an LED's cos^mu, as the unbatched integrator has them;
- spectral frames (narrow-band rigs) share the camera's bands and each light's spectrum shape (the
  batch key, `Bands`): one wavelength table per light, the frame's own irradiance a scale in the table;
- the one-pass integrator's batch mode takes the slot's lights and part BSDFs from tables (the part
  of a hit face from the slot's own split), and rays after the camera's stop within `reach`, so a
  frame's paths never meet another cell;
- ground truth: one ray per pixel centre of the whole batch film, one launch for all frames;
- textures and measured blends (`train-colour`): a batch with any such frame gives every frame its own
  mesh (`own_mesh`): its parts' faces with their own vertices and appearance attributes, as the
  unbatched scene's part meshes are, so a textured BSDF reads the frame's own values at a hit.

The images equal the same frames rendered one at a time in distribution, not bit for bit (the B
frames share one sampler; tests/test_batch.py measures it), so B is part of the config and its hash;
a stored spec alone re-renders its frame unbatched, and its shard (`msps render` of the config and
seed) reproduces the batched pixels.
"""
from __future__ import annotations

import hashlib
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from msps_render.frame import Frame
from msps_render.render.ground_truth import _centre_hits, _finish_geometry, constant_appearance
from msps_render.render.memory import frame_budget
from msps_render.render.multilight import FrameTable, integrator_dict, read_emitter_images
from msps_render.render.pool import POOLED_SHAPES, _rotation
from msps_render.render.render import _frame
from msps_render.render.slots import BsdfSlots, slot_kind
from msps_render.render.scene_dict import _bsdf, _sensor, camera_to_world, emitter_ids, mitsuba_mesh, one_pass
from msps_render.render.textures import ALBEDO, WEIGHT, subdivide_to_edge, vertex_attributes
from msps_render.render.variant import activate, resolve_variant
from msps_render.scene.families import crease_normals
from msps_render.scene.geometry import TriMesh, vertex_normals
from msps_render.scene.shapes import canonical_mesh, part_pieces, rotated_vertices, split_faces
from msps_render.scene.spec import SceneSpec
from msps_render.timing import StageTimer, stage

OBJECT_RADIUS = 1.5  # a batched shape must fit in this ball about its cell's centre (scene units)
MAX_SHAPES = 16  # shapes one batch scene keeps (paper-train draws from 9)
SHAPES_REMEMBERED = 256  # how many recent shapes' batch counts a worker keeps (a shape seen twice is kept)


def batch_key(spec: SceneSpec, variant: str) -> tuple:
    """What the frames of one launch must share: the camera, the integrator, the number of lights, their
    kind and (LEDs) their anisotropy, which the integrator's code holds."""
    i = spec.integrator
    key = (variant, spec.camera, i.kind, i.max_depth, i.spp, i.sampler, len(spec.lights))
    if light_kind(spec) == "point":
        key += ("point", anisotropy(spec))
    if spec.mode == "spectral":  # the camera's bands and each light's spectrum: the wavelength tables
        r = spec.rig
        key += ("spectral", spec.camera_response, None if r is None else (r.camera, r.filters),
                tuple(l.spectrum or l.rgb for l in spec.lights))
    return key


def light_kind(spec: SceneSpec) -> str | None:
    """"directional" or "point" when every light of the frame is of that kind, else None."""
    kinds = {l.kind for l in spec.lights}
    return kinds.pop() if len(kinds) == 1 else None


def anisotropy(spec: SceneSpec) -> tuple[float, ...]:
    """Per light, the LED exponent mu of a point light (cos^mu about its axis; 0: isotropic)."""
    mus = tuple(spec.rig.anisotropy) if spec.rig is not None and spec.rig.anisotropy else ()
    return tuple(float(m) for m in mus) + (0.0,) * (len(spec.lights) - len(mus))


def shape_key(spec: SceneSpec) -> tuple:
    s = spec.shape
    return (s.kind, s.name, tuple(s.sh_coeffs), s.subdivisions, tuple(sorted(s.params.items())), float(s.radius))


BATCHED_SHAPES = POOLED_SHAPES + ("procedural", "mesh")  # canonical meshes; procedural creases split unrotated


def lit_from_table(spec: SceneSpec, mi) -> bool:
    """Can the batch integrator take this frame's lights from its table?  One-pass (a JIT variant), no
    environment, all lights directional (`pool.lit_by_table`) or all point lights (near LEDs); RGB, or
    spectral with spectral channels (a rig of weights on R, G, B is refused by the unbatched path)."""
    spectral_ok = spec.mode == "spectral" and (spec.rig is None or spec.rig.is_spectral)
    return ((spec.mode == "rgb" or spectral_ok) and one_pass(spec, mi) and spec.environment is None
            and light_kind(spec) in ("directional", "point"))


@dataclass
class Bands:
    """A spectral batch's camera and light spectra (`render.spectral`): the camera's (len(GRID), M) bands,
    each light's spectrum shape (shared by the batch's frames: the batch key) and which lights the camera
    sees.  Light k of a frame emits shape_k * its own scale (`spectral.light_shape`)."""

    camera_id: object
    S: np.ndarray
    shapes: list
    visible: list  # light indices whose shape the camera sees (the others' images are 0, as unbatched)

    def scale(self, mi, spec: SceneSpec) -> list[float]:
        from msps_render.render.spectral import light_shape

        return [light_shape(mi, l, self.S)[1] for l in spec.lights]

    def responses(self, mi, spec: SceneSpec) -> np.ndarray:
        """(M, K): `spectral.light_responses` of the frame."""
        from msps_render.spectral.spectra import WL_STEP

        return np.stack([(sh * sc) @ self.S * WL_STEP for sh, sc in zip(self.shapes, self.scale(mi, spec))], 1)


def bands_of(mi, spec: SceneSpec) -> Bands | None:
    """The `Bands` of a spectral frame, None in RGB."""
    if spec.mode != "spectral":
        return None
    from msps_render.render.spectral import camera_bands, light_shape

    camera_id, S = camera_bands(spec)
    shapes = [light_shape(mi, l, S)[0] for l in spec.lights]
    return Bands(camera_id, S, shapes, [k for k, sh in enumerate(shapes) if (sh @ S).sum() > 0])


def batchable(specs: list[SceneSpec], mi) -> bool:
    """Can these frames share one launch?  RGB, one-pass, all lights directional or all point lights, no
    environment, generated or mesh-file shapes (`BATCHED_SHAPES`), textures and blends allowed, seen by
    orthographic or perspective cameras (`layout` bounds their rays), with one batch key."""
    return (len(specs) > 1
            and all(lit_from_table(s, mi) and s.shape.kind in BATCHED_SHAPES
                    and s.camera.kind in ("orthographic", "perspective") for s in specs)
            and len({batch_key(s, mi.variant()) for s in specs}) == 1)


def needs_own_meshes(specs: list[SceneSpec]) -> bool:
    """Does a frame of the batch have textures or measured blends?  Their BSDFs read per-vertex
    attributes of the mesh they hit, so then every frame gets its own mesh (`own_mesh`)."""
    return any(m.texture is not None or m.blend is not None for s in specs for m in s.materials)


def mesh_key(spec: SceneSpec, own: bool) -> tuple:
    """What a batch scene's mesh is made from: the shape alone (shared by every frame of that shape), or,
    for an own mesh, the whole frame (its split, rotation and materials)."""
    if not own:
        return shape_key(spec)
    return ("own", hashlib.sha256(spec.to_json(indent=None).encode()).hexdigest())


def frames_per_launch(batch_frames: int, spec: SceneSpec) -> int:
    """How many frames a launch renders for `dataset.batch_frames` and frames like `spec`: the setting,
    capped by the worker's memory budget for its light count (`render.memory.frame_budget`), counted
    in three-channel images (a spectral rig's M channels per light: M / 3 lights' worth of film)."""
    rig = spec.rig
    m = len(rig.channel_names) if spec.mode == "spectral" and rig is not None and rig.is_spectral else 3
    return max(1, min(int(batch_frames), frame_budget(-(-len(spec.lights) * max(m, 3) // 3)).batch))


def launch_groups(n_frames: int, batch_frames: int, spec_of) -> Iterator[range]:
    """A shard's frames 0..n-1 as its launches take them: consecutive groups of `frames_per_launch`
    frames (`spec_of(j)`: frame j's scene).  The worker (`pipeline/execute.py`) and an export's
    re-render (`export/source.py`) both group by it, so a frame is always re-rendered in its batch."""
    start = 0
    while start < n_frames:
        k = frames_per_launch(batch_frames, spec_of(start))
        yield range(start, min(start + k, n_frames))
        start += k


@dataclass
class BatchMesh:
    """A mesh of a batch scene, unrotated (object frame): shared by the frames of its shape, or one
    frame's own (`own_mesh`: with its face parts and appearance attributes)."""

    vertices: np.ndarray  # float64 (V, 3)
    faces: np.ndarray  # (F, 3)
    normals: np.ndarray  # (V, 3)
    parts: np.ndarray | None = None  # own mesh: the part of every face (fixed: the split is the frame's)
    attributes: dict | None = None  # own mesh: name -> (V, C) float32 (`render.textures`)

    @property
    def n_faces(self) -> int:
        return len(self.parts) if self.parts is not None else len(self.faces)

    def built(self) -> "BatchMesh":
        """What a loaded scene still needs of this mesh.  An own mesh keeps only its face parts and the
        names of its attributes: its arrays (tens of MB for a textured frame) are in the scene now, and
        no later scene is built from them (own meshes are never kept for the next batch)."""
        if self.parts is None:
            return self
        empty = np.zeros((0, 3))
        return BatchMesh(empty, empty.astype(np.int64), empty, self.parts, dict.fromkeys(self.attributes or ()))


def shared_mesh(spec: SceneSpec) -> BatchMesh:
    return BatchMesh(*batch_mesh(spec))


def own_mesh(spec: SceneSpec) -> BatchMesh:
    """One frame's mesh as the unbatched scene builds its part meshes (`scene_dict._shapes`), unrotated:
    subdivided for its textures, split into its parts on the rotated vertices, each part's faces with
    their own vertex copies and its material's attributes (`vertex_attributes`, object frame), the parts
    one after another in one mesh."""
    v, f, n = batch_mesh(spec)
    uv = canonical_mesh(spec.shape)[2] if spec.shape.kind != "procedural" else None
    textures = [m.texture for m in spec.materials if m.texture is not None]
    if textures:
        mesh = subdivide_to_edge(TriMesh(v, f, n, uv), min(t.max_edge for t in textures))
        v, f, n, uv = np.asarray(mesh.vertices, np.float64), mesh.faces, mesh.normals, mesh.uv
    part = split_faces(rotated_vertices(spec.shape, v).astype(np.float32), np.asarray(f, np.uint32), spec.split)
    vs, fs, ns, ps, at = [], [], [], [], {}
    base = 0
    for p, used, faces in part_pieces(f, part, len(v)):
        vs.append(v[used])
        ns.append(np.asarray(n, np.float64)[used])
        fs.append(faces + base)
        ps.append(np.full(len(faces), p, np.uint32))
        for name, a in vertex_attributes(spec.materials[p], v[used], ns[-1], None if uv is None else uv[used]).items():
            at.setdefault(name, []).append(np.asarray(a, np.float32))
        base += len(used)
    return BatchMesh(np.concatenate(vs), np.concatenate(fs), np.concatenate(ns), np.concatenate(ps),
                     {k: np.concatenate(a) for k, a in at.items()})


def batch_mesh(spec: SceneSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices float64, faces, vertex normals) of the shape, unrotated: the frame's camera turns instead.
    Procedural shapes split their vertices at creases as `build_mesh` does, here before the rotation
    (dihedral angles do not change with it; only float rounding near the threshold can)."""
    v, f, _ = canonical_mesh(spec.shape)
    if spec.shape.kind == "procedural":
        v, f, n = crease_normals(v, f)
        return np.asarray(v, np.float64), np.asarray(f), np.asarray(n, np.float64)
    return v, f, vertex_normals(v, f)


STEP = 0.25  # slot b's camera stands distance + b * STEP from its cell's centre


def layout(spec: SceneSpec, n_slots: int) -> tuple[float, float]:
    """(spacing of the cells, reach of every ray after the camera's).
    A later ray starts on the object (within `OBJECT_RADIUS` of its cell's centre) and any surface that
    can shadow it is within `2 * OBJECT_RADIUS`: `reach` is a little more.  A camera ray runs from its
    camera to the far clip, `OBJECT_RADIUS` past the centre along the axis: orthographic, the farthest
    camera stands `distance + (B - 1) * STEP` from the centre, at most `extent * sqrt 2` off the axis;
    perspective, the camera stands `distance` away and a ray reaches `(distance + OBJECT_RADIUS) / cos`
    of the half-diagonal field of view past it.  Cells are far enough apart that neither comes within
    `OBJECT_RADIUS` of another cell's centre."""
    c = spec.camera
    reach = 2.0 * OBJECT_RADIUS + 0.5
    if c.kind == "perspective":
        t = np.tan(np.radians(c.fov_deg) / 2.0) * np.hypot(1.0, max(c.width, c.height) / min(c.width, c.height))
        camera_reach = c.distance + (c.distance + OBJECT_RADIUS) * float(np.hypot(1.0, t))
    else:
        camera_reach = float(np.hypot(c.distance + (n_slots - 1) * STEP, c.extent * np.sqrt(2.0)))
    return max(camera_reach, OBJECT_RADIUS + reach) + OBJECT_RADIUS + 1.0, reach


def slot_keys(specs: list[SceneSpec], keys: list[tuple]) -> list[tuple]:
    """The key of each frame's cell.  Orthographic frames of one shape share its cell (the camera's
    distance names the slot); a perspective image depends on that distance, so there every frame has
    a cell of its own and the cell names the slot: a shape's second frame of the batch is a copy."""
    if specs[0].camera.kind != "perspective":
        return keys
    seen: dict[tuple, int] = {}
    out = []
    for k in keys:
        n = seen.get(k, 0)
        seen[k] = n + 1
        out.append(k if n == 0 else ("copy", n, k))
    return out


def mesh_of(key: tuple) -> tuple:
    """The mesh key a cell key stands for (`slot_keys`: a copy's is its shape's)."""
    return key[2] if key[0] == "copy" else key


LATTICE = 16  # a shape's home cell is one of LATTICE x LATTICE places in the (y, z) plane


def home_cell(key: tuple) -> tuple[int, int]:
    """Where a shape lives, from the shape alone (a stable hash): never from the worker's history."""
    h = hashlib.sha256(repr(key).encode()).digest()
    return h[0] % LATTICE - LATTICE // 2, h[1] % LATTICE - LATTICE // 2


def placement(specs: list[SceneSpec], keys: list[tuple] | None = None) -> list[tuple[int, int]]:
    """The (y, z) cell of each frame's shape: its home, or the next free cell (row-major) when a shape
    earlier in this batch holds it.  A pure function of the batch, so a frame's pixels do not depend
    on which batches the worker rendered before (the float rounding of a ray does depend on where its
    cell lies, so cells must be reproducible: tests/test_batch.py)."""
    keys = keys if keys is not None else [shape_key(s) for s in specs]  # (`mesh_key`)
    taken: dict[tuple[int, int], tuple] = {}
    where: dict[tuple, tuple[int, int]] = {}
    for k in keys:
        if k in where:
            continue
        c = home_cell(k)
        while c in taken:
            n = (c[0] + LATTICE // 2) * LATTICE + c[1] + LATTICE // 2 + 1
            c = ((n // LATTICE) % LATTICE - LATTICE // 2, n % LATTICE - LATTICE // 2)
        taken[c] = k
        where[k] = c
    return [where[k] for k in keys]


@dataclass
class BatchScene:
    """A loaded scene: each shape once, canonical, at the centre of its cell."""

    scene: object
    integrator: object
    cells: dict  # (i, j) cell -> mesh_key
    meshes: dict  # mesh_key -> BatchMesh
    spacing: float
    reach: float
    bands: Bands | None = None  # spectral: the camera's bands and the lights' spectra (the batch key's)

    @property
    def lights(self) -> list[int] | None:
        """The lights the launch traces (spectral: those the camera sees), None: all."""
        return None if self.bands is None else self.bands.visible

    def centre(self, cell: tuple[int, int]) -> np.ndarray:
        return np.array([0.0, cell[0] * self.spacing, cell[1] * self.spacing])


class BatchScenes:
    """The worker's batch scene, rebuilt only when a batch needs a shape at a cell it does not hold
    (keeping up to `MAX_SHAPES` earlier placements that do not clash), so a fixed shape pool
    (paper-train's 9 blobs) is loaded a few times per worker, then never again."""

    def __init__(self):
        self._scenes: OrderedDict[tuple, BatchScene] = OrderedDict()
        self._meshes: dict[tuple, tuple] = {}  # the shapes of the loaded scene and of the batch
        self._batches_of: OrderedDict[tuple, int] = OrderedDict()  # batches each recent shape was in
        self._ahead: dict[tuple, Future] = {}  # mesh_key -> its mesh, being built for the next batch
        self._thread: ThreadPoolExecutor | None = None
        self.bsdfs = BsdfSlots()
        self.built = 0

    def prepare(self, specs: list[SceneSpec]) -> None:
        """Start building the meshes of a coming batch in a thread, while the current batch renders.

        Why: a procedural shape (`train`: new every frame) takes ~0.1 s of numpy to build, and drjit
        runs a kernel without holding the GIL, so the next batch's shapes are built on another core
        (on a GPU, by the CPU that waits for the kernel).  A mesh is a pure function of its shape, so
        where it is built does not change a byte."""
        own = needs_own_meshes(specs)
        for s in specs:
            k = mesh_key(s, own)
            if k not in self._meshes and k not in self._ahead:
                if self._thread is None:
                    self._thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="msps-batch-mesh")
                self._ahead[k] = self._thread.submit(own_mesh if own else shared_mesh, s)
        while len(self._ahead) > 4 * MAX_SHAPES:  # never taken (a batch that failed): dropped
            self._ahead.pop(next(iter(self._ahead))).cancel()

    def _mesh(self, spec: SceneSpec, key: tuple, own: bool) -> BatchMesh | None:
        """The batch mesh of a cell key when this scene does not hold it yet (a copy's shape's, the one
        `prepare` started, else built now); None when it does."""
        base = mesh_of(key)
        ahead = self._ahead.pop(base, None)
        if key in self._meshes:
            return None
        if base in self._meshes:
            return self._meshes[base]
        if ahead is not None:
            return ahead.result()
        return own_mesh(spec) if own else shared_mesh(spec)

    def get(self, specs: list[SceneSpec], mi, timer: StageTimer | None) -> tuple[BatchScene, list, list]:
        """(the scene, each frame's cell, each frame's `mesh_key`)."""
        key = (batch_key(specs[0], mi.variant()), len(specs))
        own = needs_own_meshes(specs)
        keys = slot_keys(specs, [mesh_key(s, own) for s in specs])
        cells = placement(specs, keys)
        wanted = dict(zip(cells, keys))
        have = self._scenes.get(key)
        if have is not None and all(have.cells.get(c) == k for c, k in wanted.items()):
            return have, cells, keys
        with stage(timer, "texture" if own else "mesh"):
            for s, k in zip(specs, keys):
                got = self._mesh(s, k, own)
                if got is not None:
                    r = float(np.max(np.linalg.norm(got.vertices, axis=1)))
                    if r > OBJECT_RADIUS:
                        name = s.shape.name or s.shape.kind
                        raise ValueError(f"shape {name} reaches {r:.2f} from its centre, beyond the "
                                         f"{OBJECT_RADIUS} a batched frame allows")
                    self._meshes[k] = got
        for k in dict.fromkeys(wanted.values()):
            self._batches_of[k] = self._batches_of.pop(k, 0) + 1
        while len(self._batches_of) > SHAPES_REMEMBERED:
            self._batches_of.popitem(last=False)
        # earlier shapes stay only if shapes repeat (a fixed pool); new shapes every frame would only
        # make every build longer
        kept = {c: k for c, k in (have.cells.items() if have is not None else ())
                if c not in wanted and self._batches_of.get(k, 0) > 1 and mesh_of(k)[0] != "own"}
        if len(set(kept.values()) | set(wanted.values())) > MAX_SHAPES:
            kept = {}
        live = set(kept.values()) | set(wanted.values())
        self._meshes = {k: m for k, m in self._meshes.items() if k in live}
        # the old scene dies (every reference to it) before the new one is made: its memory (meshes,
        # BVH) is released first
        have = None
        self._scenes.clear()
        with stage(timer, "scene load"):
            bs = _build(mi, specs[0], {**kept, **wanted}, self._meshes, len(specs))
        self._meshes = {k: m for k, m in self._meshes.items() if m.parts is None}  # own meshes: in the scene only
        self._scenes[key] = bs
        self.built += 1
        return bs, cells, keys


def _build(mi, spec: SceneSpec, cells: dict, meshes: dict, n_slots: int) -> BatchScene:
    spacing, reach = layout(spec, n_slots)
    blank = mi.load_dict({"type": "diffuse"})  # never evaluated: the frame table's BSDFs are
    d: dict = {"type": "scene"}
    for c, k in sorted(cells.items()):
        bm = meshes[k]
        props = mi.Properties()
        props["bsdf"] = blank
        centre = np.array([0.0, c[0] * spacing, c[1] * spacing])
        name = f"cell{c[0]}_{c[1]}".replace("-", "m")
        m, params = mitsuba_mesh(mi, name, (bm.vertices + centre).astype(np.float32), bm.faces,
                                 bm.normals.astype(np.float32), props)
        for attr, a in (bm.attributes or {}).items():  # as `scene_dict._shapes` adds them (a list: fast)
            m.add_attribute(attr, a.shape[1], np.ascontiguousarray(a, np.float32).ravel().tolist())
        params.update()
        d[name] = m
    integ = spec.integrator
    bands = bands_of(mi, spec)
    lights = list(range(len(spec.lights))) if bands is None else bands.visible
    mus = anisotropy(spec)
    d["integrator"] = integrator_dict(integ.kind, integ.max_depth, [emitter_ids(spec)[k] for k in lights],
                                      hide_emitters=True, anisotropy=[mus[k] for k in lights] if any(mus) else (),
                                      channels=3 if bands is None else bands.S.shape[1])
    scene = mi.load_dict(d)
    if bands is not None and lights:  # light k emits a flat unit spectrum, its shape folded into its bands
        from msps_render.spectral.spectra import GRID

        scene.integrator().set_bands(GRID, {emitter_ids(spec)[k]: bands.S * bands.shapes[k][:, None] for k in lights})
    used = set(cells.values())
    return BatchScene(scene, scene.integrator(), dict(cells), {k: meshes[k].built() for k in used}, spacing, reach,
                      bands)


def _batch_sensor(mi, specs: list[SceneSpec], bs: BatchScene, cells: list):
    """One `batch` sensor: slot b's camera aimed at its cell, turned by R_b^T, standing `distance + b * STEP`
    from the centre (orthographic), or `distance` (perspective: its own cell names the slot)."""
    T = mi.ScalarTransform4f
    first = _sensor(mi, specs[0])
    c = specs[0].camera
    film = dict(first["film"], width=c.width * len(specs))
    d = {"type": "batch", "film": film, "sampler": first["sampler"]}
    for b, s in enumerate(specs):
        sub = _sensor(mi, s)
        sub.pop("sampler")
        R = np.asarray(s.shape.rotation, dtype=np.float64)
        cam = c if c.kind == "perspective" else c.model_copy(update={"distance": c.distance + b * STEP})
        sub["to_world"] = (T().translate(bs.centre(cells[b]).tolist()) @ _rotation(mi, R.T)
                           @ camera_to_world(mi, cam))
        sub["far_clip"] = cam.distance + OBJECT_RADIUS
        d[f"camera{b}"] = sub
    return mi.load_dict(d)


def _frame_table(mi, specs: list[SceneSpec], keys: list, cells: list, bs: BatchScene, slots: "BsdfSlots",
                 timer: StageTimer | None):
    """The lights, face parts and part BSDFs of every slot (and each frame's face parts, for its truth).
    A light is its direction (directional) or its position (point), turned into the object frame."""
    import drjit as dr

    B = len(specs)
    lights = bs.lights if bs.lights is not None else list(range(len(specs[0].lights)))
    K = len(lights)
    F = max(m.n_faces for m in bs.meshes.values())
    P = max(len(s.materials) for s in specs)
    dirs = np.zeros((B, K, 3), np.float32)
    rgb = np.zeros((B, K, 3), np.float32)
    face_part = np.zeros((B, F), np.uint32)
    parts, keep, wanted = [], [], []
    table = dr.zeros(mi.BSDFPtr, B * P)
    point = light_kind(specs[0]) == "point"
    for b, s in enumerate(specs):
        R = np.asarray(s.shape.rotation, dtype=np.float64)
        scale = bs.bands.scale(mi, s) if bs.bands is not None else None
        for k, n in enumerate(lights):
            l = s.lights[n]
            # a point light stands at direction * distance (`scene_dict`)
            at = np.asarray(l.direction, dtype=np.float64) * (l.distance if point else 1.0)
            dirs[b, k] = R.T @ at
            rgb[b, k] = l.rgb if scale is None else (scale[n],) * 3  # spectral: its spectrum's scale
        bm = bs.meshes[keys[b]]
        if bm.parts is not None:  # an own mesh: split when it was made
            p = bm.parts
        else:
            with stage(timer, "mesh"):  # the split of the rotated mesh, exactly as the unbatched frame's
                v32 = rotated_vertices(s.shape, bm.vertices).astype(np.float32)
                p = split_faces(v32, bm.faces.astype(np.uint32), s.split)
        face_part[b, :len(p)] = p
        parts.append(p)
        used = np.flatnonzero(np.bincount(p, minlength=len(s.materials)))
        wanted += [(slot_kind(s.materials[q]), b, q) for q in used.tolist()]
    made = slots.fill([(kind, lambda b=b, q=q: _bsdf(mi, specs[b], q, timer)) for kind, b, q in sorted(wanted)])
    keep.extend(made)
    # one scatter of all pointers as data (a scatter per BSDF bakes its pointer into a new kernel each time)
    dr.scatter(table, mi.BSDFPtr(made), mi.UInt32([b * P + q for _, b, q in sorted(wanted)]))

    def opaque(a, cls):
        x = cls(a)
        dr.make_opaque(x)
        return x

    dr.make_opaque(table)
    cell_slot = None
    if specs[0].camera.kind == "perspective":  # every frame in a cell of its own (`slot_keys`)
        where = np.zeros(LATTICE * LATTICE, np.uint32)
        for b, (i, j) in enumerate(cells):
            where[(i + LATTICE // 2) * LATTICE + j + LATTICE // 2] = b
        cell_slot = opaque(where, mi.UInt32)
    ft = FrameTable(n_frames=B, n_lights=K, spacing=bs.spacing, distance=float(specs[0].camera.distance),
                    step=STEP, reach=bs.reach,
                    light_d=tuple(opaque(dirs[..., i].ravel(), mi.Float) for i in range(3)),
                    light_e=tuple(opaque(rgb[..., i].ravel(), mi.Float) for i in range(3)),
                    face_part=opaque(face_part.ravel(), mi.UInt32), face_stride=opaque(np.uint32(F), mi.UInt32),
                    part_stride=opaque(np.uint32(P), mi.UInt32), bsdfs=table, keep=keep,
                    point=point, cell_slot=cell_slot, lattice=LATTICE)
    return ft, parts


def _truth(mi, scene, sensor, specs: list[SceneSpec], bs: BatchScene, cells: list,
           parts: list[np.ndarray]) -> list[tuple]:
    """`pooled_truth` of every frame from one ray per pixel centre of the whole batch film."""
    import drjit as dr

    c = specs[0].camera
    W, H, B = c.width, c.height, len(specs)
    _, si, valid, n = _centre_hits(mi, scene, sensor, W * B, H)
    prim = dr.select(valid, si.prim_index, 0)
    own = all(m.attributes is not None for m in bs.meshes.values())
    if own:  # every mesh carries the attributes: read them back at the hits, as `appearance_truth` does
        a = si.shape.eval_attribute_3(ALBEDO, si, valid)
        w = si.shape.eval_attribute_1(WEIGHT, si, valid)
        dr.eval(valid, n, si.p, prim, a, w)
        a_all = np.stack([np.array(a.x), np.array(a.y), np.array(a.z)], -1).reshape(H, B, W, 3)
        w_all = np.array(w).reshape(H, B, W)
    dr.eval(valid, n, si.p, prim)
    mask_all = np.array(valid, dtype=bool).reshape(H, B, W)
    n_all = np.stack([np.array(n.x), np.array(n.y), np.array(n.z)], -1).reshape(H, B, W, 3).astype(np.float64)
    p_all = np.stack([np.array(si.p.x), np.array(si.p.y), np.array(si.p.z)], -1).reshape(H, B, W, 3)
    prim_all = np.array(prim).reshape(H, B, W)
    out = []
    for b, s in enumerate(specs):
        R = np.asarray(s.shape.rotation, dtype=np.float64)
        mask = mask_all[:, b].reshape(-1)
        centre = bs.centre(cells[b])
        normal = n_all[:, b].reshape(-1, 3) @ R.T
        p = p_all[:, b].reshape(-1, 3).astype(np.float64) - centre
        depth = (c.distance - p @ R[2]).astype(np.float32)
        part = np.where(mask, parts[b][prim_all[:, b].reshape(-1)], -1).astype(np.int8)
        normal, mask, depth, part = _finish_geometry(normal, mask, depth, part, W, H)
        if own:
            albedo = np.where(mask[..., None], a_all[:, b], 0.0).astype(np.float32)
            blend = np.where(mask, w_all[:, b], 0.0).astype(np.float32)
        else:
            albedo, blend = constant_appearance(s, part)
        out.append((normal, mask, depth, part, albedo, blend))
    return out


def render_batch(specs: list[SceneSpec], variant: str | None = None, threads: int | None = None,
                 per_light: bool = False, timer: StageTimer | None = None,
                 scenes: BatchScenes | None = None) -> list[Frame]:
    """Render `specs` (see `batchable`) in one launch; one Frame each, as `render_frame` gives them."""
    variant = variant or resolve_variant(specs[0].mode)
    mi = activate(variant, threads)
    if not batchable(specs, mi):
        raise ValueError("these frames cannot share a launch (render.batch.batchable)")
    scenes = scenes if scenes is not None else BatchScenes()
    bs, cells, keys = scenes.get(specs, mi, timer)
    table, parts = _frame_table(mi, specs, keys, cells, bs, scenes.bsdfs, timer)
    with stage(timer, "scene update"):
        sensor = _batch_sensor(mi, specs, bs, cells)
    ids = emitter_ids(specs[0]) if bs.lights is None else [emitter_ids(specs[0])[k] for k in bs.lights]
    try:
        bs.integrator.set_batch(table)
        with stage(timer, "ground truth"):
            truths = _truth(mi, bs.scene, sensor, specs, bs, cells, parts)
        with stage(timer, "render"):
            if ids:
                image = mi.render(bs.scene, sensor=sensor, spp=specs[0].integrator.spp, seed=specs[0].integrator.seed)
                images = read_emitter_images(image, bs.integrator.aov_names(), ids)
            else:  # no light the camera sees (spectral): geometry only, as unbatched
                c = specs[0].camera
                images = np.zeros((0, c.height, c.width * len(specs), bs.bands.S.shape[1]), np.float32)
    finally:
        bs.integrator.set_batch(None)  # the batch's BSDFs die with it
    W = specs[0].camera.width
    if bs.bands is None:
        return [_frame(mi, s, variant, truths[b], images[:, :, b * W:(b + 1) * W], per_light)
                for b, s in enumerate(specs)]
    from msps_render.render.spectral import spectral_frame

    out = []
    for b, s in enumerate(specs):
        mine = images[:, :, b * W:(b + 1) * W]
        zero = np.zeros(mine.shape[1:], np.float32)
        per = [mine[bs.lights.index(k)] if k in bs.lights else zero for k in range(len(s.lights))]
        out.append(spectral_frame(mi, s, variant, truths[b][:4], per, bs.bands.S, bs.bands.responses(mi, s),
                                  bs.bands.camera_id, None, per_light, "emission x camera", "one-pass"))
    return out
