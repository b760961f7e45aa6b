"""Segment-wise albedo self-calibration: one colour per region between colour edges.

Why: `models/selfcal.py` fits ONE albedo colour per object from the unit length of the normals,
so a textured object (colour patches, stripes, decals) passes through with its colours tangled
with the shading -- the network then reads colour edges as normal changes.  But a texture's
colour is piecewise smooth while the shading of a smooth surface is smooth: where the image's log
jumps, the albedo jumped.  Cut the object at those jumps and each region is a small object of
(nearly) one albedo, where the same unit-norm fit pins its colour AND its brightness (the fit's
scale is absolute: |A^-1 diag(a) c| = 1).  Dividing every region by its own fit leaves an image
of albedo ~1 everywhere: the network no longer sees the texture, and the Lambertian refinement's
one-albedo test (models/refine.py) can accept the object.

A region is used only when the fit holds there: enough lit pixels, a positive factor, and at least
`min_share` of its pixels at one albedo after the factor (the refinement's test).  Pixels on edges,
in small or refused regions take the factor of the nearest accepted region.  Only objects the
object-level fit leaves alone and that grey does not already explain are touched (grey, uniform
colour: unchanged).  Thresholds chosen on `val-frames-texture` / `-grey` / `-colour` (procedural
shapes), never on a test set (docs/history.md "Stage 12").
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msps_render.models import selfcal

SUFFIX = "+segments"  # after selfcal's: NAME+selfcal+segments
DESCRIPTION = "after the object-level and the segment-wise albedo self-calibration (models/segments.py)"


@dataclass(frozen=True)
class SegmentSettings:
    """Chosen on the validation frames by experiments/segment_sweep.py (docs/history.md "Stage 12"):
    the lowest val-frames-texture error with val-frames-grey and -colour no worse than +0.10 deg."""

    edge: float = 0.06  # |grad log c| (max over channels, per pixel) above this: a colour edge
    min_pixels: int = 150  # pixels a region needs for its own fit
    rel_floor: float = 0.1  # a pixel is lit when each channel exceeds this share of the object's 99th percentile
    min_share: float = 0.8  # share of a region's pixels at one albedo after its factor
    min_regions: int = 2  # accepted regions needed (one region is the object-level fit, which refused)
    object_share: float = 0.8  # share of the object's lit pixels at one albedo after the factors
    local_floor: int = 0  # > 0: the lit floor is relative to each channel's maximum within this window (px)
    fill: str = "nearest"  # pixels outside accepted regions: "nearest" region's factor, or "consistent": of the
    #                        regions within `fill_radius`, the one whose factor gives the pixel unit albedo
    fill_radius: float = 12.0


@dataclass(frozen=True)
class SegmentFit:
    """What the segment-wise fit did to one object."""

    scale: np.ndarray  # (H, W, 3) multiplies the image; ones where nothing was applied
    labels: np.ndarray  # (H, W) int region of each pixel, 0 = edge, shadow or background
    accepted: tuple[int, ...]  # labels of the regions whose own fit was used
    applied: bool
    reason: str = ""
    object_share: float = float("nan")  # lit pixels of the object at one albedo after the factors

    @property
    def n_regions(self) -> int:
        return int(self.labels.max())


def colour_regions(image: np.ndarray, mask: np.ndarray, settings: SegmentSettings = SegmentSettings()
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(labels (H, W), lit (H, W)): connected lit object pixels between jumps of the log image.

    Only lit pixels (every channel above `rel_floor` of its 99th percentile over the object) make
    regions: a shadow would otherwise join two patches of different colour (floored logs are flat
    there; measured on validation: 16.34 vs 15.66 deg, docs/history.md "Stage 12").  The price:
    a patch whose darkest channel falls below the floor loses its dim side to its neighbours' factor."""
    from scipy import ndimage

    c = np.asarray(image, np.float64)
    m = np.asarray(mask, bool)
    top = np.percentile(c[m], 99.0, axis=0) if m.any() else np.ones(3)
    if settings.local_floor > 0:  # a dark patch is lit against its own brightness, not the object's brightest
        top = np.stack([ndimage.maximum_filter(np.where(m, np.minimum(c[..., k], top[k]), 0.0),
                                               size=settings.local_floor) for k in range(3)], -1)
    lit = m & (c > settings.rel_floor * np.maximum(top, 1e-12)).all(-1)
    logc = np.log(np.maximum(c, 1e-6))
    grad = np.zeros(m.shape)
    for ch in range(3):
        gy, gx = np.gradient(logc[..., ch])
        grad = np.maximum(grad, np.hypot(gx, gy))
    inner = lit & ndimage.binary_erosion(lit)  # gradients across the lit area's border are not colour edges
    labels, _ = ndimage.label(inner & (grad < settings.edge))
    return labels, lit


