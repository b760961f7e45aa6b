"""`msps compose`: real photographs in: one pseudo-multispectral image from per-light captures.

A capture folder in the DiLiGenT style holds one photo per white light,
`light_directions.txt` (row k: x y z toward light k, camera frame: x right,
y up, z toward the camera), `light_intensities.txt` (row k: R G B of light k;
optional, default 1), optionally `filenames.txt` (image names in light order;
default: the folder's images sorted by name) and `mask.png`.

Compose picks the three lights closest to the slant/tilt layout the network
expects (assignment minimising the total angle), divides each photo by its
light's intensity (the object under a unit white light, the DiLiGenT
convention) and mixes them with the crosstalk matrix as a coloured-light
camera would see them at once:

    composed[c] = sum_k M[c, k] * photo_k[c] / intensity_k[c]

which is exactly how the renderer forms an RGB image from three lights of RGB
`M[:, k]`.  It writes `image.exr` (linear), `mask.png`, `calibration.json` (the
chosen lights' real directions and M, in the schema `msps predict
--calibration` reads) and `preview.png`.  `compose_arrays` is the same
composition in memory (no file written), shared with `msps bench-real`.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from msps_render.errors import InputError, read_text

IMAGE_SUFFIXES = (".png", ".exr", ".hdr", ".npy", ".tif", ".tiff", ".jpg", ".jpeg")
NOT_PHOTOS = ("mask", "normal_gt", "normal", "preview")
WARN_DEVIATION_DEG = 10.0


@dataclass
class Capture:
    root: Path
    images: list[Path]
    light_dirs: np.ndarray  # (N, 3) unit rows
    intensities: np.ndarray  # (N, 3)
    mask_path: Path | None
    radiometric: bool = False  # light_intensities.txt given: untagged PNG photos are linear (`PNG_RULE`)


def _read_rows(path: Path, what: str) -> np.ndarray:
    try:
        a = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as e:
        raise InputError(path, f"cannot read {what} ({str(e).splitlines()[0][:100]})") from None
    if a.size == 0:
        raise InputError(path, f"no {what} in the file")
    if not np.isfinite(a).all():
        raise InputError(path, f"{what} contain NaN/inf")
    return a


def read_capture(root: str | Path) -> Capture:
    """Validate a capture folder (one line naming the file on any problem); reads no image yet."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(root, "capture folder not found")
    ld = root / "light_directions.txt"
    if not ld.is_file():
        raise InputError(ld, "missing (row k: x y z toward light k, camera frame)")
    L = _read_rows(ld, "light directions")
    if L.shape[1] != 3:
        raise InputError(ld, f"need 3 numbers per row (x y z), got {L.shape[1]}")
    n = np.linalg.norm(L, axis=1)
    if (n < 1e-9).any():
        raise InputError(ld, f"row {int(np.argmin(n)) + 1} is the zero vector")
    L = L / n[:, None]
    li = root / "light_intensities.txt"
    if li.is_file():
        E = _read_rows(li, "light intensities")
        if E.shape[1] == 1:
            E = np.repeat(E, 3, axis=1)
        if E.shape != L.shape:
            raise InputError(li, f"{len(E)} rows of {E.shape[1]} values; need {len(L)} rows of R G B "
                                 "(one per light direction)")
        if (E <= 0).any():
            raise InputError(li, f"row {int(np.argwhere(E <= 0)[0][0]) + 1} has an intensity <= 0")
    else:
        E = np.ones_like(L)
    fn = root / "filenames.txt"
    if fn.is_file():
        names = [s.strip() for s in read_text(fn, "filenames.txt").splitlines() if s.strip()]
        images = [root / s for s in names]
        src = fn
    else:
        images = sorted(p for p in root.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()
                        and not p.stem.lower().startswith(NOT_PHOTOS))
        src = root
    if len(images) != len(L):
        raise InputError(src, f"{len(images)} images but {len(L)} light directions in {ld.name}")
    mask = root / "mask.png"
    return Capture(root, images, L, E, mask if mask.is_file() else None, radiometric=li.is_file())


