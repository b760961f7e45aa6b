"""Check every input a dataset config refers to, before anything is written.

`validate_inputs(cfg)` runs in the driver before the output directory is
touched, for every sweep condition: each mesh file (readable, finite, has
faces), each environment-map file (finite, non-negative, lighting the camera-facing hemisphere), the
material catalogue and every measured-material (MERL) table it can draw
(header and size), texture images and UV mapping, the crosstalk matrix (finite, non-negative, every light
reaching a channel, invertible), and one sampled scene as a smoke test of the
sampler's own checks.  A bad input is an `InputError` naming the file or key,
so a render never stops half-way (leaving a manifest and no shards) because of
a file it could have checked first.
"""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from msps_render.brdf import merl
from msps_render.brdf.library import available_merl, load_catalogue
from msps_render.calibration import check_crosstalk
from msps_render.errors import InputError
from msps_render.pipeline.config import condition_config
from msps_render.scene.envmap import check_front_irradiance, load_envmap
from msps_render.scene.sample import sample_scene
from msps_render.scene.shapes import build_mesh
from msps_render.scene.spec import ShapeSpec
from msps_render.spectral.config import SpectralConfig
from msps_render.spectral.crosstalk import effective_crosstalk


def _check_merl_file(p: Path) -> None:
    """Header and size of a MERL `.binary` (cheap: no 35 MB read); `read_merl` does the full check."""
    try:
        size = p.stat().st_size
        with open(p, "rb") as fh:
            header = fh.read(merl.HEADER_BYTES)
    except OSError as e:
        raise InputError(p, f"cannot read MERL file ({e.strerror})") from None
    if len(header) < merl.HEADER_BYTES:
        raise InputError(p, f"truncated MERL file: {size} bytes, smaller than the 12-byte header")
    dims = tuple(int(d) for d in np.frombuffer(header, dtype="<i4"))
    if dims != merl.DIMS:
        raise InputError(p, f"not a MERL BRDF: header dims {dims}, expected {merl.DIMS}")
    if size != merl.FILE_BYTES:
        kind = "truncated" if size < merl.FILE_BYTES else "oversized"
        raise InputError(p, f"{kind} MERL file: {size} bytes, expected {merl.FILE_BYTES}")


def _check_materials(mc, seen: set) -> None:
    if not (mc.merl_fraction > 0 or mc.catalogue):
        return

    cat = load_catalogue(mc.catalogue)
    for _entry, path in available_merl(cat, mc.merl_dir):
        if path not in seen:
            seen.add(path)
            _check_merl_file(Path(path))


def _check_meshes(sc, seen: set) -> None:
    if sc.shape.source != "mesh":
        return

    paths = sc.shape.mesh_paths()
    if not paths:
        raise InputError("scene.shape.meshes", "source 'mesh' needs at least one mesh path")
    for p in paths:
        rp = str(Path(p).resolve())
        if rp in seen:
            continue
        seen.add(rp)
        build_mesh(ShapeSpec(kind="mesh", name=Path(p).stem, path=rp, radius=sc.shape.radius))


def _check_envmap(sc) -> None:
    env = sc.environment
    used = env.ratio > 0 or (env.ratio_range is not None and env.ratio_range[1] > 0)
    if not env.enabled or not used or env.source == "procedural":
        return

    img = load_envmap(env.source)
    if float(img.max()) <= 0:
        raise InputError(env.source, "environment map is black (all zero): it cannot light the scene at "
                                     f"the requested ratio {env.ratio}")
    _check_front(env.source, bool(env.random_rotation))


@lru_cache(maxsize=8)
def _check_front(source: str, random_rotation: bool) -> None:
    """Once per map and rotation setting (a sweep of env ratios shares one map)."""
    check_front_irradiance(load_envmap(source), source, random_rotation)


def _check_textures(sc, seen: set) -> None:
    """Texture images (every file of the folder readable, RGB or grey), and UV mapping only of meshes
    that have UVs, before anything is rendered."""
    tc = sc.materials.texture
    if tc.fraction <= 0:
        return
    if sc.mode == "spectral":
        raise InputError("scene.materials.texture", "textures need mode 'rgb' (spectral textures are not "
                                                    "supported yet)")
    if "image" not in tc.kinds:
        return
    from msps_render.scene.shapes import mesh_has_uv
    from msps_render.scene.textures import read_texture_image, texture_images

    for p in texture_images(tc.folder):
        if str(p) not in seen:
            seen.add(str(p))
            read_texture_image(p)
    if tc.mapping == "uv":
        if sc.shape.source != "mesh":
            raise InputError("scene.materials.texture.mapping", f"UV mapping needs meshes with UVs; shape "
                                                                f"source '{sc.shape.source}' has none")
        for m in sc.shape.mesh_paths():
            if not mesh_has_uv(m):
                raise InputError(m, "UV mapping asked of a mesh without UVs (texture.mapping = 'uv'; "
                                    "use 'auto' or 'triplanar')")


def _check_crosstalk(sc) -> None:
    if sc.mode == "spectral":
        sp = sc.spectral or SpectralConfig()
        check_crosstalk(effective_crosstalk(sp.lights, sp.camera), "scene.spectral (effective crosstalk)")
    else:
        M = np.asarray(sc.lights.crosstalk, dtype=np.float64)
        if M.shape != (3, len(sc.lights.tilts_deg)):
            raise InputError("scene.lights.crosstalk", f"crosstalk must be 3x{len(sc.lights.tilts_deg)} "
                                                       f"(one column per light), got {M.shape}")
        check_crosstalk(M, "scene.lights.crosstalk")


_CONFIG_KEYS = {"scene", "dataset", "sweep", "lights", "shape", "materials", "environment", "spectral", "camera",
                "integrator", "sensor"}


def validate_inputs(cfg, source: str | None = None) -> None:
    """Raise `InputError` for the first bad input of any condition of `cfg` (a `DatasetConfig`).

    `source` (the config file) prefixes errors about config keys, so the line names the file too.
    """
    meshes: set = set()
    tables: set = set()
    for _name, value in cfg.conditions():
        ccfg = cfg if cfg.sweep is None else condition_config(cfg, value)
        sc = ccfg.scene
        try:
            _check_crosstalk(sc)
            _check_meshes(sc, meshes)
            _check_envmap(sc)
            _check_materials(sc.materials, tables)
            _check_textures(sc, tables)
            sample_scene(sc, np.random.default_rng(ccfg.dataset.seed))  # the sampler's own checks
        except InputError as e:
            if source and e.source.split(".")[0] in _CONFIG_KEYS:
                raise InputError(f"{source}: {e.source}", e.problem) from None
            raise
