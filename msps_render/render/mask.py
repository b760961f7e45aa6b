"""The object mask of a scene without rendering it: one ray per pixel centre (`ground_truth`).

What `msps config show` uses to count the patches a frame will give: the mask is
exactly the one `render_frame` returns, at a fraction of the cost (no light transport).
"""
from __future__ import annotations

import numpy as np

from msps_render.render.ground_truth import ground_truth
from msps_render.render.scene_dict import build_scene_dict
from msps_render.render.variant import activate, resolve_variant
from msps_render.scene.spec import SceneSpec


def scene_mask(spec: SceneSpec, variant: str | None = None, threads: int | None = None) -> np.ndarray:
    """(H, W) bool: pixels whose centre ray hits the object (as in `render_frame(spec).mask`)."""
    variant = variant or resolve_variant(spec.mode)
    mi = activate(variant, threads)
    scene = mi.load_dict(build_scene_dict(spec, mi))
    _, mask, _, _ = ground_truth(mi, scene, spec)
    return mask
