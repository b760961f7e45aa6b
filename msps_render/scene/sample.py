"""`SceneConfig` (what to randomise, from TOML) and `sample_scene(cfg, rng) -> SceneSpec`.

The sampler is the only place randomness enters a scene: it takes an explicit
`numpy.random.Generator` and consumes it in a fixed order, so the same config
and seed give the same SceneSpec on any machine.
"""
from __future__ import annotations

import glob
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from msps_render.errors import InputError
from msps_render.scene import lights as L
from msps_render.scene import shapes as S
from msps_render.scene.materials import FAMILIES, sample_analytic
from msps_render.scene.spec import CameraSpec, EnvSpec, IntegratorSpec, SceneSpec, ShapeSpec


class _Cfg(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ShapeConfig(_Cfg):
    source: Literal["blobby", "mesh", "sphere", "primitive"] = "blobby"
    primitives: list[str] = Field(default_factory=lambda: ["torus", "capsule", "superellipsoid", "vase"])
    meshes: list[str] = Field(default_factory=list, description="paths or globs (source='mesh')")
    lmax: int = Field(4, ge=1, le=8)
    amplitude: float = Field(0.3, ge=0.0, le=0.6)
    subdivisions: int = Field(5, ge=2, le=7)
    radius: float = Field(0.95, gt=0, le=1.0)
    random_rotation: bool = True
    n_shapes: int | None = Field(None, ge=1, description="blobby: draw from a fixed pool of this many shapes")
    pool_seed: int = 0

    def mesh_paths(self) -> list[str]:
        out: list[str] = []
        for pat in self.meshes:
            hits = sorted(glob.glob(pat))
            if not hits:
                raise InputError(pat, "no mesh file matches this path/pattern")
            out.extend(hits)
        return out


class MaterialsConfig(_Cfg):
    min_count: int = Field(2, ge=1, le=8)
    max_count: int = Field(3, ge=1, le=8)
    families: list[str] = Field(default_factory=lambda: ["diffuse", "plastic", "roughplastic",
                                                         "roughconductor", "principled"])
    merl_fraction: float = Field(0.0, ge=0.0, le=1.0, description="share of measured (MERL) materials")
    catalogue: str | None = None
    merl_dir: str | None = None
    split: Literal["field", "planes"] = "field"

    @field_validator("families")
    @classmethod
    def _known(cls, v):
        from msps_render.errors import closest

        for f in v:
            if f not in FAMILIES:
                raise ValueError(f"unknown material family '{f}'{closest(f, FAMILIES)}")
        return v


class LightsConfig(_Cfg):
    kind: Literal["directional", "point"] = "directional"
    slant_deg: float = Field(30.0, gt=0.0, lt=90.0)
    tilts_deg: list[float] = Field(default_factory=lambda: [0.0, 120.0, 240.0])
    crosstalk: list[list[float]] = Field(default_factory=lambda: L.PAPER_CROSSTALK.tolist())
    irradiance: float = Field(3.0, gt=0.0)
    distance: float | None = Field(None, gt=1.0)
    jitter_deg: float = Field(0.0, ge=0.0, le=20.0)
    intensity_jitter: float = Field(0.0, ge=0.0, lt=1.0)


class EnvironmentConfig(_Cfg):
    enabled: bool = False
    source: str = "procedural"
    ratio: float = Field(0.1, ge=0.0, description="env irradiance / coloured-light irradiance")
    random_rotation: bool = True


class SceneConfig(_Cfg):
    shape: ShapeConfig = ShapeConfig()
    materials: MaterialsConfig = MaterialsConfig()
    lights: LightsConfig = LightsConfig()
    environment: EnvironmentConfig = EnvironmentConfig()
    camera: CameraSpec = CameraSpec()
    integrator: IntegratorSpec = IntegratorSpec()


def _sample_shape(cfg: ShapeConfig, rng: np.random.Generator) -> ShapeSpec:
    rot = S.random_rotation(rng) if cfg.random_rotation else ShapeSpec.model_fields["rotation"].default
    if cfg.source == "sphere":
        return ShapeSpec(kind="sphere", name="sphere", radius=cfg.radius)
    if cfg.source == "mesh":
        paths = cfg.mesh_paths()
        if not paths:
            raise InputError("shape.meshes", "source 'mesh' needs at least one mesh path")
        path = paths[int(rng.integers(len(paths)))]
        return ShapeSpec(kind="mesh", name=Path(path).stem, path=str(Path(path).resolve()),
                         rotation=rot, radius=cfg.radius)
    if cfg.source == "primitive":
        name = str(rng.choice(cfg.primitives))
        return ShapeSpec(kind="primitive", name=name, params=S.sample_primitive_params(name, rng),
                         rotation=rot, radius=cfg.radius)
    if cfg.n_shapes:  # a fixed pool, like the 10-shape Blobby dataset (train/val split by index)
        idx = int(rng.integers(cfg.n_shapes))
        coeffs = S.sample_blobby_coeffs(np.random.default_rng([cfg.pool_seed, idx]), cfg.lmax, cfg.amplitude)
        name = f"blob{idx:03d}"
    else:
        coeffs = S.sample_blobby_coeffs(rng, cfg.lmax, cfg.amplitude)
        name = "blob"
    return ShapeSpec(kind="blobby", name=name, sh_coeffs=coeffs, subdivisions=cfg.subdivisions,
                     rotation=rot, radius=cfg.radius)


def _sample_materials(cfg: MaterialsConfig, n: int, rng: np.random.Generator):
    if cfg.merl_fraction > 0 or cfg.catalogue:
        from msps_render.brdf.library import sample_materials

        return tuple(sample_materials(rng, n, catalogue=cfg.catalogue, merl_fraction=cfg.merl_fraction,
                                      merl_dir=cfg.merl_dir, families=cfg.families))
    fams = rng.choice(cfg.families, size=n, replace=len(cfg.families) < n)
    return tuple(sample_analytic(str(f), rng) for f in fams)


def sample_scene(cfg: SceneConfig, rng: np.random.Generator, seed: int | None = None) -> SceneSpec:
    """Draw one scene. Consumes `rng` in a fixed order (shape, materials, split, lights, env)."""
    shape = _sample_shape(cfg.shape, rng)
    if shape.kind == "sphere":
        n = 1
    else:
        n = int(rng.integers(cfg.materials.min_count, max(cfg.materials.min_count, cfg.materials.max_count) + 1))
    materials = _sample_materials(cfg.materials, n, rng)
    split = S.sample_split(rng, n, cfg.materials.split)
    lc = cfg.lights
    lights = L.three_lights(lc.slant_deg, lc.tilts_deg, lc.crosstalk, lc.irradiance, lc.kind, lc.distance,
                            rng=rng, jitter_deg=lc.jitter_deg, intensity_jitter=lc.intensity_jitter)
    env = None
    if cfg.environment.enabled and cfg.environment.ratio > 0:
        env = environment_for_ratio(cfg.environment, lc.irradiance, rng)
    integ = cfg.integrator.model_copy(update={"seed": int(rng.integers(2**31 - 1))})
    return SceneSpec(shape=shape, split=split, materials=materials, lights=lights, environment=env,
                     camera=cfg.camera, integrator=integ,
                     crosstalk=tuple(tuple(float(x) for x in row) for row in np.asarray(lc.crosstalk)),
                     seed=seed)


def environment_for_ratio(cfg: EnvironmentConfig, light_irradiance: float, rng: np.random.Generator) -> EnvSpec:
    """Scale the env map so its irradiance on a camera-facing plane is `ratio` x the lights'.

    The reference is the mean over lights of each light's (channel-summed)
    irradiance at normal incidence, i.e. `light_irradiance`.
    """
    from msps_render.scene.envmap import envmap_pixels, mean_irradiance_on_axis

    rot = float(rng.uniform(0, 360)) if cfg.random_rotation else 0.0
    seed = int(rng.integers(2**31 - 1))
    img = envmap_pixels(cfg.source, seed)
    e = mean_irradiance_on_axis(img, (0.0, 0.0, 1.0), rot)
    scale = cfg.ratio * light_irradiance / max(e, 1e-12)
    return EnvSpec(source=cfg.source, scale=float(scale), rotation_deg=rot, seed=seed, ratio=cfg.ratio)


def load_scene_config(path: str | Path) -> SceneConfig:
    """Read a SceneConfig from TOML: the `[scene]` table if present, else the whole file."""
    import tomllib

    from msps_render.errors import format_validation_error

    p = Path(path)
    try:
        data = tomllib.loads(p.read_text())
    except OSError as e:
        raise InputError(p, f"cannot read config ({e.strerror})") from None
    except tomllib.TOMLDecodeError as e:
        raise InputError(p, f"not valid TOML ({e})") from None
    data = data.get("scene", data)
    try:
        return SceneConfig.model_validate(data)
    except Exception as e:
        raise InputError(p, format_validation_error(e)) from None
