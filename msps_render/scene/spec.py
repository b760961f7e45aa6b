"""`SceneSpec`: one scene as plain, validated, JSON-serialisable data.

A SceneSpec is everything the renderer needs and nothing it computes: the
sampler (`scene.sample`) draws it from a seeded Generator, the renderer
(`render.render_frame`) turns it into a `Frame`.  Keeping it pure data means a
scene can be printed, saved next to its render, diffed and re-rendered.

Conventions (see docs/physics.md): the camera frame is x right, y up, z toward
the camera; the object sits at the origin inside the unit sphere; light
directions are unit vectors pointing from the surface toward the light.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated, Literal, Union

from pydantic import Field, field_validator, model_serializer, model_validator

from msps_render.brdf.families import MATERIAL_KINDS
from msps_render.scene.textures import TextureSpec
from msps_render.config_io import FrozenModel, omit_defaults
from msps_render.errors import InputError, format_validation_error, read_text
from msps_render.rig import RigSpec
from msps_render.scene.families import SHAPE_FAMILIES, unknown_family_message
from msps_render.scene.primitives import PRIMITIVES, unknown_primitive

Vec3 = tuple[float, float, float]
RGB = tuple[float, float, float]


def _unit(v: Vec3, what: str) -> Vec3:
    n = math.sqrt(sum(c * c for c in v))
    if not math.isfinite(n) or n < 1e-9:
        raise ValueError(f"{what} must be a finite non-zero vector, got {v}")
    return tuple(float(c) / n for c in v)  # type: ignore[return-value]


# --------------------------------------------------------------------- camera
class CameraSpec(FrozenModel):
    """Orthographic by default: photometric stereo assumes a distant viewer."""

    kind: Literal["orthographic", "perspective"] = Field("orthographic", description="projection")
    width: int = Field(128, ge=8, le=8192, description="frame width (px)")
    height: int = Field(128, ge=8, le=8192, description="frame height (px)")
    # Half-extent of the orthographic view (world units); object fits in radius 1.
    extent: float = Field(1.05, gt=0, description="orthographic: half-extent of the view (scene units; "
                                                  "the object fits in radius 1)")
    fov_deg: float = Field(25.0, gt=0, lt=170, description="perspective: field of view (deg)")
    distance: float = Field(5.0, gt=1.0, description="camera distance from the origin (scene units)")


# --------------------------------------------------------------------- lights
class LightSpec(FrozenModel):
    """One light. `rgb` is irradiance (directional) or intensity (point) per channel."""

    kind: Literal["directional", "point"] = "directional"
    direction: Vec3
    rgb: RGB = (1.0, 1.0, 1.0)
    distance: float | None = Field(None, gt=1.0, description="point lights only")
    slant_deg: float | None = None
    tilt_deg: float | None = None
    spectrum: str | None = Field(None, description="spectrum id (spectral mode)")

    @field_validator("direction")
    @classmethod
    def _norm(cls, v: Vec3) -> Vec3:
        return _unit(v, "light direction")

    @field_validator("rgb")
    @classmethod
    def _nonneg(cls, v: RGB) -> RGB:
        if any((not math.isfinite(c)) or c < 0 for c in v):
            raise ValueError(f"light rgb must be finite and >= 0, got {v}")
        return v

    @model_validator(mode="after")
    def _point_needs_distance(self) -> "LightSpec":
        if self.kind == "point" and self.distance is None:
            raise ValueError("a point light needs a distance")
        return self


# ---------------------------------------------------------------- environment
class EnvSpec(FrozenModel):
    """HDR environment light: a file (EXR/HDR) or the procedural sky."""

    source: str = "procedural"  # "procedural" or a path to .exr / .hdr
    scale: float = Field(1.0, ge=0)
    rotation_deg: float = 0.0  # about the camera y (up) axis
    seed: int = 0  # procedural sky only
    ratio: float | None = Field(None, description="env/light irradiance ratio it was scaled to")


# ------------------------------------------------------------------ materials
MaterialKind = Literal[MATERIAL_KINDS]  # derived from the family registry (brdf.families)


class MaterialSpec(FrozenModel):
    """A material by kind and parameters; `name` says which library entry it came from.

    `texture` (optional) varies it across the surface: the albedo and roughness of an
    analytic kind, or, for a measured one with `blend`, the per-texel weight of `blend`
    (a second measured material) against this one (`scene.textures`)."""

    name: str
    kind: MaterialKind
    params: dict[str, Union[float, str, tuple[float, float, float]]] = Field(default_factory=dict)
    texture: TextureSpec | None = None
    blend: "MaterialSpec | None" = None


# --------------------------------------------------------------------- shapes
class ShapeSpec(FrozenModel):
    """Geometry. `blobby`: radially displaced sphere; `mesh`: a file; `sphere`: analytic;
    `primitive`: a procedural non-blobby shape (torus, capsule, superellipsoid, vase) named by
    `name` with `params`, for test sets of shapes unlike the training blobs; `procedural`: a
    seeded shape family (`name` in `families.SHAPE_FAMILIES`, params {"seed", "version"}), the
    mesh is a deterministic function of (name, seed, version)."""

    kind: Literal["blobby", "mesh", "sphere", "primitive", "procedural"]
    name: str = ""
    path: str | None = None  # mesh only
    sh_coeffs: tuple[float, ...] = ()  # blobby: real SH coefficients, l = 1..lmax
    subdivisions: int = Field(5, ge=1, le=7)  # blobby icosphere level
    rotation: tuple[Vec3, Vec3, Vec3] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    radius: float = Field(1.0, gt=0, le=1.0)  # scale of the normalised shape
    params: dict[str, float] = Field(default_factory=dict)  # primitive / procedural

    @model_validator(mode="after")
    def _check(self) -> "ShapeSpec":
        if self.kind == "mesh" and not self.path:
            raise ValueError("shape kind 'mesh' needs a path")
        if self.kind == "primitive" and self.name not in PRIMITIVES:
            raise ValueError(unknown_primitive(self.name))
        if self.kind == "procedural":
            if self.name not in SHAPE_FAMILIES:
                raise ValueError(unknown_family_message(self.name))
            if "seed" not in self.params:
                raise ValueError(f"procedural shape '{self.name}' needs params.seed")
        return self


class SplitSpec(FrozenModel):
    """How the surface is divided into material parts (each its own Mitsuba shape).

    `planes`: part = number of planes the face centroid is in front of (mod n);
    `field`: part = quantile bin of a smooth random field (sum of SH) over the surface.
    """

    kind: Literal["none", "planes", "field"] = "none"
    n_parts: int = Field(1, ge=1, le=16)
    normals: tuple[Vec3, ...] = ()
    offsets: tuple[float, ...] = ()
    field_coeffs: tuple[float, ...] = ()


# ------------------------------------------------------------------ integrator
LightsMode = Literal["one-pass", "per-light"]
SamplerKind = Literal["independent", "multijitter", "stratified", "ldsampler", "orthogonal"]


def _is_prime(n: int) -> bool:
    return n >= 2 and all(n % d for d in range(2, math.isqrt(n) + 1))


def sampler_spp_problem(sampler: str, spp: int) -> str | None:
    """Why Mitsuba would silently change `spp` for this sampler (None if it keeps it): an
    error here instead, so a preset renders the sample count it says."""
    root = math.isqrt(spp)
    if sampler == "stratified" and root * root != spp:
        return f"sampler 'stratified' needs a square spp (4, 9, 16, 25, ...), got {spp}"
    if sampler == "ldsampler" and (spp & (spp - 1) or root * root != spp):
        return f"sampler 'ldsampler' needs a power of 4 as spp (4, 16, 64, ...), got {spp}"
    if sampler == "orthogonal" and not (root * root == spp and _is_prime(root)):
        return f"sampler 'orthogonal' needs spp = p^2 with p prime (4, 9, 25, 49, ...), got {spp}"
    return None


class IntegratorSpec(FrozenModel):
    kind: Literal["path", "direct"] = Field("path", description="Mitsuba integrator")
    max_depth: int = Field(6, ge=2, le=64, description="longest light path (bounces + 1)")
    spp: int = Field(32, ge=1, le=65536, description="samples per pixel (per light)")
    seed: int = Field(0, ge=0, description="sampler seed (set per frame by the sampler)")
    lights: LightsMode = Field("one-pass", description="one-pass: one render samples every light at every "
                                                       "vertex (each light in its own channel); per-light: one "
                                                       "Mitsuba render per light (the reference, slower)")
    sampler: SamplerKind = Field("independent", description="Mitsuba sampler. 'independent': plain Monte Carlo; "
                                 "'multijitter' (stratified in every dimension) reaches independent's noise at "
                                 "~1/4 of the spp on darkroom scenes (docs/benchmarks.md, bench_sampler.py)")

    @model_validator(mode="after")
    def _spp_fits_sampler(self):
        problem = sampler_spp_problem(self.sampler, self.spp)
        if problem:
            raise ValueError(problem)
        return self


# ---------------------------------------------------------------------- scene
class SceneSpec(FrozenModel):
    shape: ShapeSpec
    split: SplitSpec = SplitSpec()
    materials: tuple[MaterialSpec, ...]
    lights: tuple[LightSpec, ...]
    environment: EnvSpec | None = None
    camera: CameraSpec = CameraSpec()
    integrator: IntegratorSpec = IntegratorSpec()
    mode: Literal["rgb", "spectral"] = "rgb"
    crosstalk: tuple[RGB, RGB, RGB] | None = None  # effective 3x3 M (rows: channels, cols: lights)
    camera_response: str | None = None  # spectral mode: camera sensitivity id
    seed: int | None = None  # the seed the scene was sampled from (provenance)
    # Any rig (msps_render.rig): channels, shots, nominal lights.  None: the three-light rig of the
    # seed paper, and then left out of the JSON so stored three-light scenes keep their bytes.
    rig: RigSpec | None = None

    @model_serializer(mode="wrap")
    def _without_absent_rig(self, handler):
        return omit_defaults(self, handler(self), ("rig",))

    @model_validator(mode="before")
    @classmethod
    def _stored_before_one_pass(cls, data):
        """A stored scene whose integrator has no `lights` was rendered per light (before the field
        existed): it loads, and re-renders, that way (exports re-render per-light images from it)."""
        if isinstance(data, dict) and isinstance(data.get("integrator"), dict) and "lights" not in data["integrator"]:
            data = {**data, "integrator": {**data["integrator"], "lights": "per-light"}}
        return data

    @model_validator(mode="after")
    def _check(self) -> "SceneSpec":
        if not self.materials:
            raise ValueError("a scene needs at least one material")
        if self.split.kind != "none" and len(self.materials) < self.split.n_parts:
            raise ValueError(
                f"split has {self.split.n_parts} parts but only {len(self.materials)} materials"
            )
        if not self.lights and self.environment is None:
            raise ValueError("a scene needs at least one light or an environment")
        if self.rig is not None and len(self.rig.nominal_dirs) != len(self.lights):
            raise ValueError(f"rig has {len(self.rig.nominal_dirs)} nominal lights for {len(self.lights)} lights")
        if self.shape.kind == "sphere" and self.split.kind != "none":
            raise ValueError("the analytic sphere cannot be split into parts; use kind 'blobby'")
        return self

    # ---- serialisation
    def to_json(self, indent: int | None = 2) -> str:
        return self.model_dump_json(indent=indent)

    @classmethod
    def from_json(cls, text: str, source: str = "<string>") -> "SceneSpec":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise InputError(source, f"not valid JSON ({e})") from None
        try:
            return cls.model_validate(data)
        except Exception as e:  # pydantic.ValidationError
            raise InputError(source, format_validation_error(e)) from None

    @classmethod
    def load(cls, path: str | Path) -> "SceneSpec":
        p = Path(path)
        return cls.from_json(read_text(p, "scene file"), str(p))

    def summary(self) -> str:
        """One human-readable line per component (for logs and `msps inspect`)."""
        L = [f"shape: {self.shape.kind} {self.shape.name or self.shape.path or ''}".rstrip()]
        L.append(f"parts: {self.split.kind} x{self.split.n_parts}; materials: "
                 + ", ".join(m.name for m in self.materials))
        for i, l in enumerate(self.lights):
            L.append(f"light {i}: {l.kind} dir=({l.direction[0]:+.3f},{l.direction[1]:+.3f},"
                     f"{l.direction[2]:+.3f}) rgb={tuple(round(c, 4) for c in l.rgb)}")
        if self.environment:
            e = self.environment
            L.append(f"environment: {e.source} scale={e.scale:g} rot={e.rotation_deg:.1f}deg")
        c = self.camera
        L.append(f"camera: {c.kind} {c.width}x{c.height}; integrator: {self.integrator.kind} "
                 f"depth={self.integrator.max_depth} spp={self.integrator.spp} lights={self.integrator.lights}; "
                 f"mode: {self.mode}")
        return "\n".join(L)
