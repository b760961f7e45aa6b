"""Lambertian refinement: the closed form where the image agrees with it, the network elsewhere.

Why: with the albedo colour divided out (models/selfcal.py) a Lambertian pixel of
albedo rho reads, per light k after unmixing the crosstalk, s_k = rho max(0, l_k . n).
Where all three lights reach the pixel, calibrated Lambertian PS gives n exactly;
where one light is shadowed, the two others and |n| = 1 leave two candidate
normals.  On the unseen grey meshes the network is 5-10 degrees off on pixels where
this closed form is within 1 degree; the closed form is off where its model breaks
(cast shadows, interreflections, highlights, another albedo).  So the network
decides and the closed form refines:

* only objects of one albedo: at least `uniform_share` of the three-light pixels
  have |b| = |rho n| within `albedo_tol` (log) of the median rho.  Textured,
  multi-material, glossy and environment-lit objects fail it and keep the
  network's normals (the closed form is biased on them: measured, Stage 8);
* three lights: Lambertian PS where the pixel has the object's albedo
  (interreflections brighten, cast shadows darken) and lies within `agree_deg`
  of the network;
* one light shadowed (attached or cast shadow): of the two normals the other
  two lights allow, the one nearer the network, when within `agree_deg` of it;
* everything else: the network.
The thresholds were chosen on the whole-frame validation sets (`val-frames`,
`val-frames-grey`, `val-frames-colour`: procedural shapes, training materials),
never on a test set (docs/history.md "Stage 8").
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SUFFIX = "+refine"  # a method's name with the refinement after it
DESCRIPTION = "refined by the Lambertian closed form where the image agrees with it (models/refine.py)"


@dataclass(frozen=True)
class RefineSettings:
    """Chosen on the validation frames by the rule in docs/history.md "Stage 8" (grid: floor 0.05/0.1/0.2,
    tolerance 0.05/0.1/0.2, agreement 15/30/45 deg, share 0.7-0.95); 45 deg is the grid's edge."""

    shadow_floor: float = 0.05  # a light reaches a pixel when its shading exceeds this share of its 99th percentile
    albedo_tol: float = 0.1  # |log(|b| / rho)| below this: the pixel has the object's albedo
    agree_deg: float = 45.0  # the closed form is taken only this near the network's normal
    uniform_share: float = 0.9  # share of three-light pixels with the object's albedo to refine at all
    min_pixels: int = 50  # three-light pixels needed to estimate rho


@dataclass(frozen=True)
class ObjectAlbedo:
    """One object's albedo as the refinement sees it (estimated on the whole frame, so that
    patches of the frame are refined exactly as the frame is)."""

    rho: float  # median |b| over three-light pixels; nan when fewer than `min_pixels`
    uniform: float  # share of three-light pixels within `albedo_tol` of rho
    top: np.ndarray  # (3,) each light's 99th-percentile shading over the object
    n_three: int  # three-light pixels

    def accepts(self, settings: "RefineSettings") -> bool:
        return bool(np.isfinite(self.rho) and self.uniform >= settings.uniform_share)


@dataclass(frozen=True)
class RefineStats:
    """What the refinement did to one object."""

    albedo: ObjectAlbedo
    n_pixels: int  # mask pixels
    n_three: int  # pixels given the three-light normal
    n_two: int  # pixels given a two-light normal


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _shading(c: np.ndarray, crosstalk: np.ndarray) -> np.ndarray:
    """Per-light shading s_k = rho max(0, l_k . n) of pixels c (N, 3): the crosstalk unmixed."""
    return np.asarray(c, np.float64) @ np.linalg.inv(np.asarray(crosstalk, np.float64)).T


def estimate_albedo(image: np.ndarray, mask: np.ndarray, light_dirs: np.ndarray, crosstalk: np.ndarray,
                    settings: RefineSettings = RefineSettings()) -> ObjectAlbedo:
    """rho and how much of the object has it, from the object's pixels (`mask` (H, W))."""
    shading = _shading(np.asarray(image)[np.asarray(mask, bool)], crosstalk)
    if len(shading) == 0:
        return ObjectAlbedo(float("nan"), 0.0, np.ones(3), 0)
    top = np.maximum(np.percentile(shading, 99.0, axis=0), 1e-12)  # not the max: a highlight would set it
    three = (shading > settings.shadow_floor * top).all(1)
    if three.sum() < settings.min_pixels:
        return ObjectAlbedo(float("nan"), 0.0, top, int(three.sum()))
    nb = np.linalg.norm(shading[three] @ np.linalg.inv(np.asarray(light_dirs, np.float64)).T, axis=1)
    rho = float(np.median(nb))
    uniform = float((np.abs(np.log(np.maximum(nb, 1e-12) / rho)) < settings.albedo_tol).mean())
    return ObjectAlbedo(rho, uniform, top, int(three.sum()))


