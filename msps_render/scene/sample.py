"""`SceneConfig` (what to randomise, from TOML) and `sample_scene(cfg, rng) -> SceneSpec`.

The sampler is the only place randomness enters a scene: it takes an explicit
`numpy.random.Generator` and consumes it in a fixed order, so the same config
and seed give the same SceneSpec on any machine.
"""
from __future__ import annotations

import glob
import os
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, field_validator, model_serializer

from msps_render.brdf.families import FAMILIES, GAMUTS, unknown_family
from msps_render.config_io import StrictModel, omit_defaults, read_toml, validate
from msps_render.errors import InputError
from msps_render.scene.envmap import envmap_pixels, expand_path, irradiance_on_axis, missing_asset
from msps_render.scene.families import expand_families, sample_family_params
from msps_render.scene.geometry import sample_blobby_coeffs
from msps_render.scene.rig_layouts import RigConfig, sample_rig, spectral_rig
from msps_render.scene.lights import PAPER_CROSSTALK, random_crosstalk, three_lights
from msps_render.scene.materials import sample_analytic, sample_materials
from msps_render.scene.primitives import PRIMITIVES, sample_primitive_params, unknown_primitive
from msps_render.scene.shapes import random_rotation, sample_split
from msps_render.scene.spec import CameraSpec, EnvSpec, IntegratorSpec, SceneSpec, ShapeSpec
from msps_render.scene.texturing import texture_materials
from msps_render.scene.textures import TextureConfig
from msps_render.spectral.config import SpectralConfig
from msps_render.spectral.crosstalk import effective_crosstalk


def _known(names: list[str], registry: dict, message) -> list[str]:
    """`names` if every one is in `registry`, else ValueError(message(first unknown))."""
    for n in names:
        if n not in registry:
            raise ValueError(message(n))
    return names


class ShapeConfig(StrictModel):
    source: Literal["blobby", "mesh", "sphere", "primitive", "procedural"] = Field(
        "blobby", description="what the object is: random spherical-harmonic blob, user meshes, a sphere, "
                              "a primitive, or a procedural shape family (docs/shapes.md)")
    primitives: list[str] = Field(default_factory=lambda: list(PRIMITIVES),
                                  description="source='primitive': primitives to draw from")
    families: list[str] = Field(default_factory=lambda: ["mixed"],
                                description="source='procedural': shape families, one drawn per shape "
                                            "('mixed' = all: detailed, creased, concave, thin, composite)")
    meshes: list[str] = Field(default_factory=list, description="paths or globs (source='mesh'); $VARS and ~ "
                                                                 "are expanded (the unseen-* presets read "
                                                                 "$MSPS_TEST_DATA/meshes/<name>.obj)")
    mesh_order: Literal["random", "cycle"] = Field(
        "random", description="source='mesh': draw a mesh per frame (random) or take them in turn (cycle: "
                              "frame k of each condition gets mesh k mod N, so every mesh gets the same "
                              "number of frames)")
    lmax: int = Field(4, ge=1, le=8, description="blobby: highest spherical-harmonic degree")
    amplitude: float = Field(0.3, ge=0.0, le=0.6, description="blobby: SH perturbation amplitude (x radius)")
    subdivisions: int = Field(5, ge=2, le=7, description="blobby: icosphere subdivisions of the mesh")
    radius: float = Field(0.95, gt=0, le=1.0, description="object bounding radius (scene units; the view "
                                                          "half-extent is camera.extent)")
    random_rotation: bool = Field(True, description="rotate each object uniformly at random")
    n_shapes: int | None = Field(None, ge=1, description="blobby/procedural: draw from a fixed pool of this many shapes")
    pool_seed: int = Field(0, description="seed of the fixed shape pool (n_shapes)")

    @field_validator("primitives")
    @classmethod
    def _known_primitives(cls, v):
        return _known(v, PRIMITIVES, unknown_primitive)

    @field_validator("families")
    @classmethod
    def _known_families(cls, v):
        if not v:
            raise ValueError("families must name at least one shape family")
        expand_families(v)  # raises on unknown names, listing the known ones
        return v

    def mesh_paths(self) -> list[str]:
        """Why variables: a preset that names third-party meshes (the unseen-* test sets) cannot know where
        a user keeps them, and a path relative to the working directory breaks from any other folder."""
        out: list[str] = []
        for pat in self.meshes:
            path = expand_path(pat)
            hits = sorted(glob.glob(path))
            if not hits:
                raise missing_asset(pat, path, "no mesh file matches this path/pattern")
            out.extend(hits)
        return out


