"""msps: synthetic data for multispectral photometric stereo.

Small public facade over the pipeline stages (see docs/architecture.md):

    cfg   = SceneConfig()                      # or load a preset from scenes/
    spec  = sample_scene(cfg, np.random.default_rng(0))
    frame = render_frame(spec)                 # Mitsuba is imported only here
    frame.save("out/")

Importing this package imports neither Mitsuba nor torch.
"""
from __future__ import annotations

__version__ = "0.1.0"

from msps_render.errors import InputError
from msps_render.scene.spec import (CameraSpec, EnvSpec, IntegratorSpec, LightSpec, MaterialSpec,
                                    SceneSpec, ShapeSpec, SplitSpec)


def __getattr__(name):  # lazy: keep `import msps_render` free of heavy imports
    if name == "render_frame":
        from msps_render.render.render import render_frame

        return render_frame
    if name in ("sample_scene", "SceneConfig"):
        from msps_render.scene import sample

        return getattr(sample, name)
    if name == "Frame":
        from msps_render.frame import Frame

        return Frame
    raise AttributeError(name)


__all__ = ["__version__", "InputError", "SceneSpec", "ShapeSpec", "SplitSpec", "MaterialSpec", "LightSpec",
           "EnvSpec", "CameraSpec", "IntegratorSpec", "render_frame", "sample_scene", "SceneConfig", "Frame"]
