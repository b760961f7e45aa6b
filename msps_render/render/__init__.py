"""Render stage: SceneSpec -> Frame (the only stage that imports Mitsuba, lazily)."""
from msps_render.render.render import analytic_sphere_normals, build_scene_dict, render_frame
from msps_render.render.variant import resolve_variant

__all__ = ["render_frame", "build_scene_dict", "resolve_variant", "analytic_sphere_normals"]
