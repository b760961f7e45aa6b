"""Calibrated Lambertian photometric stereo on the three channels of one image (Woodham).

With light k of direction l_k whose response in channel i on a white surface
is M[i, k] (the crosstalk matrix), a Lambertian pixel of grey albedo rho and
normal n reads c_i = rho * sum_k M[i, k] max(0, l_k . n).  Ignoring the
max (unshadowed pixels) this is c = rho * M L n, so n = normalise((M L)^-1 c).
The grey-albedo assumption is the paper's "constant albedo" baseline: coloured
surfaces break it, which is exactly why the network is needed.
"""
from __future__ import annotations

import numpy as np


def lambertian_ps(image: np.ndarray, light_dirs: np.ndarray, crosstalk: np.ndarray,
                  mask: np.ndarray | None = None) -> np.ndarray:
    """Normals (..., 3) from an image (..., 3); light_dirs rows = unit vectors toward the lights."""
    A = np.asarray(crosstalk, dtype=np.float64) @ np.asarray(light_dirs, dtype=np.float64)  # c = A (rho n)
    b = np.asarray(image, dtype=np.float64) @ np.linalg.inv(A).T
    n = b / np.maximum(np.linalg.norm(b, axis=-1, keepdims=True), 1e-12)
    n[np.linalg.norm(b, axis=-1) < 1e-12] = (0.0, 0.0, 1.0)
    if mask is not None:
        n = np.where(np.asarray(mask, bool)[..., None], n, 0.0)
    return n.astype(np.float32)


def unshadowed(normal: np.ndarray, light_dirs: np.ndarray, mask: np.ndarray, margin: float = 0.02) -> np.ndarray:
    """Pixels lit by every light (n . l_k > margin for all k): where Lambertian PS is exact."""
    d = np.asarray(normal) @ np.asarray(light_dirs).T
    return np.asarray(mask, bool) & (d > margin).all(-1)


# ------------------------------------------------------------------ any rig: N lights x M channels
def rig_observations(shots: np.ndarray, rig, points: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(readings (P, K), model rows (P, K, 3)) of P pixels: K = S*M readings per pixel, reading k = row_k . (rho n).

    shots (S, P, M); row (s, m) = sum_{n in s} C[m, n] a_n(x) l_n(x) (msps_render.rig's image model:
    near lights give every pixel its own directions and fall-off, from its surface point)."""
    from msps_render.rig import pixel_factors_dirs

    S, P, M = shots.shape
    C = np.asarray(rig.crosstalk, np.float64)
    if points is None or not rig.has_point_lights:
        A = rig.observation_matrix()  # (S*M, 3)
        rows = np.broadcast_to(A, (P,) + A.shape)
    else:
        L, a = pixel_factors_dirs(rig, points)  # (N, P, 3), (N, P)
        La = L * a[..., None]
        rows = np.concatenate([np.einsum("mn,npi->pmi", C[:, list(s)], La[list(s)]) for s in rig.shot_list], axis=1)
    readings = np.transpose(shots, (1, 0, 2)).reshape(P, S * M).astype(np.float64)
    return readings, rows


def lambertian_ps_rig(shots: np.ndarray, rig, mask: np.ndarray | None = None, points: np.ndarray | None = None,
                      discard: tuple[float, float] = (0.0, 0.0), chunk: int = 8192) -> np.ndarray:
    """Calibrated least-squares photometric stereo for any rig: normals (H, W, 3) from shots (S, H, W, M).

    Every reading of a pixel (S shots x M channels) is one equation row . (rho n) = I with a grey
    albedo rho (the classic baseline; white lights make it exact for coloured surfaces channel by
    channel only if the channels are solved apart, which a grey model does not need on DiLiGenT-style
    data once each channel is divided by its light's intensity -- C does that).  `discard` = (dark,
    bright): the standard robust variant drops that fraction of each pixel's darkest readings
    (shadows) and brightest (highlights) shots before solving (a multiplexed single shot has nothing
    to drop).  Needs >= 3 independent readings left; pixels without them get (0, 0, 1)."""
    shots = np.asarray(shots)
    S, H, W, M = shots.shape
    m = np.ones((H, W), bool) if mask is None else np.asarray(mask, bool)
    out = np.zeros((H, W, 3), np.float32)
    idx = np.flatnonzero(m.ravel())
    flat = shots.reshape(S, H * W, M)
    pts = None if points is None else np.asarray(points, np.float64).reshape(H * W, 3)
    lo, hi = discard
    if not (0 <= lo < 1 and 0 <= hi < 1 and lo + hi < 1):
        raise ValueError(f"discard fractions must be in [0, 1) and sum below 1, got {discard}")
    for i in range(0, len(idx), chunk):
        sel = idx[i:i + chunk]
        I, A = rig_observations(flat[:, sel], rig, None if pts is None else pts[sel])
        w = np.ones((len(sel), S))  # per shot: a shadow or a highlight hides every channel of it at once
        n_lo, n_hi = int(np.floor(lo * S)), int(np.floor(hi * S))
        if n_lo or n_hi:
            brightness = (I / np.maximum(np.linalg.norm(A, axis=-1), 1e-12)).reshape(len(sel), S, M).mean(-1)
            order = np.argsort(brightness, axis=1, kind="stable")
            if n_lo:
                np.put_along_axis(w, order[:, :n_lo], 0.0, axis=1)
            if n_hi:
                np.put_along_axis(w, order[:, S - n_hi:], 0.0, axis=1)
        w = np.repeat(w, M, axis=1)
        AtA = np.einsum("pk,pki,pkj->pij", w, A, A)
        Atb = np.einsum("pk,pki,pk->pi", w, A, I)
        ok = np.linalg.matrix_rank(AtA, tol=1e-9) == 3
        b = np.zeros((len(sel), 3))
        b[ok] = np.linalg.solve(AtA[ok], Atb[ok][..., None])[..., 0]
        nb = np.linalg.norm(b, axis=-1, keepdims=True)
        n = np.where(nb > 1e-12, b / np.maximum(nb, 1e-12), np.array([0.0, 0.0, 1.0]))
        out.reshape(-1, 3)[sel] = n
    return out
