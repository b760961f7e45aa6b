"""`Frame`: the output of one render, with its exact ground truth.

All arrays are numpy, row 0 is the top of the image, column 0 the left.
`image` is linear HDR radiance (never gamma-encoded or clipped); `normal` is in
the camera frame (x right, y up, z toward the camera), unit length where
`mask` is True and zero elsewhere.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from msps_render.io.images import write_exr, write_png
from msps_render.preview import normal_to_rgb8, srgb8, tonemap
from msps_render.rig import Rig, rig_of_spec
from msps_render.scene.spec import SceneSpec


@dataclass
class Frame:
    image: np.ndarray  # (H, W, 3) float32 linear radiance
    normal: np.ndarray  # (H, W, 3) float32, camera frame
    mask: np.ndarray  # (H, W) bool, pixel centre hits the object
    depth: np.ndarray  # (H, W) float32, z-depth from the camera plane (0 = background)
    part: np.ndarray  # (H, W) int8, material part index (-1 = background)
    spec: SceneSpec
    variant: str = ""
    per_light: np.ndarray | None = None  # (K, H, W, 3) float32, one image per light
    env_image: np.ndarray | None = None  # (H, W, 3) environment-only contribution
    clean_image: np.ndarray | None = None  # radiance before a sensor model (noise/quantisation), if one ran
    albedo: np.ndarray | None = None  # (H, W, 3) diffuse albedo at pixel centres (0: none, e.g. measured)
    blend: np.ndarray | None = None  # (H, W) weight of the second material of a measured blend
    meta: dict = field(default_factory=dict)
    shots: np.ndarray | None = None  # (S, H, W, M) the rig's camera images (rig scenes: `spec.rig`)
    points: np.ndarray | None = None  # (H, W, 3) surface point per pixel, camera frame (rigs with near lights)
    shadow: np.ndarray | None = None  # (L, H, W) uint8 per light: 0 lit, 1 attached, 2 cast (`render.shadows`)

    def __post_init__(self) -> None:
        H, W = self.mask.shape
        for name, shape in (("image", (H, W, 3)), ("normal", (H, W, 3)), ("depth", (H, W)),
                            ("part", (H, W))):
            arr = getattr(self, name)
            if arr.shape != shape:
                raise ValueError(f"Frame.{name} has shape {arr.shape}, expected {shape}")

    @property
    def light_dirs(self) -> np.ndarray:
        """(K, 3) unit vectors toward each light, camera frame."""
        return np.array([l.direction for l in self.spec.lights], dtype=np.float64)

    @property
    def rig(self) -> Rig:
        """The true rig this frame was rendered with (`msps_render.rig`)."""
        return rig_of_spec(self.spec)

    @property
    def crosstalk(self) -> np.ndarray:
        """(3, K) M, M[i, k] = share of light k's signal in channel i (columns sum to 1).

        Sampled scenes carry it (`SceneSpec.crosstalk`); for a hand-made spec without one it is
        the lights' RGB with each column scaled to sum 1 -- the same convention as the sampler
        (RGB = irradiance * M[:, k]) and the spectral mode, so consumers never see two scales.
        """
        if self.spec.rig is not None:  # (M, K): channel m's reading of light k at the object centre
            return self.rig.crosstalk
        if self.spec.crosstalk is not None:
            return np.array(self.spec.crosstalk, dtype=np.float64)
        rgb = np.array([l.rgb for l in self.spec.lights], dtype=np.float64).reshape(-1, 3).T
        s = rgb.sum(axis=0, keepdims=True)
        return np.divide(rgb, s, out=np.zeros_like(rgb), where=s > 0)

    # ------------------------------------------------------------------ output
    def save(self, out_dir: str | Path) -> list[Path]:
        """Write EXR (image, normal, depth, mask) + PNG previews (image, normal, mask, part map; per light
        with the image's exposure) + scene.json."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        written = [
            write_exr(out / "image.exr", self.image),
            write_exr(out / "normal.exr", self.normal),
            write_exr(out / "depth.exr", self.depth[..., None].repeat(3, -1)),
            write_png(out / "image.png", tonemap(self.image, self.mask)),
            write_png(out / "normal.png", normal_to_rgb8(self.normal, self.mask)),
            write_png(out / "mask.png", (self.mask * 255).astype(np.uint8)),
        ]
        written.append(write_png(out / "part.png", _part_rgb8(self.part)))
        if self.albedo is not None:  # ground-truth appearance: linear albedo, PNG shows it sRGB-encoded
            written.append(write_exr(out / "albedo.exr", self.albedo))
            written.append(write_png(out / "albedo.png", srgb8(self.albedo)))
            written.append(write_exr(out / "blend.exr", self.blend[..., None].repeat(3, -1)))
        if self.per_light is not None:
            white = _white(self.image, self.mask)  # one exposure for all lights: brightnesses compare
            for k, img in enumerate(self.per_light):
                written.append(write_exr(out / f"light{k}.exr", img))
                written.append(write_png(out / f"light{k}.png", tonemap(img / white, None, 100.0)))
        p = out / "scene.json"
        p.write_text(self.spec.to_json())
        written.append(p)
        return written


def _white(image: np.ndarray, mask: np.ndarray) -> float:
    """The image's 99th-percentile object radiance (the exposure of `tonemap`), for shared exposures."""
    ref = image[mask] if mask.any() else image.reshape(-1, image.shape[-1])
    return max(float(np.percentile(ref, 99.0)), 1e-8) if ref.size else 1.0


def _part_rgb8(part: np.ndarray) -> np.ndarray:
    """Material part map: part k in colour k of a fixed palette, background black."""
    palette = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
                        [140, 86, 75], [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207]],
                       np.uint8)
    rgb = palette[np.mod(part.astype(np.int64), len(palette))]
    rgb[part < 0] = 0
    return rgb