def two_light_normals(shading: np.ndarray, light_dirs: np.ndarray, rho: float, shadowed: int,
                      near: np.ndarray) -> np.ndarray:
    """Unit normals with rho l_i . n = s_i for the two lights other than `shadowed`, the one of the
    two solutions nearer `near` (N, 3).  When noise leaves the line of solutions outside the unit
    sphere, its point nearest the sphere."""
    i, j = (k for k in range(3) if k != shadowed)
    li, lj = np.asarray(light_dirs[i], np.float64), np.asarray(light_dirs[j], np.float64)
    G = np.array([[li @ li, li @ lj], [li @ lj, lj @ lj]])
    coef = (np.stack([shading[:, i], shading[:, j]], 1) / rho) @ np.linalg.inv(G).T
    n0 = coef[:, :1] * li + coef[:, 1:] * lj  # in span(li, lj): l_i . n0 = s_i / rho
    u = _unit(np.cross(li, lj))
    t = np.sqrt(np.maximum(1.0 - (n0 * n0).sum(1), 0.0))[:, None]
    plus, minus = _unit(n0 + t * u), _unit(n0 - t * u)
    return np.where(((plus * near).sum(1) >= (minus * near).sum(1))[:, None], plus, minus)


def refine_pixels(c: np.ndarray, net: np.ndarray, light_dirs: np.ndarray, crosstalk: np.ndarray,
                  albedo: ObjectAlbedo, settings: RefineSettings = RefineSettings()
                  ) -> tuple[np.ndarray, int, int]:
    """Pixels c (N, 3) of one object with the network's normals `net` (N, 3): (normals, n_three, n_two);
    the pixels not refined keep `net` exactly."""
    given = np.asarray(net)
    if not albedo.accepts(settings) or len(c) == 0:
        return given, 0, 0
    net = _unit(given.astype(np.float64))
    L = np.asarray(light_dirs, np.float64)
    shading = _shading(c, crosstalk)
    reached = shading > settings.shadow_floor * albedo.top
    b = shading @ np.linalg.inv(L).T  # rho n where all three lights reach the pixel
    nb = np.linalg.norm(b, axis=1)
    same_albedo = np.abs(np.log(np.maximum(nb, 1e-12) / albedo.rho)) < settings.albedo_tol
    lam = _unit(b)
    out = given.astype(np.float64)
    take3 = reached.all(1) & same_albedo & (_angle_deg(lam, net) < settings.agree_deg)
    out[take3] = lam[take3]
    n_two = 0
    for k in range(3):
        sel = ~reached[:, k] & reached[:, [a for a in range(3) if a != k]].all(1)
        if not sel.any():
            continue
        cand = two_light_normals(shading[sel], L, albedo.rho, k, net[sel])
        # no test of the shadowed light's reading: in a cast shadow the true normal faces that light
        ok = _angle_deg(cand, net[sel]) < settings.agree_deg
        out[np.flatnonzero(sel)[ok]] = cand[ok]
        n_two += int(ok.sum())
    return out, int(take3.sum()), n_two


def refine_normals(image: np.ndarray, mask: np.ndarray, normals: np.ndarray, light_dirs: np.ndarray,
                   crosstalk: np.ndarray, settings: RefineSettings = RefineSettings()
                   ) -> tuple[np.ndarray, RefineStats]:
    """The network's `normals` (H, W, 3) of one object, refined where `image` (H, W, 3, albedo colour
    already divided out) agrees with the Lambertian closed form; `mask` (H, W) the object."""
    m = np.asarray(mask, bool)
    albedo = estimate_albedo(image, m, light_dirs, crosstalk, settings)
    out = np.array(normals, np.float32, copy=True)
    refined, n3, n2 = refine_pixels(np.asarray(image)[m], np.asarray(normals)[m], light_dirs, crosstalk,
                                    albedo, settings)
    if n3 or n2:
        out[m] = refined.astype(np.float32)
    return out, RefineStats(albedo, int(m.sum()), n3, n2)
