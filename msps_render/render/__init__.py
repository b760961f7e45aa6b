"""Render stage: SceneSpec -> Frame.  The only Mitsuba translator (scene dicts, materials,
env bitmaps, the `merl` BSDF plugin, spectral rendering, ground truth); Mitsuba is imported
lazily, inside functions, once a variant is chosen."""
from msps_render.render.render import render_frame
from msps_render.render.scene_dict import build_scene_dict
from msps_render.render.variant import resolve_variant

__all__ = ["render_frame", "build_scene_dict", "resolve_variant"]
