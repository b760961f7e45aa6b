"""SceneSpec -> Frame.  The only stage that talks to Mitsuba.

The image is `mi.render` with a box pixel filter (a pixel is the mean radiance
over its footprint).  Ground truth (normal, depth, mask, part) comes from one
ray through each pixel centre with `scene.ray_intersect`, so it is exact and
never blended with the background.  Per-emitter images come from one render
with the `msps_multilight` integrator (`spec.integrator.lights = "one-pass"`:
every light sampled at every vertex, each in its own film channels) or, as the
reference, one Mitsuba render per emitter from the same compiled scene with the
others switched off through `mi.traverse` ("per-light"; scalar variants always).
The full image is their sum: linearity makes that exact, and it keeps
`image == Σ per_light + env` bit-for-bit consistent.
"""
from __future__ import annotations

import numpy as np

from msps_render.frame import Frame
from msps_render.render.emitters import render_emitters_one_pass, render_emitters_separately
from msps_render.render.ground_truth import frame_truth, pixel_points, pooled_truth
from msps_render.render.multilight import PART_ATTRIBUTE
from msps_render.render.pool import ScenePool, poolable
from msps_render.render.scene_dict import build_scene_dict, emitter_ids, one_pass
from msps_render.render.spectral import render_spectral_frame
from msps_render.render.variant import activate, resolve_variant
from msps_render.rig import compose_shots
from msps_render.scene.spec import SceneSpec
from msps_render.timing import StageTimer, stage


def render_frame(spec: SceneSpec, variant: str | None = None, threads: int | None = None,
                 per_light: bool = False, timer: StageTimer | None = None, scenes: ScenePool | None = None) -> Frame:
    """Render one scene. `variant=None` resolves the best working variant for `spec.mode`.
    `timer` (optional) times the steps (benchmarks/bench_breakdown.py).

    Frames that a scene pool accepts (`pool.poolable`: repeated shapes, one-pass RGB) always come
    from a pooled scene, so a SceneSpec renders to the same pixels wherever it is rendered (a
    corpus worker, a re-render from a stored spec, `msps scene render`): `scenes` is the worker's
    pool, kept across frames; without one a pool for this frame alone is used (same pixels, same
    cost as a fresh scene).  Every other frame is built fresh (`render_fresh`)."""
    variant = variant or resolve_variant(spec.mode)
    mi = activate(variant, threads)
    slots = scenes.bsdfs if scenes is not None else None  # the worker's BSDF slots (`render.slots`)
    if spec.mode == "spectral":  # not split into steps: all of it is timed as "render"
        with stage(timer, "render"):
            return render_spectral_frame(spec, mi, variant, per_light=per_light, slots=slots)
    if not poolable(spec, mi):
        return render_fresh(spec, variant, threads, per_light, timer, slots)
    scenes = scenes if scenes is not None else ScenePool(max_scenes=1)
    with scenes.frame(spec, mi, timer) as pooled:
        with stage(timer, "ground truth"):
            truth = pooled_truth(mi, pooled.scene, pooled.sensor, spec, PART_ATTRIBUTE)
        with stage(timer, "render"):
            images = render_emitters_one_pass(mi, pooled.scene, emitter_ids(spec), spec.integrator.spp,
                                              spec.integrator.seed, pooled.sensor)
    return _frame(mi, spec, variant, truth, images, per_light)


def render_fresh(spec: SceneSpec, variant: str | None = None, threads: int | None = None,
                 per_light: bool = False, timer: StageTimer | None = None, slots=None) -> Frame:
    """Render one RGB scene from a scene built for it alone (`mi.load_dict` of `build_scene_dict`):
    every frame `render_frame` does not pool, and the reference the pooled frames are tested
    against (tests/test_pool.py).  `slots`: the worker's BSDF slots (the same pixels, fewer kernels)."""
    variant = variant or resolve_variant(spec.mode)
    mi = activate(variant, threads)
    d = build_scene_dict(spec, mi, timer, slots=slots)
    with stage(timer, "scene load"):
        scene = mi.load_dict(d)
    with stage(timer, "ground truth"):
        truth = frame_truth(mi, scene, spec)
    with stage(timer, "render"):
        if one_pass(spec, mi):
            images = render_emitters_one_pass(mi, scene, emitter_ids(spec), spec.integrator.spp,
                                              spec.integrator.seed)
        else:
            images = render_emitters_separately(mi, scene, spec)
    return _frame(mi, spec, variant, truth, images, per_light)


def _frame(mi, spec: SceneSpec, variant: str, truth: tuple, images: list[np.ndarray], per_light: bool) -> Frame:
    """The Frame of a render: per-emitter images summed (lights, then the environment), ground truth."""
    normal, mask, depth, part, albedo, blend = truth
    # one (K [+ env], H, W, C) block, lights then the environment: views of it, no per-light copies
    arr = images if isinstance(images, np.ndarray) else (
        np.stack(images) if len(images) else np.zeros((0,) + normal.shape, np.float32))
    n_env = 1 if spec.environment is not None else 0
    env_img = arr[-1] if n_env else None
    per = arr[:len(arr) - n_env]
    image = per.sum(axis=0) + (env_img if env_img is not None else 0.0)
    shots = points = None
    if spec.rig is not None:  # the rig's camera images: sums of lights, linear maps of R, G, B
        shots = compose_shots(spec.rig, per, env_img)
        if any(l.kind == "point" for l in spec.lights):
            points = pixel_points(spec.camera, depth, mask)
    if not per_light:
        per = None
    return Frame(image=np.ascontiguousarray(image[..., :3], dtype=np.float32), normal=normal, mask=mask,
                 depth=depth, part=part, spec=spec, variant=variant, per_light=per, env_image=env_img,
                 albedo=albedo, blend=blend, meta={"mitsuba_version": mi.__version__, "lights": "one-pass" if one_pass(spec, mi) else "per-light"},
                 shots=shots, points=points)
