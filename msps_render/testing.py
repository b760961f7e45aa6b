"""Helpers for tests and benchmarks (not part of the pipeline): analytic references."""
from __future__ import annotations

import numpy as np

# A crosstalk matrix (rows: camera channels, columns: lights; columns sum to 1, diagonally dominant)
# far from symmetric: M - M.T has entries of 0.06-0.10, so code that swaps rows and columns -- light
# k's RGB read from row k, or A = M.T @ L in the solve -- changes the result by several percent of
# a light (the paper's 0.92/0.04 matrix is symmetric and hides such a transpose).
ASYMMETRIC_CROSSTALK = np.array([[0.86, 0.02, 0.10],
                                 [0.12, 0.90, 0.02],
                                 [0.02, 0.08, 0.88]])


def frame_bootstrap(num, den=None, n: int = 2000, seed: int = 0) -> tuple[float, float]:
    """95 % interval of sum(num) / sum(den) over frames drawn with replacement (den: 1 per frame).

    Per-frame sums of pixel errors as `num` and of the baseline's as `den` give the pixel-pooled
    ratio; per-frame MAEs and no `den` give the mean over frames. How far another draw of frames
    of the same kind could move a claimed number: the tests' noise margins.
    """
    num = np.asarray(num, np.float64)
    den = np.ones_like(num) if den is None else np.asarray(den, np.float64)
    idx = np.random.default_rng(seed).integers(0, len(num), size=(n, len(num)))
    lo, hi = np.percentile(num[idx].sum(1) / den[idx].sum(1), [2.5, 97.5])
    return float(lo), float(hi)


def analytic_sphere_normals(width: int, height: int, extent: float, radius: float):
    """Analytic normals/mask of an orthographic sphere at the pixel centres (for tests).

    Mitsuba's orthographic camera maps the film width to x in +-extent and keeps pixels square,
    so y spans +-extent * height / width (checked by test_non_square_frame_normals_match_...).
    """
    xs = ((np.arange(width) + 0.5) / width * 2 - 1) * extent
    ys = (1 - (np.arange(height) + 0.5) / height * 2) * extent * height / width
    X, Y = np.meshgrid(xs, ys)
    r2 = (X ** 2 + Y ** 2) / radius ** 2
    mask = r2 < 1
    Z = np.sqrt(np.clip(1 - r2, 0, None))
    n = np.stack([X / radius, Y / radius, Z], -1)
    n[~mask] = 0
    return n, mask


def write_sphere_capture(d, lights, size: int, rng, intensity_range=(0.5, 2.0), mask=None,
                         with_filenames: bool = True, mask_channels: int = 1) -> dict:
    """A synthetic, exact DiLiGenT-style capture in folder `d` (created): an orthographic Lambertian
    sphere of grey albedo varying across x, one 16-bit linear PNG per light (slant, tilt) of random
    RGB intensity (not divided out, as DiLiGenT), light_directions.txt, light_intensities.txt,
    filenames.txt (optional) and mask.png.  Returns normal, mask, L, E and the image names."""
    from pathlib import Path

    from msps_render.calibration import direction_from_slant_tilt
    from msps_render.io.png16 import to_unorm, write_png

    d = Path(d)
    d.mkdir(parents=True)
    n, sphere = analytic_sphere_normals(size, size, 1.05, 1.0)
    mask = sphere if mask is None else mask(n, sphere)
    albedo = (0.3 + 0.6 * np.linspace(0, 1, size)[None, :]) * np.ones((size, 1))
    L = np.array([direction_from_slant_tilt(s, t) for s, t in lights])
    E = rng.uniform(*intensity_range, size=(len(L), 3))
    imgs = [albedo[..., None] * np.clip(n @ l, 0, None)[..., None] * e[None, None, :] for l, e in zip(L, E)]
    top = max(float(i.max()) for i in imgs)
    names = [f"{k + 1:03d}.png" for k in range(len(L))]
    for name, img in zip(names, imgs):
        write_png(d / name, to_unorm(img / top))  # 16-bit linear, one exposure for all
    (d / "light_directions.txt").write_text("".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in L))
    (d / "light_intensities.txt").write_text("".join(f"{r:.6f} {g:.6f} {b:.6f}\n" for r, g, b in E))
    if with_filenames:
        (d / "filenames.txt").write_text("".join(nm + "\n" for nm in names))
    m8 = (mask * 255).astype(np.uint8)
    write_png(d / "mask.png", np.repeat(m8[..., None], 3, axis=-1) if mask_channels == 3 else m8)
    return {"normal": n, "mask": mask, "L": L, "E": E, "names": names}


def corrupt_patch_chunk(shard, chunk: int) -> None:
    """Overwrite 16 bytes in the middle of compressed chunk `chunk` of a shard's patch images:
    the file still opens, and reading that chunk fails (what a bad disk block looks like)."""
    import h5py

    from msps_render.dataset import schema as K

    with h5py.File(shard, "r") as h:
        info = h[K.PATCH_IMAGE].id.get_chunk_info(chunk)
    with open(shard, "r+b") as f:
        f.seek(info.byte_offset + info.size // 2)
        f.write(bytes(16))

