"""Frames in one launch on the CPU (issue 45 item 1, a probe, not product): B paper-train frames as B
objects in one scene, each in its own cell of space (x = i * SPACING) and seen by its own orthographic
camera, through Mitsuba's `batch` sensor (one film B frames wide) and the one-pass integrator with the
frame's three lights (the same lights for every frame here: the probe measures the kernel, not the
per-frame light table a product would need).  Prints the CPU seconds of one `mi.render` per frame
for B = 1, 2, 4, 8 (kernels warm), and how far each sub-image of a B = 8 launch is from the same
object rendered alone (relative mean |difference| against the two renders' own noise, measured as
the difference between two seeds of the lone render): cells far apart keep the frames apart.

    MSPS_THREADS=1 PYTHONPATH=. .venv/bin/python experiments/batch_probe.py
"""
from __future__ import annotations

import time

import drjit as dr
import numpy as np

from msps_render.pipeline.config import load_config
from msps_render.render.scene_dict import _bound, build_scene_dict, camera_to_world, light_key, mitsuba_mesh
from msps_render.render.variant import activate
from msps_render.scene.sample import sample_scene
from msps_render.scene.shapes import build_mesh

SPACING = 50.0  # objects fit in radius 1; far enough that no ray of one frame meets another's object

mi = activate("llvm_ad_rgb", 1)
cfg = load_config("paper-train")
specs = [sample_scene(cfg.scene, np.random.default_rng(i), seed=i, frame_index=i) for i in range(8)]
base = build_scene_dict(specs[0], mi)
cam = specs[0].camera
T = mi.ScalarTransform4f


def sensor(i: int, width: int) -> dict:
    return {"type": "orthographic", "to_world": T().translate([i * SPACING, 0.0, 0.0]) @ camera_to_world(mi, cam),
            "near_clip": 0.01, "far_clip": 2 * cam.distance + 10,
            "film": {"type": "hdrfilm", "width": width, "height": cam.height, "rfilter": {"type": "box"},
                     "pixel_format": "rgb", "component_format": "float32"}}


def scene(frames: list[int]) -> "mi.Scene":
    d = {"type": "scene", "integrator": base["integrator"]}
    for k in range(3):
        d[light_key(k)] = base[light_key(k)]
    d["bound"] = _bound(mi)
    for j, i in enumerate(frames):
        m = build_mesh(specs[i].shape)
        props = mi.Properties()
        props["bsdf"] = mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.5, 0.4]}})
        mesh, params = mitsuba_mesh(mi, f"object{j}", m.vertices + np.float32([j * SPACING, 0, 0]), m.faces,
                                    m.normals, props)
        params.update()
        d[f"object{j}"] = mesh
    if len(frames) == 1:
        d["sensor"] = sensor(0, cam.width)
    else:
        d["sensor"] = {"type": "batch", "film": sensor(0, cam.width * len(frames))["film"],
                       **{f"s{j}": sensor(j, cam.width) for j in range(len(frames))}}
    d["sensor"]["sampler"] = {"type": "multijitter", "sample_count": 8}
    return mi.load_dict(d)


def cpu_render(sc, seed: int) -> tuple[np.ndarray, float]:
    t = time.process_time()
    img = np.array(mi.render(sc, spp=8, seed=seed))
    dr.sync_thread()
    return img, time.process_time() - t


for B in (1, 2, 4, 8):
    sc = scene(list(range(B)))
    ts = [cpu_render(sc, s)[1] for s in range(8)]
    print(f"B = {B}: {np.median(ts[2:]) / B * 1e3:.1f} ms CPU per frame (one launch {np.median(ts[2:]) * 1e3:.1f} ms)")
batch, _ = cpu_render(scene(list(range(8))), 1)
W = cam.width
for i in (0, 3, 7):
    lone = scene([i])
    a, _ = cpu_render(lone, 1)
    b, _ = cpu_render(lone, 2)
    sub = batch[:, i * W:(i + 1) * W]
    m = a[..., :3].mean()
    print(f"frame {i}: batch vs alone {np.abs(sub[..., :3] - a[..., :3]).mean() / m:.4f}, two seeds alone "
          f"{np.abs(b[..., :3] - a[..., :3]).mean() / m:.4f} (mean |diff| / mean)")