def fit_segments(image: np.ndarray, mask: np.ndarray, light_dirs: np.ndarray, crosstalk: np.ndarray,
                 settings: SegmentSettings = SegmentSettings(), whole: selfcal.ColourFit | None = None
                 ) -> SegmentFit:
    """Per-region albedo factors of one object (`image` (H, W, 3) linear, `mask` (H, W)); `whole`: the
    object-level fit of the same image when the caller has it (else made here)."""
    m = np.asarray(mask, bool)
    ones = np.ones(m.shape + (3,))
    if whole is None:
        whole = selfcal.fit_albedo_colour(image, m, light_dirs, crosstalk)
    if whole.applied:
        return SegmentFit(ones, np.zeros(m.shape, int), (), False, "one colour fits the object")
    if whole.grey_share >= selfcal.MIN_SHARE:
        return SegmentFit(ones, np.zeros(m.shape, int), (), False, "grey explains the object")
    labels, lit = colour_regions(image, m, settings)
    Ai = np.linalg.inv(np.asarray(crosstalk, np.float64) @ np.asarray(light_dirs, np.float64))
    B = Ai.T @ Ai
    c = np.asarray(image, np.float64)
    factor = np.full(m.shape + (3,), np.nan)
    accepted = []
    sizes = np.bincount(labels.ravel())
    for r in np.flatnonzero(sizes >= settings.min_pixels):
        if r == 0:
            continue
        sel = labels == r
        cr = c[sel]
        a = selfcal.fit_scale(cr, B)
        if not (np.all(a > 0) and np.all(np.isfinite(a))):
            continue
        if selfcal.albedo_share(a, cr, B) < settings.min_share:
            continue
        factor[sel] = a
        accepted.append(int(r))
    if len(accepted) < max(settings.min_regions, 1):
        return SegmentFit(ones, labels, tuple(accepted), False, f"{len(accepted)} region(s) with a fit")
    scale = _fill(factor, labels, accepted, c, B, settings)
    scale /= np.median(scale[m].mean(-1))  # keep the image's exposure: albedo ~1 becomes the median albedo
    scale[~m] = 1.0
    share = selfcal.albedo_share(np.ones(3), (c * scale)[lit], B)
    if share < settings.object_share:
        return SegmentFit(ones, labels, tuple(accepted), False, f"one albedo for {share:.0%} of the object after "
                          "the factors", share)
    return SegmentFit(scale, labels, tuple(accepted), True, "", share)


def _fill(factor: np.ndarray, labels: np.ndarray, accepted: list[int], c: np.ndarray, B: np.ndarray,
          settings: SegmentSettings) -> np.ndarray:
    """(H, W, 3) factors everywhere: the accepted regions' own, elsewhere by `settings.fill`."""
    from scipy import ndimage

    have = np.isfinite(factor[..., 0])
    _, (iy, ix) = ndimage.distance_transform_edt(~have, return_indices=True)
    scale = factor[iy, ix]
    if settings.fill != "consistent":
        return scale
    best = np.full(have.shape, 0.1)  # |log |b|| must beat the refinement's one-albedo tolerance
    for r in accepted:
        near = ~have & (ndimage.distance_transform_edt(labels != r) <= settings.fill_radius)
        if not near.any():
            continue
        a = factor[labels == r][0]
        ca = c[near] * a
        err = np.abs(0.5 * np.log(np.maximum(np.einsum("ni,ij,nj->n", ca, B, ca), 1e-24)))
        take = err < best[near]
        idx = np.flatnonzero(near.ravel())[take]
        best.ravel()[idx] = err[take]
        scale.reshape(-1, 3)[idx] = a
    return scale


def calibrated(image: np.ndarray, mask: np.ndarray, light_dirs: np.ndarray, crosstalk: np.ndarray,
               settings: SegmentSettings = SegmentSettings()) -> np.ndarray:
    """The image after the object-level self-calibration or, where that leaves it, the segment-wise one."""
    whole = selfcal.fit_albedo_colour(image, mask, light_dirs, crosstalk)
    if whole.applied:
        return selfcal.apply_colour_fit(image, whole)
    fit = fit_segments(image, mask, light_dirs, crosstalk, settings, whole)
    img = np.asarray(image)
    return (img * fit.scale).astype(img.dtype, copy=False) if fit.applied else img
