"""Procedural primitives (torus, capsule, superellipsoid, vase): shapes unlike the training
blobs, for test sets.  The registry `PRIMITIVES` holds each one's mesh builder and parameter
sampler; an unknown name is an error, never a fallback."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from msps_render.errors import InputError, closest
from msps_render.scene.geometry import icosphere


def _torus(p):
    import trimesh

    m = trimesh.creation.torus(major_radius=1.0, minor_radius=p.get("minor", 0.4), major_sections=96,
                               minor_sections=48)
    return np.asarray(m.vertices), np.asarray(m.faces)


def _capsule(p):
    import trimesh

    m = trimesh.creation.capsule(height=p.get("height", 1.0), radius=p.get("radius", 0.5), count=[48, 48])
    return np.asarray(m.vertices), np.asarray(m.faces)


def _superellipsoid(p):
    """Signed-power map of a sphere: exponent < 1 gives rounded boxes, > 1 pinched shapes."""
    d, f = icosphere(5)
    e = np.array([p.get("ex", 0.6), p.get("ey", 0.6), p.get("ez", 0.6)])
    scale = np.array([p.get("sx", 1.0), p.get("sy", 0.8), p.get("sz", 0.7)])
    return np.sign(d) * np.abs(d) ** e * scale, f


def _vase(p):
    """Surface of revolution of a smooth wavy profile (concave regions => cast shadows)."""
    import trimesh

    z = np.linspace(-1.0, 1.0, 96)
    r = p.get("base", 0.45) + p.get("wave", 0.18) * np.sin(np.pi * p.get("freq", 1.5) * z + p.get("phase", 0.0))
    r = r * np.sqrt(np.clip(1 - z ** 2, 0, None)) ** 0.3  # close the ends smoothly
    r[0] = r[-1] = 0.0
    m = trimesh.creation.revolve(np.stack([r, z], 1), sections=96)
    return np.asarray(m.vertices), np.asarray(m.faces)


def _torus_params(rng: np.random.Generator) -> dict[str, float]:
    return {"minor": float(rng.uniform(0.25, 0.5))}


def _capsule_params(rng: np.random.Generator) -> dict[str, float]:
    return {"height": float(rng.uniform(0.5, 1.5)), "radius": float(rng.uniform(0.35, 0.6))}


def _superellipsoid_params(rng: np.random.Generator) -> dict[str, float]:
    return {k: float(rng.uniform(0.4, 1.6)) for k in ("ex", "ey", "ez")} | {
        k: float(rng.uniform(0.6, 1.0)) for k in ("sx", "sy", "sz")}


def _vase_params(rng: np.random.Generator) -> dict[str, float]:
    return {"base": float(rng.uniform(0.35, 0.55)), "wave": float(rng.uniform(0.08, 0.22)),
            "freq": float(rng.uniform(1.0, 2.5)), "phase": float(rng.uniform(0, 2 * np.pi))}


@dataclass(frozen=True)
class Primitive:
    """A procedural primitive: `build(params) -> (vertices, faces)`, `sample(rng) -> params`."""

    build: Callable[[dict], tuple[np.ndarray, np.ndarray]]
    sample: Callable[[np.random.Generator], dict[str, float]]


# The registry: one entry adds a primitive (ShapeSpec validation and sampling use these names).
PRIMITIVES: dict[str, Primitive] = {
    "torus": Primitive(_torus, _torus_params),
    "capsule": Primitive(_capsule, _capsule_params),
    "superellipsoid": Primitive(_superellipsoid, _superellipsoid_params),
    "vase": Primitive(_vase, _vase_params),
}


def unknown_primitive(name: str) -> str:
    return f"unknown primitive '{name}'{closest(name, PRIMITIVES)} (known: {', '.join(PRIMITIVES)})"


def primitive(name: str) -> Primitive:
    """The registered primitive `name`; `InputError` for an unknown name."""
    p = PRIMITIVES.get(name)
    if p is None:
        raise InputError("shape.name", unknown_primitive(name))
    return p


def sample_primitive_params(name: str, rng: np.random.Generator) -> dict[str, float]:
    return primitive(name).sample(rng)


def build_primitive(name: str, params: dict) -> tuple[np.ndarray, np.ndarray]:
    return primitive(name).build(params)