class MaterialsConfig(StrictModel):
    min_count: int = Field(2, ge=1, le=8, description="fewest materials per object (one per part)")
    max_count: int = Field(3, ge=1, le=8, description="most materials per object")
    families: list[str] = Field(default_factory=lambda: ["diffuse", "plastic", "roughplastic",
                                                         "roughconductor", "principled"],
                                description="analytic material families to draw from")
    merl_fraction: float = Field(0.0, ge=0.0, le=1.0, description="share of measured (MERL) materials")
    measured: Literal["auto", "merl", "nbrdf", "generated"] = Field(
        "auto", description="measured materials: real MERL file if found else built-in Neural-BRDF fit "
                            "(auto), only one of them, or analytic stand-ins (generated)")
    holdout: Literal["train", "test", "all"] = Field(
        "train", description="held-out materials (brdf/split.toml): excluded (train), only (test), or all")
    split_file: str | None = Field(None, description="held-out split (default brdf/split.toml)")
    catalogue: str | None = Field(None, description="material catalogue TOML (default: brdf/catalogue.toml)")
    merl_dir: str | None = Field(None, description="folder of MERL .binary files (else $MSPS_MERL_DIR); "
                                                   "used only when merl_fraction > 0")
    split: Literal["field", "planes"] = Field("field", description="how the object is divided into "
                                                                   "material parts")
    albedo: Literal[GAMUTS] = Field("moderate", description="albedo colours of analytic families: moderate "
                                                            "(every channel >= half the largest; corpora up to "
                                                            "v0.4), full (saturated and dark) or mixed (a "
                                                            "third each achromatic/moderate/full; "
                                                            "docs/appearance.md)")
    texture: TextureConfig = Field(default_factory=TextureConfig,
                                   description="spatially varying appearance (docs/appearance.md)")

    @field_validator("families")
    @classmethod
    def _known_material_families(cls, v):
        return _known(v, FAMILIES, unknown_family)


class CrosstalkRandom(StrictModel):
    """`[scene.lights.crosstalk_random]`: one crosstalk matrix per frame (`lights.random_crosstalk`)."""

    diagonal: tuple[float, float] = Field((0.75, 0.95), description="own-channel share of each light [lo, hi]")
    asymmetry: float = Field(0.5, ge=0.0, le=1.0, description="how unevenly a light's leak splits over the "
                                                              "other two channels (0 = evenly, the paper)")

    @field_validator("diagonal")
    @classmethod
    def _diag(cls, v):
        if not 0.34 <= v[0] <= v[1] <= 1.0:
            raise ValueError(f"diagonal must satisfy 0.34 <= lo <= hi <= 1 (diagonally dominant), got {list(v)}")
        return v


class LightsConfig(StrictModel):
    kind: Literal["directional", "point"] = Field("directional", description="light type")
    slant_deg: float = Field(30.0, gt=0.0, lt=90.0, description="angle between each light and the view "
                                                                "axis (deg)")
    tilts_deg: list[float] = Field(default_factory=lambda: [0.0, 120.0, 240.0],
                                   description="azimuth of each light around the view axis (deg), one per "
                                               "colour channel")
    crosstalk: list[list[float]] = Field(default_factory=lambda: PAPER_CROSSTALK.tolist(),
                                         description="3x3 matrix, column k = the camera's RGB response "
                                                     "to light k (rgb mode)")
    irradiance: float = Field(3.0, gt=0.0, description="irradiance of each light on a surface facing it "
                                                       "(linear units)")
    distance: float | None = Field(None, gt=1.0, description="point lights: distance from the origin "
                                                             "(scene units)")
    jitter_deg: float = Field(0.0, ge=0.0, le=20.0, description="random perturbation of each light "
                                                                "direction per frame: drawn uniformly in "
                                                                "the cone of this half-angle (deg)")
    intensity_jitter: float = Field(0.0, ge=0.0, lt=1.0, description="relative random change of each "
                                                                     "light's intensity per frame")
    slant_range_deg: tuple[float, float] | None = Field(
        None, description="draw the slant per frame uniformly in [lo, hi] deg (robust corpora); "
                          "overrides slant_deg")
    crosstalk_random: CrosstalkRandom | None = Field(
        None, description="rgb mode: draw the crosstalk per frame (a random rig) instead of `crosstalk`")

    @field_validator("slant_range_deg")
    @classmethod
    def _range(cls, v):
        if v is not None and not (0.0 < v[0] <= v[1] < 90.0):
            raise ValueError(f"slant_range_deg must satisfy 0 < lo <= hi < 90, got {list(v)}")
        return v


