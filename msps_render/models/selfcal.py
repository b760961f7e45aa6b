"""Object-level albedo-colour self-calibration: undo one uniform albedo colour before the network.

Why: a Lambertian pixel reads c = diag(rho) A n with A = crosstalk @ light_dirs, so
one RGB image cannot tell a coloured albedo from a change of shading.  Over a
whole object of *uniform* albedo colour the ambiguity is only three numbers,
and the unit length of the normals fixes them: with a = 1 / rho,

    || A^-1 diag(a) c(x) ||^2 = 1   for every lit pixel x,

which many pixels of varied normal over-determine (a 40x40 patch rarely has
enough normal variation; a whole object has).  The fit is compared with the
grey hypothesis a = s (1, 1, 1): only when the colour fit explains the pixels
clearly better (residual below `accept` times the grey one) is the image
rescaled, so grey, textured and non-Lambertian objects pass through unchanged.
A second condition guards objects of several materials, where one material can fit well
while the others are ignored (a channel's factor driven towards 0): at least `MIN_SHARE`
of the lit pixels must have one albedo after the factor (|b| within `SHARE_TOL`, log, of
the median -- the refinement's one-albedo test; chosen on validation frames,
docs/history.md "Stage 9").  And the grey hypothesis goes first: when the pixels already
pass that test with no factor, grey explains the object and a colour fit would be fitting
interreflections in its creases (docs/history.md "Stage 10").
The scale is normalised to mean 1, so the image keeps its exposure.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_IU, _JU = np.triu_indices(3)
REL_FLOOR = 0.1  # a pixel is used when every channel exceeds this fraction of the channel's 99th percentile over the object
MIN_PIXELS = 200
ACCEPT = 0.7  # colour residual / grey residual below this -> rescale
SHARE_TOL = 0.1  # |log(|b| / median |b|)| below this after the factor: a pixel has the fitted albedo
MIN_SHARE = 0.9  # share of lit pixels with the fitted albedo needed to rescale (docs/history.md "Stage 9")


@dataclass(frozen=True)
class ColourFit:
    """What the fit found for one object: the per-channel factor and why it was (not) applied."""

    scale: np.ndarray  # (3,) multiplies the image's channels; (1, 1, 1) when not applied
    fitted: np.ndarray  # (3,) the colour fit's factor, mean 1, whether applied or not
    grey_rms: float  # rms of |n|^2 - 1 under the grey hypothesis
    colour_rms: float  # ... under the fitted colour
    n_pixels: int
    applied: bool
    share: float = float("nan")  # lit pixels whose |b| after the factor is within SHARE_TOL of the median
    grey_share: float = float("nan")  # ... with no factor: >= MIN_SHARE means grey already explains them

    @property
    def ratio(self) -> float:
        return self.colour_rms / max(self.grey_rms, 1e-12)


def _unit_norm_residual(a: np.ndarray, c: np.ndarray, B: np.ndarray) -> np.ndarray:
    ac = c * a
    return np.einsum("ni,ij,nj->n", ac, B, ac) - 1.0


def fit_scale(c: np.ndarray, B: np.ndarray, iters: int = 30) -> np.ndarray:
    """Least-squares a (3,) of sum_x (|A^-1 diag(a) c_x|^2 - 1)^2: linear fit of a a^T, rank-1, then Gauss-Newton."""
    X = (c[:, _IU] * c[:, _JU]) * B[_IU, _JU] * np.where(_IU == _JU, 1.0, 2.0)
    q, *_ = np.linalg.lstsq(X, np.ones(len(c)), rcond=None)
    Q = np.zeros((3, 3))
    Q[_IU, _JU] = q
    Q[_JU, _IU] = q
    w, V = np.linalg.eigh(Q)
    a = np.abs(V[:, -1]) * np.sqrt(max(w[-1], 1e-12))
    g = X.sum(1)  # grey start as a fallback when the rank-1 start is worse
    a_grey = np.full(3, np.sqrt(max((g @ np.ones(len(c))) / max(g @ g, 1e-300), 1e-12)))
    if np.mean(_unit_norm_residual(a_grey, c, B) ** 2) < np.mean(_unit_norm_residual(a, c, B) ** 2):
        a = a_grey
    lam = 1e-3
    r = _unit_norm_residual(a, c, B)
    for _ in range(iters):  # Levenberg-Marquardt on three unknowns
        J = 2.0 * c * ((c * a) @ B)  # d r / d a
        H = J.T @ J
        step = np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), -J.T @ r)
        a_new = a + step
        r_new = _unit_norm_residual(a_new, c, B)
        if r_new @ r_new < r @ r:
            a, r, lam = a_new, r_new, lam * 0.3
            if np.abs(step).max() < 1e-7 * np.abs(a).max():
                break
        else:
            lam *= 10.0
    return a


def albedo_share(a: np.ndarray, c: np.ndarray, B: np.ndarray, tol: float = SHARE_TOL) -> float:
    """Share of pixels c (N, 3) whose |b| = |A^-1 diag(a) c| lies within `tol` (log) of the median:
    one uniform albedo explains them.  Why: the residual ratio alone accepts an object where one
    material of several fits well and the rest is ignored (a channel's factor driven to ~0)."""
    q = np.einsum("ni,ij,nj->n", c * a, B, c * a)
    nb = np.sqrt(np.maximum(q, 1e-24))
    return float((np.abs(np.log(nb / np.median(nb))) < tol).mean())


def fit_albedo_colour(image: np.ndarray, mask: np.ndarray, light_dirs: np.ndarray, crosstalk: np.ndarray,
                      accept: float = ACCEPT, rel_floor: float = REL_FLOOR,
                      min_pixels: int = MIN_PIXELS, min_share: float = MIN_SHARE,
                      grey_first: bool = True) -> ColourFit:
    """Fit one uniform albedo colour to an object's lit pixels; `image` (H, W, 3), `mask` (H, W).
    `grey_first`: refuse when the pixels pass the one-albedo test with no factor."""
    c = np.asarray(image, np.float64)[np.asarray(mask, bool)]
    none = ColourFit(np.ones(3), np.ones(3), float("nan"), float("nan"), 0, False)
    if len(c) == 0:
        return none
    top = np.percentile(c, 99.0, axis=0)  # not the max: one specular highlight would set it
    lit = (c > rel_floor * top).all(1) & (top > 0).all()
    c = c[lit]
    if len(c) < min_pixels:
        return ColourFit(np.ones(3), np.ones(3), float("nan"), float("nan"), int(len(c)), False)
    Ai = np.linalg.inv(np.asarray(crosstalk, np.float64) @ np.asarray(light_dirs, np.float64))
    B = Ai.T @ Ai
    g = np.einsum("ni,ij,nj->n", c, B, c)
    s2 = g.sum() / max(g @ g, 1e-300)
    grey = float(np.sqrt(np.mean((s2 * g - 1.0) ** 2)))
    a = fit_scale(c, B)
    colour = float(np.sqrt(np.mean(_unit_norm_residual(a, c, B) ** 2)))
    fitted = a / a.mean()
    share = albedo_share(a, c, B)
    grey_share = albedo_share(np.ones(3), c, B)
    ok = bool(np.all(fitted > 0) and np.isfinite(colour) and colour < accept * grey and share >= min_share
              and not (grey_first and grey_share >= min_share))
    return ColourFit(fitted if ok else np.ones(3), fitted, grey, colour, int(len(c)), ok, share, grey_share)


def apply_colour_fit(image: np.ndarray, fit: ColourFit) -> np.ndarray:
    return (np.asarray(image) * fit.scale).astype(np.asarray(image).dtype, copy=False)


SUFFIX = "+selfcal"  # a method's name with the self-calibration in front of it
DESCRIPTION = "after object-level albedo-colour self-calibration (models/selfcal.py)"


def self_calibrated(image: np.ndarray, mask: np.ndarray, light_dirs: np.ndarray,
                    crosstalk: np.ndarray) -> np.ndarray:
    """The image with its object's uniform albedo colour divided out when the fit accepts one."""
    return apply_colour_fit(image, fit_albedo_colour(image, mask, light_dirs, crosstalk))
