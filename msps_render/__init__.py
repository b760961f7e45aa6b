"""msps: synthetic data for multispectral photometric stereo.

Small public facade over the pipeline stages (see docs/architecture.md):

    cfg   = SceneConfig()                      # or load a preset from scenes/
    spec  = sample_scene(cfg, np.random.default_rng(0))
    frame = render_frame(spec)                 # Mitsuba is imported only here
    frame.save("out/")

    render_dataset(load_config("demo"), "out/demo")   # the whole pipeline

Names are loaded on first use, so `import msps_render` (and the training side,
`msps_render.data` / `msps_render.models`) imports neither Mitsuba nor torch
nor the scene sampler.
"""
from __future__ import annotations

import importlib

__version__ = "0.6.0"

from msps_render.errors import InputError

_LAZY = {  # public name -> module that defines it
    **dict.fromkeys(("SceneSpec", "ShapeSpec", "SplitSpec", "MaterialSpec", "LightSpec", "EnvSpec",
                     "CameraSpec", "IntegratorSpec"), "msps_render.scene.spec"),
    "sample_scene": "msps_render.scene.sample",
    "SceneConfig": "msps_render.scene.sample",
    "render_frame": "msps_render.render.render",
    "Frame": "msps_render.frame",
    "load_config": "msps_render.pipeline.config",
    "render_dataset": "msps_render.pipeline.run",
}


def __getattr__(name):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(name)
    return getattr(importlib.import_module(module), name)


__all__ = ["__version__", "InputError", *_LAZY]