class EnvironmentConfig(StrictModel):
    enabled: bool = Field(False, description="add environment (ambient) light")
    source: str = Field("procedural", description="'procedural' (seeded sky) or an env-map file "
                                                                  "(.exr, .hdr; $VARS and ~ expanded)")
    ratio: float = Field(0.1, ge=0.0, description="env irradiance / coloured-light irradiance")
    ratio_range: tuple[float, float] | None = Field(
        None, description="draw the ratio per frame uniformly in [lo, hi] (robust corpora); overrides ratio")
    random_rotation: bool = Field(True, description="rotate the env map at random per frame")

    @field_validator("ratio_range")
    @classmethod
    def _range(cls, v):
        if v is not None and not (0.0 <= v[0] <= v[1]):
            raise ValueError(f"ratio_range must satisfy 0 <= lo <= hi, got {list(v)}")
        return v


class SceneConfig(StrictModel):
    shape: ShapeConfig = ShapeConfig()
    materials: MaterialsConfig = MaterialsConfig()
    lights: LightsConfig = LightsConfig()
    environment: EnvironmentConfig = EnvironmentConfig()
    camera: CameraSpec = CameraSpec()
    integrator: IntegratorSpec = IntegratorSpec()
    # spectral mode: `spectral` is used when mode == "spectral" (defaults if absent).  The camera's
    # sensor model is not part of the scene: it is the preset's top-level `[sensor]` table.
    mode: Literal["rgb", "spectral"] = Field("rgb", description="rgb: crosstalk matrix given; spectral: "
                                                                 "light spectra x camera sensitivities")
    spectral: SpectralConfig | None = None
    rig: RigConfig | None = Field(None, description="any photometric-stereo rig: N lights x M channels, one "
                                                    "shot or one image per light, far or near (docs/rigs.md); "
                                                    "absent: the three-light [scene.lights] rig")

    @model_serializer(mode="wrap")
    def _without_absent_rig(self, handler):
        """Configs without a rig serialise (and hash) as before the rig existed: same shards, same bytes."""
        return omit_defaults(self, handler(self), ("rig",))


def _sample_shape(cfg: ShapeConfig, rng: np.random.Generator, frame_index: int | None = None) -> ShapeSpec:
    rot = random_rotation(rng) if cfg.random_rotation else ShapeSpec.model_fields["rotation"].default
    if cfg.source == "sphere":
        return ShapeSpec(kind="sphere", name="sphere", radius=cfg.radius)
    if cfg.source == "mesh":
        paths = cfg.mesh_paths()
        if not paths:
            raise InputError("shape.meshes", "source 'mesh' needs at least one mesh path")
        k = int(rng.integers(len(paths)))
        if cfg.mesh_order == "cycle" and frame_index is not None:
            k = frame_index % len(paths)
        path = paths[k]
        return ShapeSpec(kind="mesh", name=Path(path).stem, path=str(Path(path).resolve()),
                         rotation=rot, radius=cfg.radius)
    if cfg.source == "primitive":
        name = str(rng.choice(cfg.primitives))
        return ShapeSpec(kind="primitive", name=name, params=sample_primitive_params(name, rng),
                         rotation=rot, radius=cfg.radius)
    if cfg.source == "procedural":
        fams = expand_families(cfg.families)
        sub = rng
        if cfg.n_shapes:  # a fixed pool of procedural shapes (index -> same family and seed)
            idx = int(rng.integers(cfg.n_shapes))
            sub = np.random.default_rng([cfg.pool_seed, idx, 0x9F])
        name = fams[int(sub.integers(len(fams)))]
        return ShapeSpec(kind="procedural", name=name, params=sample_family_params(name, sub),
                         rotation=rot, radius=cfg.radius)
    if cfg.n_shapes:  # a fixed pool, like the 10-shape Blobby dataset (train/val split by index)
        idx = int(rng.integers(cfg.n_shapes))
        coeffs = sample_blobby_coeffs(np.random.default_rng([cfg.pool_seed, idx]), cfg.lmax, cfg.amplitude)
        name = f"blob{idx:03d}"
    else:
        coeffs = sample_blobby_coeffs(rng, cfg.lmax, cfg.amplitude)
        name = "blob"
    return ShapeSpec(kind="blobby", name=name, sh_coeffs=coeffs, subdivisions=cfg.subdivisions,
                     rotation=rot, radius=cfg.radius)


