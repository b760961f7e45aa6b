"""Mirror ensemble: predict the object and its mirror image, and average.

Why: the paper's rig (tilts 0/120/240 deg, one crosstalk for all channels) is symmetric about the
image x-axis.  Mirroring a scene about that axis (rows reversed, n_y -> -n_y) maps light k onto
light P(k) (0 <-> 0, 120 <-> 240), so the mirrored image with its channels permuted by P is
exactly what the rig would record of the mirrored object with its albedo channels permuted:

    c = diag(rho) M L n,   L S = Pi L,   M Pi = Pi M   =>   Pi^T c = diag(Pi^T rho) M L (S n)

(S the mirror, Pi the permutation).  The network was not trained to be equivariant under this,
so the two predictions err differently and their mean is better (measured: docs/history.md
"Stage 9").  Only exact symmetries are used (no resampling): a rig without one is refused.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from msps_render.errors import InputError

SUFFIX = "+mirror"
DESCRIPTION = "averaged with its prediction of the mirrored image (models/symmetry.py)"
ANGLE_TOL_DEG = 1.0  # a mirrored light this near another light is that light
CROSSTALK_TOL = 1e-3


@dataclass(frozen=True)
class Mirror:
    """One exact symmetry of the rig: an image axis to reverse and the channel permutation."""

    axis: int  # 0: rows reversed (camera y -> -y); 1: columns reversed (x -> -x)
    perm: tuple[int, int, int]  # mirrored light k is light perm[k]

    def image(self, image: np.ndarray) -> np.ndarray:
        """The mirrored image as the rig would record it: channel perm[k] reads what channel k did."""
        out = np.empty_like(image)
        out[..., list(self.perm)] = np.flip(image, self.axis)
        return out

    def mask(self, mask: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(np.flip(mask, self.axis))

    def normals_back(self, normals: np.ndarray) -> np.ndarray:
        """Normals predicted for the mirrored image, in the original image's frame."""
        n = np.array(np.flip(normals, self.axis))
        n[..., 1 - self.axis] *= -1.0  # rows are y, columns are x
        return n


def find_mirror(light_dirs: np.ndarray, crosstalk: np.ndarray) -> Mirror | None:
    """The rig's mirror symmetry about the image x- or y-axis, or None."""
    L = np.asarray(light_dirs, np.float64)
    L = L / np.linalg.norm(L, axis=1, keepdims=True)
    M = np.asarray(crosstalk, np.float64)
    for axis in (0, 1):
        S = np.ones(3)
        S[1 - axis] = -1.0
        cos = (L * S) @ L.T  # cos[k, j]: mirrored light k against light j
        perm = tuple(int(j) for j in cos.argmax(1))
        if sorted(perm) != [0, 1, 2]:
            continue
        if np.degrees(np.arccos(np.clip(cos[range(3), perm], -1, 1))).max() > ANGLE_TOL_DEG:
            continue
        Pi = np.eye(3)[list(perm)]  # (Pi L)_k = l_perm[k] = S l_k
        if np.abs(M @ Pi - Pi @ M).max() <= CROSSTALK_TOL * max(np.abs(M).max(), 1e-12):
            return Mirror(axis, perm)
    return None


def require_mirror(light_dirs: np.ndarray, crosstalk: np.ndarray, what: str = "--mirror") -> Mirror:
    m = find_mirror(light_dirs, crosstalk)
    if m is None:
        raise InputError(what, "the rig has no mirror symmetry about an image axis (the lights' tilts must be "
                               "symmetric and the crosstalk the same under that swap); predict without it")
    return m


def mirror_ensemble(predict: Callable[[np.ndarray, np.ndarray], np.ndarray], image: np.ndarray,
                    mask: np.ndarray, mirror: Mirror) -> np.ndarray:
    """Unit mean of `predict(image, mask)` and its prediction of the mirrored image (mapped back);
    0 outside the mask."""
    a = predict(image, mask)
    return unit_mean(a, mirror.normals_back(predict(mirror.image(image), mirror.mask(mask))), mask)


def mirror_ensemble_batch(predict: Callable[[np.ndarray, np.ndarray], np.ndarray], images: np.ndarray,
                          masks: np.ndarray, mirrors: list[Mirror]) -> np.ndarray:
    """`mirror_ensemble` for a batch (B, H, W, 3) / (B, H, W), each item by its own rig's mirror, in two
    calls of `predict` (the batch, then its mirror images)."""
    a = predict(images, masks)
    x = np.stack([mr.image(im) for mr, im in zip(mirrors, images)])
    xm = np.stack([mr.mask(m) for mr, m in zip(mirrors, masks)])
    back = np.stack([mr.normals_back(n) for mr, n in zip(mirrors, predict(x, xm))])
    return unit_mean(a, back, masks)


def unit_mean(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(a + b) / |a + b| for normals (..., 3); 0 outside `mask` (...)."""
    s = np.asarray(a, np.float64) + np.asarray(b, np.float64)
    n = s / np.maximum(np.linalg.norm(s, axis=-1, keepdims=True), 1e-12)
    n[~np.asarray(mask, bool)] = 0.0
    return n.astype(np.float32)


PAPER_MIRROR = Mirror(axis=0, perm=(0, 2, 1))  # the augmentation's mirror: exact for any rig, mirrored with it


def mirror_batch(batch: dict, which) -> dict:
    """A training batch with the patches `which` (B,) bool replaced by their mirror images.

    Exact for any rig: rows reversed (n_y -> -n_y) and channels 1, 2 swapped is what the mirrored
    rig (lights mirrored and relabelled, crosstalk relabelled) records of the mirrored object with
    its albedo's channels 1, 2 swapped -- so `light_dirs` and `crosstalk` are mirrored too."""
    import torch

    w = torch.as_tensor(np.asarray(which, bool))
    if not w.any():
        return batch
    p = list(PAPER_MIRROR.perm)  # an involution: channel p[k] reads what channel k did
    out = dict(batch)

    def sel(new, old):
        shape = (-1,) + (1,) * (old.dim() - 1)
        return torch.where(w.view(shape), new, old)

    out["image"] = sel(torch.flip(batch["image"], (2,))[:, p], batch["image"])
    out["mask"] = sel(torch.flip(batch["mask"], (2,)), batch["mask"])
    n = torch.flip(batch["normal"], (2,)).clone()
    n[:, 1] = -n[:, 1]
    out["normal"] = sel(n, batch["normal"])
    if "light_dirs" in batch:
        L = batch["light_dirs"].clone()
        L[..., 1] = -L[..., 1]
        out["light_dirs"] = sel(L[:, p], batch["light_dirs"])
    if "crosstalk" in batch:
        out["crosstalk"] = sel(batch["crosstalk"][:, p][:, :, p], batch["crosstalk"])
    return out
