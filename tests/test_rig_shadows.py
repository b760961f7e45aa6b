"""Per-light shadow masks (issue 42 item 3, `dataset.storage.store_shadows`): attached shadows against the
sphere's closed form, cast shadows against the renderer's own per-light images, and the shards."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import binary_erosion

from msps_render.dataset.schema import SHADOW_ATTACHED, SHADOW_CAST, SHADOW_LIT
from msps_render.scene.materials import lambertian
from msps_render.scene.rig_layouts import RigConfig, sample_rig
from msps_render.scene.sample import SceneConfig, sample_scene
from msps_render.scene.spec import CameraSpec, SceneSpec, ShapeSpec
from msps_render.testing import analytic_sphere_normals

RES = 64


def test_sphere_attached_shadows_follow_n_dot_l_and_nothing_is_cast(rgb_variant):
    """A sphere: code 1 exactly where the analytic normal faces away from the light (n . l <= 0), 0
    elsewhere, and no cast shadow (convex).  Near lights included: l = (p - x)/|p - x| per pixel.
    Pixels with |n . l| < 0.01 are left out (the analytic normal at the pixel centre vs the renderer's
    float32 intersection: a grazing pixel may go either way)."""
    from msps_render.render.shadows import render_shadows

    for rig in ({"layout": "ring", "n_lights": 6, "slant_deg": 80.0},
                {"layout": "ring", "n_lights": 4, "slant_deg": 60.0, "kind": "point", "distance": 2.5}):
        lights, rs = sample_rig(RigConfig.model_validate(rig), np.random.default_rng(0))
        spec = SceneSpec(shape=ShapeSpec(kind="sphere", radius=0.9), materials=(lambertian((0.5, 0.5, 0.5)),),
                         lights=lights, camera=CameraSpec(width=RES, height=RES), rig=rs)
        s = render_shadows(spec, rgb_variant)
        n, mask = analytic_sphere_normals(RES, RES, radius=0.9, extent=spec.camera.extent)
        assert s.shape == (len(lights), RES, RES) and not (s[:, ~mask] != SHADOW_LIT).any()
        for k, l in enumerate(lights):
            if l.kind == "point":
                x = n * 0.9  # the sphere's surface point of each pixel (centred at the origin)
                to = np.asarray(l.direction) * l.distance - x
                d = to / np.linalg.norm(to, axis=-1, keepdims=True)
            else:
                d = np.broadcast_to(np.asarray(l.direction), n.shape)
            ndl = (n * d).sum(-1)
            sure = mask & (np.abs(ndl) > 0.01)
            assert np.array_equal(s[k][sure] == SHADOW_ATTACHED, ndl[sure] <= 0), (rig, k)
            assert (ndl[sure] <= 0).sum() > 50  # the lights are grazing enough to shadow part of the sphere
        assert not (s == SHADOW_CAST).any()


def test_cast_shadows_are_where_the_light_does_not_reach(rgb_variant):
    """A concave shape (cups, dents) under 8 low lights, white Lambertian, direct light only: inside a
    cast-shadow region (the pixel and its 8 neighbours all cast, so the whole pixel footprint is) the
    renderer's image of that light is exactly 0, and inside a lit region it is > 0."""
    from msps_render.render import render_frame
    from msps_render.render.shadows import render_shadows

    cfg = SceneConfig.model_validate({"camera": {"width": RES, "height": RES},
                                      "integrator": {"kind": "direct", "spp": 16},
                                      "shape": {"source": "procedural", "families": ["concave"]},
                                      "rig": {"layout": "ring", "n_lights": 8, "slant_deg": 70.0}})
    spec = sample_scene(cfg, np.random.default_rng(9))
    spec = spec.model_copy(update={"materials": tuple(lambertian((0.8, 0.8, 0.8), "white") for _ in spec.materials)})
    s = render_shadows(spec, rgb_variant)
    frame = render_frame(spec, variant=rgb_variant, per_light=True)
    n_cast = n_lit = 0
    for k in range(len(spec.lights)):
        img = frame.per_light[k].sum(-1)
        cast = binary_erosion(s[k] == SHADOW_CAST, np.ones((3, 3)))
        lit = binary_erosion((s[k] == SHADOW_LIT) & frame.mask, np.ones((3, 3)))
        assert (img[cast] == 0).all(), f"light {k}: {np.count_nonzero(img[cast])} of {cast.sum()} lit"
        assert (img[lit] > 0).mean() > 0.99
        n_cast, n_lit = n_cast + cast.sum(), n_lit + lit.sum()
    assert n_cast > 100 and n_lit > 1000, (n_cast, n_lit)


def test_store_shadows_writes_patches_and_frames(tmp_path):
    from cli_helpers import cli

    from msps_render.dataset import schema as K
    from msps_render.dataset.reader import iter_rig_frames, open_shard, read_rig_patches

    out = tmp_path / "ds"
    r = cli("render", "demo-rig", "--out", out, "--set", "dataset.n_shards=1", "--set", "dataset.frames_per_shard=1",
            "--set", "scene.camera.width=64", "--set", "scene.camera.height=64", "--set", "dataset.patches.stride=8",
            "--set", "dataset.storage.store_shadows=true")
    assert r.returncode == 0, r.stderr[-2000:]
    shard = next((out / "shards").glob("*.h5"))
    with open_shard(shard) as h:
        p = read_rig_patches(h)
        yx = h[K.PATCH_YX][()]
    frame = next(iter_rig_frames(shard))
    L, P = frame.shadow.shape[0], p["image"].shape[2]
    assert frame.shadow.dtype == np.uint8 and frame.shadow.shape == (8, 64, 64) and set(np.unique(frame.shadow)) <= {0, 1, 2}
    assert p["shadow"].shape == (len(yx), L, P, P)
    for i, (y, x) in enumerate(yx):
        assert np.array_equal(p["shadow"][i], frame.shadow[:, y:y + P, x:x + P])
    assert (frame.shadow == SHADOW_ATTACHED).any()
    assert cli("verify", out).returncode == 0
    # the disk estimates count the codes: one byte per light and pixel, as stored
    from msps_render.dataset.sizes import raw_patch_bytes

    extra = raw_patch_bytes(P, "float16", "float16", 8, 3, False, 8) - raw_patch_bytes(P, "float16", "float16", 8, 3)
    assert extra == p["shadow"][0].nbytes == 8 * P * P
    shown = cli("config", "show", "demo-rig", "--set", "dataset.storage.store_shadows=true")
    assert shown.returncode == 0 and "+ 8 shadow codes" in shown.stdout, shown.stdout[-1500:]


def test_store_shadows_without_a_rig_is_one_line(tmp_path):
    from cli_helpers import cli

    r = cli("render", "demo", "--out", tmp_path / "x", "--set", "dataset.storage.store_shadows=true")
    assert r.returncode == 1 and "store_shadows needs a [scene.rig]" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "x").exists()


def test_shadows_in_a_scalar_variant_are_refused_in_one_error(scalar_variant):
    from msps_render.errors import InputError
    from msps_render.render.shadows import render_shadows

    lights, rs = sample_rig(RigConfig.model_validate({"layout": "ring", "n_lights": 4}), np.random.default_rng(0))
    spec = SceneSpec(shape=ShapeSpec(kind="sphere", radius=0.9), materials=(lambertian((0.5, 0.5, 0.5)),),
                     lights=lights, camera=CameraSpec(width=8, height=8), rig=rs)
    with pytest.raises(InputError, match="store_shadows.*JIT variant"):
        render_shadows(spec, scalar_variant)