def _sample_materials(cfg: MaterialsConfig, n: int, rng: np.random.Generator):
    if cfg.merl_fraction > 0 or cfg.catalogue:
        return tuple(sample_materials(rng, n, catalogue=cfg.catalogue, merl_fraction=cfg.merl_fraction,
                                      merl_dir=cfg.merl_dir, families=cfg.families, measured=cfg.measured,
                                      holdout=cfg.holdout, split_file=cfg.split_file, gamut=cfg.albedo))
    fams = rng.choice(cfg.families, size=n, replace=len(cfg.families) < n)
    return tuple(sample_analytic(str(f), rng, gamut=cfg.albedo) for f in fams)


def sample_scene(cfg: SceneConfig, rng: np.random.Generator, seed: int | None = None,
                 frame_index: int | None = None) -> SceneSpec:
    """Draw one scene. Consumes `rng` in a fixed order (shape, materials, split, lights, env).

    `frame_index` (the frame's position in its condition) lets `shape.mesh_order = "cycle"`
    give every mesh the same number of frames; it is otherwise unused.
    """
    shape = _sample_shape(cfg.shape, rng, frame_index)
    if shape.kind == "sphere":
        n = 1
    else:
        n = int(rng.integers(cfg.materials.min_count, max(cfg.materials.min_count, cfg.materials.max_count) + 1))
    materials = _sample_materials(cfg.materials, n, rng)
    split = sample_split(rng, n, cfg.materials.split)
    if cfg.rig is not None:
        return _sample_rig_scene(cfg, rng, seed, shape, materials, split)
    lc = cfg.lights
    crosstalk, spectra, camera_response = lc.crosstalk, None, None
    if lc.crosstalk_random is not None and cfg.mode == "rgb":  # a random rig per frame
        crosstalk = random_crosstalk(rng, lc.crosstalk_random.diagonal, lc.crosstalk_random.asymmetry,
                                     len(lc.tilts_deg))
    if cfg.mode == "spectral":  # effective crosstalk of the light spectra x camera
        sc = cfg.spectral or SpectralConfig()
        if sc.random_rig is not None:  # a random LED x camera pair per frame (drawn only when asked)
            if len(sc.random_rig.peaks_nm) != len(lc.tilts_deg):
                raise InputError("scene.spectral.random_rig.peaks_nm", f"{len(sc.random_rig.peaks_nm)} peak "
                                                                       f"ranges for {len(lc.tilts_deg)} lights")
            leds, cam = sc.random_rig.draw(rng)
            sc = sc.model_copy(update={"lights": leds, "camera": cam})
        if len(sc.lights) != len(lc.tilts_deg):
            raise InputError("scene.spectral.lights", f"{len(sc.lights)} light spectra for "
                                                      f"{len(lc.tilts_deg)} light tilts")
        spectra, camera_response = sc.lights, sc.camera
        crosstalk = effective_crosstalk(sc.lights, sc.camera)
    slant = float(rng.uniform(*lc.slant_range_deg)) if lc.slant_range_deg is not None else lc.slant_deg
    lights = three_lights(slant, lc.tilts_deg, crosstalk, lc.irradiance, lc.kind, lc.distance,
                            rng=rng, jitter_deg=lc.jitter_deg, intensity_jitter=lc.intensity_jitter)
    if spectra is not None:
        lights = tuple(l.model_copy(update={"spectrum": s}) for l, s in zip(lights, spectra))
    env = None
    ec = cfg.environment
    if ec.enabled and ec.ratio_range is not None:
        ec = ec.model_copy(update={"ratio": float(rng.uniform(*ec.ratio_range))})
    if ec.enabled and ec.ratio > 0:
        env = environment_for_ratio(ec, lights_plane_irradiance(lights), rng)
    integ = cfg.integrator.model_copy(update={"seed": int(rng.integers(2**31 - 1))})
    if cfg.materials.texture.fraction > 0:  # drawn last: presets without textures keep every draw
        if cfg.mode == "spectral":
            raise InputError("scene.materials.texture", "textures need mode 'rgb' (spectral textures are "
                                                        "not supported yet)")
        materials = texture_materials(cfg.materials, shape, materials, rng)
    return SceneSpec(shape=shape, split=split, materials=materials, lights=lights, environment=env,
                     camera=cfg.camera, integrator=integ, mode=cfg.mode, camera_response=camera_response,
                     crosstalk=tuple(tuple(float(x) for x in row) for row in np.asarray(crosstalk)),
                     seed=seed)


