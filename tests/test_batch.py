"""Frames in batches (render/batch.py, `dataset.batch_frames`): B pooled frames from one kernel launch.

What must hold: the closed form at B > 1 (a Lambertian ball per slot, each with its own rotation and
lights), exact ground truth (the same mask and parts as one frame at a time, normals and depth to
float rounding), images equal to the unbatched frames in distribution (the difference is the noise
between two seeds, no more), determinism, and shards: `batch_frames = 1` is the config (and hash)
of before, B > 1 renders, verifies and reproduces itself byte for byte."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import binary_erosion

from msps_render.render import render_frame
from msps_render.render.pool import ScenePool
from msps_render.scene.lights import three_lights
from msps_render.scene.materials import lambertian
from msps_render.scene.spec import CameraSpec, IntegratorSpec, SceneSpec, ShapeSpec

pytest.importorskip("mitsuba")

RHO, E = 0.7, 3.0


def _rotation(rng) -> tuple:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return tuple(tuple(float(x) for x in row) for row in q)


def _balls(n: int, kind: str = "direct", spp: int = 8) -> list[SceneSpec]:
    """n Lambertian balls (a blob with no SH terms: a subdivided icosphere), each turned its own way and
    lit by three coloured lights of its own slant and tilt."""
    rng = np.random.default_rng(5)
    out = []
    for b in range(n):
        lights = three_lights(20.0 + 10.0 * b, tuple(float(t) + 15.0 * b for t in (0, 120, 240)), irradiance=E)
        out.append(SceneSpec(shape=ShapeSpec(kind="blobby", name="ball", sh_coeffs=(), subdivisions=5, radius=0.95,
                                             rotation=_rotation(rng)),
                             materials=(lambertian((RHO,) * 3),), lights=lights,
                             camera=CameraSpec(width=64, height=64),
                             integrator=IntegratorSpec(kind=kind, spp=spp, max_depth=4, seed=3 + b)))
    return out


def test_each_batched_frame_matches_the_lambertian_closed_form(rgb_variant):
    """Four balls in one launch: light k's image of frame b is rho/pi E_k max(n.l_k, 0) with n the frame's
    own ground-truth normal (the mesh's shading normal, which the renderer also uses) and l_k its own
    lights.  Same tolerance argument as tests/test_multilight.py (pixel-footprint averaging < 0.1 %
    away from the rim, pixel-position noise < 0.2 % at 8 spp): 1 % mean relative error.  A frame that
    read another slot's lights or rotation is off by tens of per cent."""
    from msps_render.render.batch import render_batch

    specs = _balls(4)
    frames = render_batch(specs, rgb_variant, threads=1, per_light=True)
    dark_values = []
    for b, (s, f) in enumerate(zip(specs, frames)):
        inner = binary_erosion(f.mask, iterations=2)
        assert inner.mean() > 0.4, b  # the ball fills the frame: the comparison means something
        for k, l in enumerate(s.lights):
            cos = np.clip(f.normal @ np.array(l.direction), 0, None)
            lit = inner & (cos > 0.05)
            for c in range(3):
                expected = RHO / np.pi * l.rgb[c] * cos[lit]
                rel = np.abs(f.per_light[k][..., c][lit] - expected) / expected
                assert lit.sum() > 1000 and rel.mean() < 0.01, (b, k, c, rel.mean())
            dark_values.append(f.per_light[k][inner & (f.normal @ np.array(l.direction) < -0.05)].ravel())
        assert np.array_equal(f.image, f.per_light.sum(0).astype(np.float32))
    dark = np.concatenate(dark_values)
    assert dark.size > 100 and dark.max() == 0.0  # convex, no environment: unlit is black


def test_batched_truth_is_the_unbatched_truth_and_images_differ_by_noise_only(rgb_variant, paper_specs):
    """paper-train's first 4 frames, batched and one at a time: the same mask and parts, normals and
    depth to float rounding (the cells sit up to ~80 units out), constant albedo
    equal.  Images: the mean |batched - unbatched| over the object is the mean |seed a - seed b| of
    the unbatched frame (two independent renders differ by sqrt 2 sigma either way): within 15 %
    (observed 0-5 %), and the object's mean radiance within 1 %.  A frame with another frame's lights,
    rotation or materials differs by O(1)."""
    from msps_render.render.batch import render_batch

    specs = paper_specs[:4]
    batched = render_batch(specs, rgb_variant, threads=1)
    pool = ScenePool()
    for b, s in enumerate(specs):
        one = render_frame(s, rgb_variant, threads=1, scenes=pool)
        other = render_frame(s.model_copy(update={"integrator": s.integrator.model_copy(
            update={"seed": s.integrator.seed + 7})}), rgb_variant, threads=1, scenes=pool)
        f, m = batched[b], one.mask
        assert np.array_equal(f.mask, one.mask) and np.array_equal(f.part, one.part), b
        assert m.mean() > 0.15, b
        # 99 % of pixels within 6e-5 (the cells sit up to ~70 units out); a grazing pixel may turn its
        # normal's facing sign or slide along the surface with the rounding (<= 1 of ~7000 per frame seen)
        off = (np.abs(f.normal - one.normal).max(-1) > 1e-3) | (np.abs(f.depth - one.depth) > 1e-3)
        assert off.sum() <= max(2, 5e-4 * m.sum()), (b, off.sum())
        assert np.abs(f.depth - one.depth).max() < 1e-2, b  # observed <= 1.4e-3
        assert np.array_equal(f.albedo, one.albedo), b
        d_batch = np.abs(f.image - one.image)[m].mean()
        d_seed = np.abs(other.image - one.image)[m].mean()
        assert d_seed > 0 and abs(d_batch / d_seed - 1) < 0.15, (b, d_batch, d_seed)
        assert abs(f.image[m].mean() / one.image[m].mean() - 1) < 0.01, b


def test_batched_frames_have_the_unbatched_noise_against_a_converged_reference(rgb_variant, paper_specs):
    """The Monte-Carlo check: the mean |frame - 256-spp reference| over the object, summed over the
    shard's 8 frames, batched (B = 8) over unbatched.  Independent random numbers, so the two errors
    agree only statistically: three trials of 8 frames gave 0.93, 0.97 and 1.04 (frames alone 0.8-1.15),
    so 12 %.  Lights or materials of another slot, or a ray that wanders into another cell, change
    the error several-fold."""
    from msps_render.render.batch import render_batch

    pool = ScenePool()
    refs = [render_frame(s.model_copy(update={"integrator": s.integrator.model_copy(update={"spp": 256, "seed": 99})}),
                         rgb_variant, threads=1, scenes=pool) for s in paper_specs]
    batched = render_batch(paper_specs, rgb_variant, threads=1)
    alone = [render_frame(s, rgb_variant, threads=1, scenes=pool) for s in paper_specs]
    err_b = sum(np.abs(f.image - r.image)[r.mask].mean() for f, r in zip(batched, refs))
    err_1 = sum(np.abs(f.image - r.image)[r.mask].mean() for f, r in zip(alone, refs))
    assert err_1 > 0 and abs(err_b / err_1 - 1) < 0.12, (err_b, err_1)


def test_a_batch_does_not_depend_on_the_batches_before_it(rgb_variant, paper_specs):
    """The same batch from a new worker, and from one that rendered two other batches first (its kept
    scene then holds other shapes too, and was built in another order), gives the same bytes: where a
    shape's cell lies changes a ray's float rounding (a moved firefly differed by 0.34 when cells
    were numbered in order of appearance), so cells come from the shape alone (`placement`)."""
    from msps_render.render.batch import BatchScenes, render_batch

    fresh = render_batch(paper_specs[:4], rgb_variant, threads=1)
    scenes = BatchScenes()
    render_batch(paper_specs[5:8] + paper_specs[3:4], rgb_variant, threads=1, scenes=scenes)
    render_batch(paper_specs[4:8], rgb_variant, threads=1, scenes=scenes)
    built = scenes.built
    after = render_batch(paper_specs[:4], rgb_variant, threads=1, scenes=scenes)
    again = render_batch(paper_specs[:4], rgb_variant, threads=1, scenes=scenes)
    assert scenes.built == built + 1  # the first batch's shapes were not all there; then they are
    for f, g, h in zip(fresh, after, again):
        for name in ("image", "normal", "depth", "mask", "part"):
            assert np.array_equal(getattr(f, name), getattr(g, name)), name
            assert np.array_equal(getattr(f, name), getattr(h, name)), name


def test_placement_is_a_pure_function_of_the_batch_and_never_shares_a_cell(paper_specs):
    from msps_render.render.batch import home_cell, placement, shape_key

    specs = paper_specs
    cells = placement(specs)
    by_shape = {}
    for s, c in zip(specs, cells):
        assert by_shape.setdefault(shape_key(s), c) == c  # one cell per shape within a batch
    assert len(set(by_shape.values())) == len(by_shape)  # and one shape per cell
    assert placement(specs) == cells and placement(specs[::-1])[::-1] != [] 
    # two shapes with one home: the later one takes the next cell, the earlier keeps its home
    a, b = specs[0], specs[1]
    import msps_render.render.batch as batch

    home = home_cell(shape_key(a))
    orig = batch.home_cell
    try:
        batch.home_cell = lambda key: home
        ca, cb = placement([a, b])
        assert ca == home and cb != home and abs((cb[0] * batch.LATTICE + cb[1]) - (ca[0] * batch.LATTICE + ca[1])) == 1
    finally:
        batch.home_cell = orig


def test_frames_that_cannot_share_a_launch_are_refused(rgb_variant, paper_specs):
    from msps_render.render.batch import batchable, render_batch
    from msps_render.render.variant import activate

    mi = activate(rgb_variant, 1)
    env = paper_specs[1].model_copy(update={"lights": paper_specs[1].lights[:2]})  # another batch key
    assert batchable(paper_specs[:2], mi) and not batchable([paper_specs[0], env], mi)
    assert not batchable(paper_specs[:1], mi)
    with pytest.raises(ValueError, match="cannot share a launch"):
        render_batch([paper_specs[0], env], rgb_variant, threads=1)


def test_batch_frames_shards(tmp_path):
    """`batch_frames = 1` leaves the config JSON (and hash) as before the option; a batched paper-train
    shard renders, verifies, has the unbatched shard's patches (same truth, same coverage) and is
    byte-identical when rendered again."""
    import h5py
    import hdf5plugin  # noqa: F401

    from msps_render.dataset.verify import verify_dataset
    from msps_render.pipeline.config import config_json, load_config
    from msps_render.pipeline.run import render_dataset

    one = load_config("paper-train")
    assert "batch_frames" not in config_json(one)
    assert "batch_frames" in config_json(load_config("paper-train", ["dataset.batch_frames=4"]))
    sets = ["dataset.n_shards=1", "dataset.frames_per_shard=4"]
    for name, extra in (("b1", []), ("b4", ["dataset.batch_frames=4"]), ("b4again", ["dataset.batch_frames=4"])):
        render_dataset(load_config("paper-train", sets + extra), tmp_path / name, workers=1, progress=False,
                       threads=1)
    assert not any(verify_dataset(tmp_path / "b4").values())
    shard = "shards/shard-00000.h5"
    assert (tmp_path / "b4" / shard).read_bytes() == (tmp_path / "b4again" / shard).read_bytes()
    with h5py.File(tmp_path / "b1" / shard) as a, h5py.File(tmp_path / "b4" / shard) as b:
        assert np.array_equal(a["patches/yx"][:], b["patches/yx"][:])
        dn = np.abs(a["patches/normal"][:].astype(np.float32) - b["patches/normal"][:]).max(-1)
        assert (dn > 2e-3).mean() < 1e-4  # float16 rounding, but for grazing pixels (see above)
        ia, ib = a["patches/image"][:].astype(np.float32), b["patches/image"][:].astype(np.float32)
        assert not np.array_equal(ia, ib)  # other random numbers ...
        assert abs(ib.mean() / ia.mean() - 1) < 0.01  # ... the same radiance


@pytest.mark.parametrize("preset, extra", [
    ("paper-train", []),
    ("train-colour", ["scene.camera.width=64", "scene.camera.height=64", "scene.integrator.spp=4"]),  # textures
    ("spectral-train", ["scene.camera.width=64", "scene.camera.height=64", "scene.integrator.spp=4"])])  # spectral
def test_an_export_re_renders_a_batched_frame_to_its_stored_pixels(tmp_path, preset, extra):
    """`msps export --rerender` of a dataset rendered 4 frames per launch re-renders each frame's batch, so
    its per-light images sum to the stored frame (as for unbatched datasets: <= 1e-5 of the brightest
    pixel); a frame re-rendered alone differs by its noise (a few per cent).  The dataset is rendered at
    one thread, the export at the tests' two (`render.variant.flush_denormals`: before it, spectral-train's
    first frame differed by 8e-5)."""
    from msps_render.export import export_dataset
    from msps_render.export.source import rerender_per_light
    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.run import render_dataset

    cfg = load_config(preset, ["dataset.n_shards=1", "dataset.frames_per_shard=4", "dataset.batch_frames=4",
                               "dataset.storage.store_frames=true", *extra])
    render_dataset(cfg, tmp_path / "ds", workers=1, progress=False, threads=1)
    idx = export_dataset(tmp_path / "ds", "diligent", tmp_path / "dl", rerender=True)
    devs = [f["per_light_max_rel_deviation"] for f in idx["frames"]]
    assert len(devs) == 4 and max(devs) <= 1e-5, devs
    from msps_render.export.source import iter_export_frames

    ef = next(iter_export_frames(tmp_path / "ds"))
    alone, _ = rerender_per_light(ef)
    m = ef.mask
    assert np.abs(alone.sum(0) - ef.image)[m].max() / ef.image[m].max() > 1e-3  # the check above means something


def test_many_lights_cap_the_frames_per_launch_by_the_memory_budget():
    """A batch's film holds N images of each frame: 8 frames of 64 lights took 930 MiB of a worker, 2
    took 580, so beyond three lights at most 128 // N frames share a launch; the groups of a shard are
    a pure function of its config (the worker and an export's re-render both use `launch_groups`)."""
    from msps_render.render.batch import frames_per_launch, launch_groups

    def spec(n_lights):
        return _balls(1)[0].model_copy(update={"lights": tuple(_balls(1)[0].lights[:1]) * n_lights})

    assert [frames_per_launch(8, spec(n)) for n in (1, 3, 8, 64, 96)] == [8, 8, 8, 2, 1]
    assert frames_per_launch(1, spec(3)) == 1
    assert [list(g) for g in launch_groups(7, 4, lambda j: spec(3))] == [[0, 1, 2, 3], [4, 5, 6]]
    assert [list(g) for g in launch_groups(5, 8, lambda j: spec(64))] == [[0, 1], [2, 3], [4]]


def test_procedural_shapes_batch_with_the_unbatched_truth(rgb_variant):
    """`train`'s procedural shapes (new every frame) batch too: each is split at its creases before the
    rotation (the unbatched frame splits after it; dihedral angles do not change, only float rounding
    near the threshold could), so masks and parts match, normals and depth to rounding at all but a
    few pixels (observed: masks and parts identical, <= 0.05 % of pixels off), and the mean radiance over
    the object to its noise at 64 spp (observed 0.2-0.9 %; another frame's lights or materials: tens of %)."""
    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.plan import frame_rngs, frame_seed, plan
    from msps_render.render.batch import render_batch
    from msps_render.scene.sample import sample_scene

    cfg = load_config("train", ["dataset.n_shards=1", "scene.camera.width=96", "scene.camera.height=96",
                                "scene.integrator.spp=64"])
    t = plan(cfg)[0]
    specs = [sample_scene(cfg.scene, rng, seed=frame_seed(t, j), frame_index=j)
             for j, rng in enumerate(frame_rngs(t, 3))]
    assert all(s.shape.kind == "procedural" for s in specs)
    batched = render_batch(specs, rgb_variant, threads=1)
    for b, s in enumerate(specs):
        one = render_frame(s, rgb_variant, threads=1)
        f, m = batched[b], one.mask
        assert m.mean() > 0.1 and (f.mask != one.mask).mean() < 1e-3, b
        both = f.mask & one.mask
        assert (f.part[both] == one.part[both]).mean() > 0.995, b
        off = (np.abs(f.normal - one.normal).max(-1) > 1e-3)[both] | (np.abs(f.depth - one.depth) > 1e-3)[both]
        assert off.mean() < 5e-3, (b, off.mean())
        assert abs(f.image[both].mean() / one.image[both].mean() - 1) < 0.02, b


@pytest.mark.parametrize("value", ["0", "65", "eight"])
def test_a_bad_batch_frames_is_one_line_and_writes_nothing(tmp_path, value):
    from cli_helpers import cli, one_line_error

    r = cli("render", "paper-train", "--out", tmp_path / "ds", "--set", f"dataset.batch_frames={value}")
    line = one_line_error(r)
    assert "dataset.batch_frames" in line, line
    assert not (tmp_path / "ds").exists()


def test_the_next_launchs_shapes_are_built_ahead_in_a_thread_without_changing_a_byte(tmp_path, monkeypatch):
    """With more than one launch per shard, the next launch's procedural shapes are built in a thread while
    the current one renders (`BatchScenes.prepare`): the second launch's meshes come from that thread, and
    the shard is byte-identical to one rendered with every mesh built in the worker's own thread."""
    import threading

    import msps_render.render.batch as batch
    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.run import render_dataset

    built = []
    real = batch.batch_mesh

    def recorded(spec):
        built.append(threading.current_thread().name)
        return real(spec)

    monkeypatch.setattr(batch, "batch_mesh", recorded)
    cfg = load_config("train", ["dataset.n_shards=1", "dataset.frames_per_shard=4", "dataset.batch_frames=2",
                                "scene.camera.width=64", "scene.camera.height=64", "scene.integrator.spp=4"])
    render_dataset(cfg, tmp_path / "ahead", workers=1, progress=False, threads=1)
    ahead = sorted(built)  # (the thread may finish before the worker's own builds: order by name)
    assert ahead[:2] == ["MainThread"] * 2, ahead  # the first launch's shapes: nothing was built ahead
    assert len(ahead) == 4 and all(n.startswith("msps-batch-mesh") for n in ahead[2:]), ahead
    built.clear()
    monkeypatch.setattr(batch.BatchScenes, "prepare", lambda self, specs: None)
    render_dataset(cfg, tmp_path / "inline", workers=1, progress=False, threads=1)
    assert built == ["MainThread"] * 4
    shard = "shards/shard-00000.h5"
    assert (tmp_path / "ahead" / shard).read_bytes() == (tmp_path / "inline" / shard).read_bytes()


def test_textured_and_blended_frames_batch_with_the_unbatched_truth_and_appearance(rgb_variant, tmp_path):
    """`train-colour` (textures, measured blends) batches: a batch with such a frame gives every frame its
    own mesh (parts with their own vertices and attributes, as the unbatched part meshes), so the masks and
    parts are identical, the albedo and blend truth equal the unbatched to float rounding (the texture is
    evaluated at the unrotated vertices; observed <= 3e-4), and the mean radiance over the object is the
    unbatched frame's to its noise at 64 spp (observed <= 0.13 %; a texture read from another frame's mesh
    would change it by tens of %).  A batched train-colour shard verifies and repeats byte for byte."""
    from msps_render.dataset.verify import verify_dataset
    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.plan import frame_rngs, frame_seed, plan
    from msps_render.pipeline.run import render_dataset
    from msps_render.render.batch import needs_own_meshes, render_batch
    from msps_render.scene.sample import sample_scene

    cfg = load_config("train-colour", ["dataset.n_shards=1", "scene.camera.width=96", "scene.camera.height=96",
                                       "scene.integrator.spp=64"])
    t = plan(cfg)[0]
    specs = [sample_scene(cfg.scene, rng, seed=frame_seed(t, j), frame_index=j)
             for j, rng in enumerate(frame_rngs(t, 4))]
    mats = [m for s in specs for m in s.materials]
    assert needs_own_meshes(specs) and any(m.texture is not None for m in mats) and any(m.blend is not None for m in mats)
    batched = render_batch(specs, rgb_variant, threads=1)
    textured = 0
    for b, s in enumerate(specs):
        one = render_frame(s, rgb_variant, threads=1)
        f = batched[b]
        assert one.mask.mean() > 0.1 and np.array_equal(f.mask, one.mask), b
        assert np.array_equal(f.part, one.part), b
        assert np.abs(f.albedo - one.albedo).max() < 2e-3 and np.abs(f.blend - one.blend).max() < 2e-3, b
        m = one.mask
        textured += int(np.ptp(one.albedo[m], axis=0).max() > 0.05 or np.ptp(one.blend[m]) > 0.05)
        assert abs(f.image[m].mean() / one.image[m].mean() - 1) < 0.01, b
    assert textured >= 2  # the albedo or blend truth varies across the object: textures were read

    sets = ["dataset.n_shards=1", "dataset.frames_per_shard=4", "dataset.batch_frames=4", "scene.camera.width=64",
            "scene.camera.height=64", "scene.integrator.spp=4"]
    for name in ("a", "b"):
        render_dataset(load_config("train-colour", sets), tmp_path / name, workers=1, progress=False, threads=1)
    assert not any(verify_dataset(tmp_path / "a").values())
    shard = "shards/shard-00000.h5"
    assert (tmp_path / "a" / shard).read_bytes() == (tmp_path / "b" / shard).read_bytes()


def test_own_meshes_are_rebuilt_not_kept_when_their_frames_come_back(rgb_variant):
    """Own meshes (textured frames) leave only their face parts in the worker once their scene is built,
    and are never kept for a later scene: frames rendered again after other batches are rebuilt, and
    give the same pixels as the first time (a batch does not depend on the batches before it)."""
    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.plan import frame_rngs, frame_seed, plan
    from msps_render.render.batch import BatchScenes, needs_own_meshes, render_batch
    from msps_render.scene.sample import sample_scene

    cfg = load_config("train-colour", ["dataset.n_shards=3", "scene.camera.width=48", "scene.camera.height=48",
                                       "scene.integrator.spp=2"])
    groups = [[sample_scene(cfg.scene, rng, seed=frame_seed(t, j), frame_index=j)
               for j, rng in enumerate(frame_rngs(t, 2))] for t in plan(cfg)]
    assert all(needs_own_meshes(g) for g in groups)
    scenes = BatchScenes()
    first = render_batch(groups[0], rgb_variant, threads=1, scenes=scenes)
    assert all(m.vertices.size == 0 and m.parts is not None for m in scenes._scenes[next(iter(scenes._scenes))]
               .meshes.values())  # the arrays are in the scene only
    for g in (groups[1], groups[0], groups[2]):  # the third keeps nothing of the second (seen twice)
        again = render_batch(g, rgb_variant, threads=1, scenes=scenes)
    assert all(f.mask.any() for f in again)
    again = render_batch(groups[0], rgb_variant, threads=1, scenes=scenes)
    for a, b in zip(first, again):
        assert np.array_equal(a.image, b.image) and np.array_equal(a.albedo, b.albedo)


def test_a_plastic_slot_keeps_its_ior(rgb_variant, paper_specs):
    """Mitsuba's smooth plastic bakes its IOR into the kernel as a literal (other IORs, other code), so
    the IOR is part of a BSDF slot's kind (`render.slots.slot_kind`, `render.materials.BAKED`): a batch
    whose plastics all have IOR 1.5 leaves the IOR 1.4 slots holding the BSDFs they held, and a slot
    never changes its code.  (What it saves, measured in docs/benchmarks.md "Kernels on new content":
    fewer new kernels per batch on content no run has seen.)"""
    from msps_render.render.batch import BatchScenes, render_batch
    from msps_render.render.slots import slot_kind as _slot_kind
    from msps_render.scene.spec import MaterialSpec

    def plastic(ior, a):
        return MaterialSpec(name="plastic", kind="plastic", params={"diffuse_reflectance": (a, 0.5, 0.3),
                                                                    "int_ior": ior})

    assert _slot_kind(plastic(1.4, 0.2)) != _slot_kind(plastic(1.5, 0.2))
    assert _slot_kind(plastic(1.4, 0.2)) == _slot_kind(plastic(1.4, 0.7))
    assert _slot_kind(lambertian((0.1, 0.2, 0.3))) == _slot_kind(lambertian((0.5, 0.5, 0.5))) == "diffuse"
    L = lambertian((0.3, 0.4, 0.5))
    small = CameraSpec(width=24, height=24)

    def batch(menu):  # paper-train's first 4 shapes, each split in two parts
        return [s.model_copy(update={"materials": m, "split": s.split.model_copy(update={"n_parts": 2}),
                                     "camera": small, "integrator": s.integrator.model_copy(update={"spp": 1})})
                for s, m in zip(paper_specs[:4], menu)]

    scenes = BatchScenes()
    render_batch(batch([(plastic(1.4, 0.2), L), (plastic(1.4, 0.6), L), (plastic(1.5, 0.4), L),
                        (plastic(1.5, 0.8), L)]), rgb_variant, threads=1, scenes=scenes)
    held = {i: b for i, (k, b) in enumerate(scenes.bsdfs.slots) if k == _slot_kind(plastic(1.4, 0))}
    assert len(held) == 2 and {k for k, _ in scenes.bsdfs.slots} == {"diffuse", "plastic@1.4", "plastic@1.5"}
    render_batch(batch([(plastic(1.5, 0.3), L), (plastic(1.5, 0.7), L), (L, L), (L, L)]), rgb_variant, threads=1,
                 scenes=scenes)
    assert all(scenes.bsdfs.slots[i][1] is b for i, b in held.items())  # the IOR 1.4 slots untouched
    assert sum(k == "plastic@1.5" for k, _ in scenes.bsdfs.slots) == 2


def _near_balls(n: int, mu: float) -> list[SceneSpec]:
    """`_balls` under near LEDs instead: a 3 x 3 grid 2.5 units away (1/r^2 varies ~2x over the ball),
    each LED cos^mu about its axis, every frame its own rotation and its own light intensities."""
    from msps_render.scene.rig_layouts import RigConfig, sample_rig

    rng = np.random.default_rng(11)
    out = []
    for b, ball in enumerate(_balls(n, spp=32)):
        lights, rig = sample_rig(RigConfig.model_validate(
            {"layout": "grid", "grid": {"rows": 3, "cols": 3, "pitch": 1.2, "plane_distance": 2.5},
             "anisotropy_mu": mu, "capture": "sequential", "channels": "rgb", "irradiance": 2.0 + b}), rng)
        out.append(ball.model_copy(update={"lights": lights, "rig": rig, "shape": ball.shape.model_copy(
            update={"rotation": _rotation(rng)})}))
    return out


def test_point_lights_batch_to_the_closed_form(rgb_variant):
    """Three balls under near LEDs (cos^2 about their axes, 1/r^2) in one launch: light k's image of frame b
    is rho/pi I_k cos^mu(LED axis) max(n.l, 0) / r^2, with n, the surface point (`Frame.points`) and the
    light position of the frame's own world.  With near lights the radiance changes fast across a pixel,
    so its sample-position noise dominates: 1 % mean relative error at 32 spp (observed 0.4-0.75 %, the
    same as each frame rendered alone; 1.3 % at 8 spp, alone too).  The light of another slot, a missing
    1/r^2 (2x across the ball) or cos^mu (tens of %), or a light placed in the rotated frame without the
    rotation are far off."""
    from msps_render.render.batch import batchable, render_batch
    from msps_render.render.variant import activate

    mu = 2.0
    specs = _near_balls(3, mu)
    assert batchable(specs, activate(rgb_variant, 1))
    frames = render_batch(specs, rgb_variant, threads=1, per_light=True)
    for b, (s, f) in enumerate(zip(specs, frames)):
        inner = binary_erosion(f.mask, iterations=2)
        assert inner.mean() > 0.4 and f.points is not None, b
        x = f.points[inner]
        for k, l in enumerate(s.lights):
            at = np.array(l.direction) * l.distance
            to = at - x
            r = np.linalg.norm(to, axis=-1)
            d = to / r[:, None]
            cos = np.sum(f.normal[inner] * d, -1)
            led = np.clip(d @ (at / np.linalg.norm(at)), 0, None) ** mu
            lit = cos > 0.05
            for c in range(3):
                expected = RHO / np.pi * l.rgb[c] * led[lit] * cos[lit] / r[lit] ** 2
                rel = np.abs(f.per_light[k][..., c][inner][lit] - expected) / expected
                assert lit.sum() > 500 and rel.mean() < 0.01, (b, k, c, rel.mean())


def _preset_specs(preset: str, n: int, sets=()) -> list[SceneSpec]:
    """The first n scenes of `preset`'s first shard (with `--set` overrides)."""
    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.plan import frame_rngs, frame_seed, plan
    from msps_render.scene.sample import sample_scene

    cfg = load_config(preset, ["dataset.n_shards=1", *sets])
    t = plan(cfg)[0]
    return [sample_scene(cfg.scene, rng, seed=frame_seed(t, j), frame_index=j) for j, rng in enumerate(frame_rngs(t, n))]


def _shots_to_their_noise(f, s: SceneSpec, variant: str):
    """Frame `f` of a batch against scene `s` rendered alone and again with another seed: the same mask and
    parts, every shot's channel means over the object within 2 %, and the mean |batched - alone| the mean
    |seed a - seed b| of the frame alone within 15 % (two independent renders differ by sqrt 2 sigma).
    Returns the frame rendered alone."""
    one = render_frame(s, variant, threads=1)
    other = render_frame(s.model_copy(update={"integrator": s.integrator.model_copy(
        update={"seed": s.integrator.seed + 7})}), variant, threads=1)
    m = one.mask
    assert m.mean() > 0.1 and np.array_equal(f.mask, m) and np.array_equal(f.part, one.part)
    assert f.shots.shape == one.shots.shape
    ratio = f.shots[:, m].mean(1) / one.shots[:, m].mean(1)
    assert np.abs(ratio - 1).max() < 0.02, np.abs(ratio - 1).max()
    d_batch, d_seed = np.abs(f.shots - one.shots)[:, m].mean(), np.abs(other.shots - one.shots)[:, m].mean()
    assert abs(d_batch / d_seed - 1) < 0.15, (d_batch, d_seed)
    return one


def test_near_field_frames_batch_with_the_unbatched_truth_and_radiance(rgb_variant):
    """`near-field` (49 LEDs, perspective camera, procedural shapes) batches: each frame has a cell of its
    own, so a shape seen twice in one launch is a copy (here frame 0's shape again, turned and lit as
    frame 1).  Masks and parts as one frame at a time, depth and the surface points to rounding (the cells
    sit ~100 units out: observed <= 1.2e-4), and every LED's shot to its noise: the mean over the object
    within 2 % (observed <= 0.35 %), and the mean |batched - unbatched| the mean |seed a - seed b| of the
    unbatched frame within 15 % (observed 0.99-1.00); the other frame's shots are off by 88 % or more."""
    from msps_render.render.batch import batchable, layout, render_batch
    from msps_render.render.variant import activate

    specs = _preset_specs("near-field", 2, ["scene.camera.width=64", "scene.camera.height=64",
                                            "scene.integrator.spp=16"])
    twin = specs[1].model_copy(update={"shape": specs[0].shape.model_copy(update={"rotation": specs[1].shape.rotation})})
    specs = [specs[0], twin]
    assert specs[0].camera.kind == "perspective" and len(specs[0].lights) == 49
    assert batchable(specs, activate(rgb_variant, 1))
    assert layout(specs[0], 2)[0] > 2 * specs[0].camera.distance  # a camera ray never reaches another cell
    batched = render_batch(specs, rgb_variant, threads=1)
    for f, s in zip(batched, specs):
        one = _shots_to_their_noise(f, s, rgb_variant)
        m = one.mask
        assert np.abs(f.depth - one.depth).max() < 2e-3 and np.abs(f.points - one.points)[m].max() < 2e-3
        assert (np.abs(f.normal - one.normal).max(-1) > 1e-3).sum() <= max(2, 5e-4 * m.sum())
        assert f.shots.shape == (49, 64, 64, 3)


def test_a_batched_near_field_shard_verifies_repeats_and_has_the_unbatched_patches(tmp_path):
    """A `near-field` shard (49 LEDs: 2 frames a launch, `frames_per_launch`) at `batch_frames = 4`
    verifies, is byte-identical when rendered again, and has the unbatched shard's patches: the same
    windows, surface points to float16 rounding, every shot's radiance to its noise (1 %)."""
    import h5py
    import hdf5plugin  # noqa: F401

    from msps_render.dataset.verify import verify_dataset
    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.run import render_dataset

    sets = ["dataset.n_shards=1", "dataset.frames_per_shard=4", "scene.camera.width=48", "scene.camera.height=48",
            "scene.integrator.spp=4", "dataset.patches.size=16", "dataset.patches.stride=16"]
    for name, extra in (("b1", []), ("b4", ["dataset.batch_frames=4"]), ("b4again", ["dataset.batch_frames=4"])):
        render_dataset(load_config("near-field", sets + extra), tmp_path / name, workers=1, progress=False,
                       threads=1)
    assert not any(verify_dataset(tmp_path / "b4").values())
    shard = "shards/shard-00000.h5"
    assert (tmp_path / "b4" / shard).read_bytes() == (tmp_path / "b4again" / shard).read_bytes()
    with h5py.File(tmp_path / "b1" / shard) as a, h5py.File(tmp_path / "b4" / shard) as b:
        assert np.array_equal(a["patches/yx"][:], b["patches/yx"][:]) and len(a["patches/yx"]) > 10
        assert np.abs(a["patches/points"][:].astype(np.float32) - b["patches/points"][:]).max() < 1e-2
        ia, ib = a["patches/image"][:].astype(np.float32), b["patches/image"][:].astype(np.float32)
        assert not np.array_equal(ia, ib)  # other random numbers ...
        assert abs(ib.mean() / ia.mean() - 1) < 0.01, ib.mean() / ia.mean()  # ... the same radiance


def test_narrowband_frames_batch_to_the_closed_form_of_their_own_leds(spectral_variant):
    """Spectral frames batch: three grey Lambertian balls under the 6-LED, 6-filter narrow-band rig of
    tests/test_rig_spectral.py (one multiplexed shot), each turned its own way and lit at its own irradiance
    (1x, 1.5x, 2x: the table's per-frame scale on the LEDs' shared spectra), in one launch.  Every channel
    of every frame is its closed form rho/pi sum_n C[m, n] max(0, n . l_n) with C from the Gaussian
    overlaps: the median ratio within 1 %, as that test argues (observed <= 0.14 %).  Another frame's
    irradiance is 33-100 % off; a light or channel out of order 100 %."""
    from test_rig_spectral import RHO as GREY, closed_form_crosstalk, rig_table, scene_config

    from msps_render.render.batch import batchable, render_batch
    from msps_render.render.variant import activate
    from msps_render.rig import Rig, lambertian_shots, rig_of_spec
    from msps_render.scene.sample import sample_scene

    specs = []
    for b, ball in enumerate(_balls(3, spp=16)):
        spec = sample_scene(scene_config(rig_table(irradiance=3.0 * (1 + b / 2))), np.random.default_rng(3))
        specs.append(spec.model_copy(update={"shape": ball.shape, "materials": (lambertian((GREY,) * 3),)}))
    assert batchable(specs, activate(spectral_variant, 1))
    frames = render_batch(specs, spectral_variant, threads=1)
    for b, (s, f) in enumerate(zip(specs, frames)):
        assert f.shots.shape == (1, 64, 64, 6) and f.meta["lights"] == "one-pass", b
        rig = Rig(rig_of_spec(s).light_dirs, closed_form_crosstalk() * (1 + b / 2), shots=s.rig.shots)
        ref = lambertian_shots(rig, f.normal, GREY)[0]
        inner = binary_erosion(f.mask, iterations=3)
        assert inner.mean() > 0.4, b
        for m in range(6):
            sel = inner & (ref[..., m] > 0.1 * ref[..., m].max())
            med = float(np.median(f.shots[0][..., m][sel] / ref[..., m][sel]))
            assert sel.sum() > 500 and abs(med - 1) < 0.01, (b, m, med)


def test_narrowband_preset_frames_batch_with_the_unbatched_truth_and_shots(spectral_variant):
    """`narrowband` (spectral, 6 LEDs x 6 filters, procedural shapes, measured and analytic materials)
    batches: masks and parts as one frame at a time, the same light responses in the frame's meta, and
    every channel's shot to its noise (mean over the object within 2 %, observed <= 0.9 %; the mean
    |batched - unbatched| the mean |seed a - seed b| within 15 %, observed 1.01-1.06)."""
    from msps_render.render.batch import frames_per_launch, render_batch

    specs = _preset_specs("narrowband", 2, ["scene.camera.width=64", "scene.camera.height=64"])
    # the memory cap counts film: 6 lights x 6 channels are 12 three-channel images, 128 // 12 frames
    assert frames_per_launch(64, specs[0]) == 10
    batched = render_batch(specs, spectral_variant, threads=1)
    for f, s in zip(batched, specs):
        one = _shots_to_their_noise(f, s, spectral_variant)
        np.testing.assert_allclose(f.meta["light_response"], one.meta["light_response"], rtol=1e-6)
        assert f.meta["crosstalk_effective"] == one.meta["crosstalk_effective"]


def test_mesh_file_shapes_batch_with_the_unbatched_truth(rgb_variant, shared_data):
    """Shapes read from mesh files (`diligent-rig`'s test meshes; its 96 lights allow one frame a launch, so
    here under three lights) batch: masks and parts as one frame at a time, normals and depth to rounding
    but a few grazing pixels, and the mean radiance to its noise (observed <= 0.5 % at 16 spp)."""
    from msps_render.render.batch import batchable, render_batch
    from msps_render.render.variant import activate

    lights = three_lights(30.0, (0.0, 120.0, 240.0), irradiance=E)
    specs = [s.model_copy(update={"lights": lights, "rig": None}) for s in _preset_specs(
        "diligent-rig", 3, ["dataset.frames_per_shard=3", "scene.camera.width=96", "scene.camera.height=96"])]
    assert {s.shape.kind for s in specs} == {"mesh"} and len({s.shape.name for s in specs}) == 3
    assert batchable(specs, activate(rgb_variant, 1))
    batched = render_batch(specs, rgb_variant, threads=1)
    for b, s in enumerate(specs):
        one = render_frame(s, rgb_variant, threads=1)
        f, m = batched[b], one.mask
        assert m.mean() > 0.1 and np.array_equal(f.mask, m) and np.array_equal(f.part, one.part), b
        off = (np.abs(f.normal - one.normal).max(-1) > 1e-3) | (np.abs(f.depth - one.depth) > 1e-3)
        assert off.sum() <= max(2, 2e-3 * m.sum()), (b, off.sum())
        assert abs(f.image[m].mean() / one.image[m].mean() - 1) < 0.02, b
