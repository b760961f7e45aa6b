"""One image per emitter from one loaded scene (noise-free direct lighting with several lights).

Two ways, same expectation per emitter: `render_emitters_one_pass` (one render with the
`msps_multilight` integrator, each emitter in its own film channels; the default) and
`render_emitters_separately` (one Mitsuba render per emitter; the reference).
"""
from __future__ import annotations

import numpy as np

from msps_render.render.multilight import read_emitter_images
from msps_render.render.scene_dict import ENV_KEY, emitter_ids
from msps_render.scene.spec import SceneSpec


def _emitter_names(params, spec: SceneSpec) -> list[str]:
    """Emitter ids in render order (lights, then environment), checked against `mi.traverse`."""
    names = emitter_ids(spec)
    missing = [n for n in names if f"{n}.sampling_weight" not in params]
    if missing:
        raise RuntimeError(f"emitters not found in the loaded scene: {missing}")
    return names


def render_emitters_one_pass(mi, scene, ids: list[str], spp: int, seed: int, sensor=None) -> np.ndarray:
    """One image per emitter id (in `ids` order) from ONE render with the scene's `msps_multilight`
    integrator: every light is sampled at every path vertex and written to its own AOV channels,
    read back by name from the film.  `sensor`: the camera (default: the scene's first)."""
    integrator = scene.integrator()
    if list(getattr(integrator, "emitter_ids", ())) != list(ids):
        raise RuntimeError(f"the scene's integrator is not msps_multilight over emitters {ids}: {integrator}")
    sensor = sensor if sensor is not None else scene.sensors()[0]
    image = mi.render(scene, sensor=sensor, spp=spp, seed=seed)
    return read_emitter_images(image, integrator.aov_names(), ids)


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