def _sample_rig_scene(cfg: SceneConfig, rng: np.random.Generator, seed, shape, materials, split) -> SceneSpec:
    """The rest of `sample_scene` for a `[scene.rig]` (same draw order: lights, env, integrator, textures)."""
    cfg.rig.check_mode(cfg.mode)  # filters and spectra in mode "spectral" only, channels/colours in "rgb"
    lights, rig = sample_rig(cfg.rig, rng)
    if cfg.mode == "spectral":  # LED spectra x M camera channels: C is their closed-form integral (no draws)
        lights, rig = spectral_rig(cfg.rig, lights, rig)
    env = None
    ec = cfg.environment
    if ec.enabled and ec.ratio_range is not None:
        ec = ec.model_copy(update={"ratio": float(rng.uniform(*ec.ratio_range))})
    if ec.enabled and ec.ratio > 0:  # the ratio is to one image's lights (the mean shot)
        env = environment_for_ratio(ec, lights_plane_irradiance(lights) / len(rig.shots), rng)
    integ = cfg.integrator.model_copy(update={"seed": int(rng.integers(2**31 - 1))})
    if cfg.materials.texture.fraction > 0:
        if cfg.mode == "spectral":
            raise InputError("scene.materials.texture", "textures need mode 'rgb' (spectral textures are "
                                                        "not supported yet)")
        materials = texture_materials(cfg.materials, shape, materials, rng)
    return SceneSpec(shape=shape, split=split, materials=materials, lights=lights, environment=env,
                     camera=cfg.camera, integrator=integ, mode=cfg.mode, seed=seed, rig=rig)


def lights_plane_irradiance(lights) -> float:
    """Channel-summed irradiance of all lights on a camera-facing plane at the origin.

    `LightSpec.rgb` is each light's camera response on a white reflector at normal
    incidence (both modes), so this is Σ_k sum(rgb_k)·max(0, l_k·z) (point lights: /d²).
    """
    total = 0.0
    for l in lights:
        e = sum(l.rgb) * max(0.0, l.direction[2])
        if l.kind == "point":
            e /= l.distance ** 2
        total += e
    return total


def environment_for_ratio(cfg: EnvironmentConfig, light_irradiance: float, rng: np.random.Generator) -> EnvSpec:
    """Scale the env map so its irradiance on a camera-facing plane is `ratio` x the lights'.

    Both sides are channel-summed irradiance on a plane facing the camera (+z):
    `light_irradiance` is `lights_plane_irradiance(lights)` (all coloured lights
    together), the env's is `irradiance_on_axis(map, +z).sum() * scale`.  So on a
    white camera-facing plane the env adds exactly `ratio` x the lights' image
    energy (docs/physics.md).  Spectral mode keeps this meaning (the renderer
    corrects the scale for RGB->spectrum upsampling).
    """
    rot = float(rng.uniform(0, 360)) if cfg.random_rotation else 0.0
    seed = int(rng.integers(2**31 - 1))
    img = envmap_pixels(cfg.source, seed)
    e = float(irradiance_on_axis(img, (0.0, 0.0, 1.0), rot).sum())
    if not e > 0:  # validate_inputs refuses such maps first (`check_front_irradiance`)
        raise InputError(cfg.source, f"environment map sheds no light on the camera-facing plane at rotation "
                                     f"{rot:g} deg: it cannot be scaled to the ratio {cfg.ratio}")
    scale = cfg.ratio * light_irradiance / e
    return EnvSpec(source=expand_path(cfg.source), scale=float(scale), rotation_deg=rot, seed=seed,
                   ratio=cfg.ratio)  # the spec names the file read, whatever the worker's environment


def load_scene_config(path: str | Path) -> SceneConfig:
    """Read a SceneConfig from TOML: the `[scene]` table if present, else the whole file."""
    data = read_toml(path)
    return validate(SceneConfig, data.get("scene", data), path)