def choose_lights(light_dirs: np.ndarray, slant_deg: float, tilts_deg) -> tuple[np.ndarray, np.ndarray]:
    """(indices of the capture lights closest to the targets, their angles to the targets in degrees)."""
    from scipy.optimize import linear_sum_assignment

    from msps_render.calibration import direction_from_slant_tilt

    T = np.array([direction_from_slant_tilt(slant_deg, t) for t in tilts_deg])
    ang = np.degrees(np.arccos(np.clip(np.asarray(light_dirs) @ T.T, -1.0, 1.0)))  # (N, 3)
    rows, cols = linear_sum_assignment(ang)
    idx = np.empty(len(T), dtype=int)
    idx[cols] = rows
    return idx, ang[idx, np.arange(len(T))]


def read_photo(path: Path, linear: bool | None = None, warn=None, radiometric: bool = False) -> np.ndarray:
    """A capture image as linear float RGB (H, W, 3); alpha is dropped.  PNG follows the one rule of
    `msps predict`, `msps compose` and `msps bench-real` (`io.png16.PNG_RULE`: its tag, else linear in a
    `radiometric` capture, else 16-bit linear, 8-bit sRGB, `warn(message)` hearing the guess; `linear`
    True/False forces it).  JPG/TIFF are decoded as sRGB, EXR/HDR/NPY are linear."""
    from msps_render.io.png16 import read_png_linear
    from msps_render.io.images import read_image

    if not path.is_file():
        raise InputError(path, "image file not found")
    if path.suffix.lower() == ".png":
        img = read_png_linear(path, linear, warn, radiometric)
    else:
        img = read_image(path).astype(np.float64)  # EXR/HDR/NPY linear; JPG/TIFF decoded as sRGB
    if img.ndim == 2:
        img = img[..., None]
    if img.shape[-1] in (2, 4):  # grey+alpha, RGBA: drop alpha
        img = img[..., :-1]
    if img.shape[-1] == 1:
        img = np.repeat(img, 3, axis=-1)
    if img.shape[-1] != 3:
        raise InputError(path, f"expected an RGB or grey image, got {img.shape[-1]} channels")
    return img


def parse_crosstalk(text: str | None) -> np.ndarray:
    """--crosstalk: 'paper' (default, 0.92/0.04), 'identity', or a JSON 3x3 (rows: channels, columns: lights)."""
    import json

    from msps_render.calibration import PAPER_CROSSTALK, crosstalk_problem

    if text is None or text.strip().lower() == "paper":
        return PAPER_CROSSTALK.copy()
    if text.strip().lower() in ("identity", "none"):
        return np.eye(3)
    try:
        M = np.asarray(json.loads(text), dtype=np.float64)
    except (json.JSONDecodeError, TypeError, ValueError) as e:
        raise InputError("--crosstalk", f"not 'paper', 'identity' or a JSON 3x3 matrix ({e})") from None
    if M.shape != (3, 3):
        raise InputError("--crosstalk", f"must be 3x3, got shape {list(M.shape)}")
    why = crosstalk_problem(M)
    if why:
        raise InputError("--crosstalk", f"crosstalk {why}")
    return M


class Composed(NamedTuple):
    """One pseudo-multispectral image composed in memory (`compose_arrays`)."""

    image: np.ndarray  # (H, W, 3) linear, 0 outside the mask
    mask: np.ndarray  # (H, W) bool
    light_dirs: np.ndarray  # (3, 3) the chosen lights' measured directions (rows)
    deviation_deg: np.ndarray  # (3,) angle of each chosen light to its target
    indices: np.ndarray  # (3,) indices into capture.images / light_dirs


def _check_layout(slant_deg: float, tilts_deg) -> list[float]:
    from msps_render.calibration import direction_from_slant_tilt

    tilts = [float(t) for t in tilts_deg]
    if len(tilts) != 3:
        raise InputError("--tilts", f"need 3 tilts, got {len(tilts)}")
    direction_from_slant_tilt(slant_deg, 0.0)  # validates the slant
    return tilts


def select_lights(cap: Capture, slant_deg: float = 30.0,
                  tilts_deg=(0.0, 120.0, 240.0)) -> tuple[np.ndarray, np.ndarray]:
    """(indices into the capture, deviations in degrees) of the three front lights (z > 0) nearest the layout."""
    tilts = _check_layout(slant_deg, tilts_deg)
    front = cap.light_dirs[:, 2] > 0
    if front.sum() < 3:
        raise InputError(cap.root / "light_directions.txt", "fewer than 3 lights in front of the object (z > 0)")
    cand = np.nonzero(front)[0]
    sel, dev = choose_lights(cap.light_dirs[cand], slant_deg, tilts)
    return cand[sel], dev


def read_mask(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """A mask PNG as bool (channel 0 > 0), checked against the images' (H, W)."""
    from msps_render.io.png16 import read_png

    m = read_png(path)
    m = (m[..., 0] if m.ndim == 3 else m) > 0
    if m.shape != tuple(shape):
        raise InputError(path, f"mask is {m.shape[1]}x{m.shape[0]}, images are {shape[1]}x{shape[0]}")
    return m


def compose_arrays(cap: Capture, slant_deg: float = 30.0, tilts_deg=(0.0, 120.0, 240.0),
                   crosstalk: np.ndarray | None = None, linear: bool | None = None, warn=None) -> Composed:
    """The composition itself, in memory (no file written): the three lights nearest the layout,
    each photo divided by its light's intensity, mixed by `composed[c] = sum_k M[c,k] photo_k[c]`;
    0 outside the mask (mask.png, else the non-zero pixels).  `linear`, `warn`: see `read_photo`."""
    from msps_render.calibration import PAPER_CROSSTALK

    M = PAPER_CROSSTALK.copy() if crosstalk is None else np.asarray(crosstalk, np.float64)
    idx, dev = select_lights(cap, slant_deg, tilts_deg)
    photos = [read_photo(cap.images[i], linear, warn, cap.radiometric) for i in idx]
    H, W = photos[0].shape[:2]
    for i, p in zip(idx, photos):
        if p.shape[:2] != (H, W):
            raise InputError(cap.images[i], f"image is {p.shape[1]}x{p.shape[0]}, "
                                            f"{cap.images[idx[0]].name} is {W}x{H}")
    unit = [p / cap.intensities[i][None, None, :] for i, p in zip(idx, photos)]  # unit white light
    comp = np.zeros((H, W, 3))
    for k in range(3):
        comp += unit[k] * M[:, k][None, None, :]
    m = read_mask(cap.mask_path, (H, W)) if cap.mask_path is not None else comp.max(-1) > 0
    comp[~m] = 0.0
    return Composed(comp, m, cap.light_dirs[idx], np.asarray(dev, np.float64), idx)


def compose_capture(capture_dir: str | Path, out: str | Path, slant_deg: float = 30.0,
                    tilts_deg=(0.0, 120.0, 240.0), crosstalk: np.ndarray | None = None,
                    linear: bool | None = None) -> dict:
    """Write OUT/{image.exr, mask.png, calibration.json, preview.png}; returns a summary with warnings
    (among them how PNG photos were decoded, where `read_photo` had to guess)."""
    from msps_render.calibration import PAPER_CROSSTALK, write_calibration
    from msps_render.io.images import write_exr
    from msps_render.io.png16 import write_png
    from msps_render.io.staging import check_new_out, staged_dir
    from msps_render.preview import tonemap

    out = Path(out)
    tilts = _check_layout(slant_deg, tilts_deg)
    M = PAPER_CROSSTALK.copy() if crosstalk is None else np.asarray(crosstalk, np.float64)
    cap = read_capture(capture_dir)
    select_lights(cap, slant_deg, tilts)  # a capture without 3 front lights fails before --out is checked
    check_new_out(out)
    guesses: list[str] = []
    comp, m, L, dev, idx = compose_arrays(cap, slant_deg, tilts, M, linear, guesses.append)
    if guesses:  # one line for the three photos
        guesses = [guesses[0] if len(guesses) == 1 else
                   f"{guesses[0]} (and {len(guesses) - 1} more photo(s) of {cap.root} alike)"]
    warnings = guesses + [f"light {cap.images[i].name} is {d:.1f} deg from the target (slant {slant_deg:g}, tilt {t:g})"
                for i, d, t in zip(idx, dev, tilts) if d > WARN_DEVIATION_DEG]
    info = {"capture": str(cap.root.resolve()), "images": [cap.images[i].name for i in idx],
            "light_indices": [int(i) + 1 for i in idx], "target_slant_deg": float(slant_deg),
            "target_tilts_deg": tilts, "deviation_deg": [float(d) for d in dev],
            "intensities": cap.intensities[idx].tolist()}
    with staged_dir(out) as stage:
        write_exr(stage / "image.exr", comp.astype(np.float32))
        write_png(stage / "mask.png", (m * 255).astype(np.uint8))
        write_calibration(stage / "calibration.json", L, M, source="msps compose", info=info)
        write_png(stage / "preview.png", tonemap(comp, m), srgb=True)
    return {**info, "out": str(out), "warnings": warnings}
