"""The shard schema: every HDF5 key of a shard is spelled here and nowhere else.

A shard (docs/shard-format.md) holds two groups: `patches/*` (one row per
patch) and `frames/*` (one row per rendered frame), plus file attributes.
Writers, readers, verification, preview, benchmarks and tests name arrays by
the constants below.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

FORMAT_VERSION = 1  # the three-light rig's shards (byte-identical to v0.6)
RIG_FORMAT_VERSION = 2  # any rig: patches x shots x P x P x channels (docs/shard-format.md "Version 2")
READABLE_VERSIONS = (FORMAT_VERSION, RIG_FORMAT_VERSION)
COMPRESSIONS = ("lzf", "gzip", "zstd", "blosc2-lz4", "none")  # zstd and blosc2-lz4: hdf5plugin filters
PATCH_CHUNK = 16  # patches per HDF5 chunk: small enough for cheap random access

PATCHES = "patches"
FRAMES = "frames"

# patches/*: one row per patch
PATCH_IMAGE = "patches/image"  # (N, P, P, 3) float16/32 linear radiance
PATCH_NORMAL = "patches/normal"  # (N, P, P, 3) camera frame
PATCH_MASK = "patches/mask"  # (N, P, P) uint8
PATCH_FRAME_INDEX = "patches/frame_index"  # (N,) int32
PATCH_YX = "patches/yx"  # (N, 2) int32 top-left corner in the frame

PATCH_POINTS = "patches/points"  # v2, near lights: (N, P, P, 3) float32 surface point (camera frame)
PATCH_SHADOW = "patches/shadow"  # v2, store_shadows: (N, L, P, P) uint8 per light: 0 lit, 1 attached, 2 cast
SHADOW_LIT, SHADOW_ATTACHED, SHADOW_CAST = 0, 1, 2  # codes of patches/shadow (0 also off the object)

# frames/*: one row per frame
FRAME_LIGHT_DIRS = "frames/light_dirs"  # (F, 3, 3) rows = toward light k
FRAME_CROSSTALK = "frames/crosstalk"  # (F, 3, 3)
FRAME_LIGHT_RGB = "frames/light_rgb"  # (F, 3, 3)
FRAME_SLANT_DEG = "frames/slant_deg"
FRAME_ENV_RATIO = "frames/env_ratio"
FRAME_ENV_ROTATION_DEG = "frames/env_rotation_deg"
FRAME_SPP = "frames/spp"
FRAME_SEED = "frames/frame_seed"
FRAME_IMAGE = "frames/image"  # optional whole frames (store_frames = true)
FRAME_NORMAL = "frames/normal"
FRAME_MASK = "frames/mask"
FRAME_ALBEDO = "frames/albedo"  # (F, H, W, 3) float16, whole frames only: diffuse albedo (0 = none)
FRAME_BLEND = "frames/blend"  # (F, H, W) float16, whole frames only: measured-blend weight
FRAME_PER_LIGHT = "frames/per_light"  # (F, K, H, W, 3) image_dtype, store_per_light: light k alone
FRAME_ENV_IMAGE = "frames/env_image"  # (F, H, W, 3) image_dtype, store_per_light: environment alone
# version 2 (any rig): light_dirs (F, N, 3), crosstalk (F, M, N) channel-by-light, light_rgb (F, N, 3), and
FRAME_LIGHT_POS = "frames/light_pos"  # (F, N, 3) point lights' positions, NaN rows: directional
FRAME_NOMINAL_DIRS = "frames/nominal_light_dirs"  # (F, N, 3) the calibration's directions (before errors)
FRAME_NOMINAL_CROSSTALK = "frames/nominal_crosstalk"  # (F, M, N) the calibration's channel-by-light matrix
FRAME_SHOTS = "frames/shots"  # (F, S, H, W, M) whole frames' camera images (store_frames)
FRAME_POINTS = "frames/points"  # (F, H, W, 3) whole frames' surface points (near lights, store_frames)
FRAME_SHADOW = "frames/shadow"  # (F, L, H, W) uint8 whole frames' per-light shadow codes (store_shadows + store_frames)
FRAME_RIG_JSON = "frames/rig_json"  # utf-8: the frame's RigSpec (channels, shots, nominal lights)
FRAME_SCENE_JSON = "frames/scene_json"  # utf-8 strings
FRAME_OBJECT = "frames/object"
FRAME_MATERIALS = "frames/materials"
FRAME_CONDITION = "frames/condition"

# file attributes
ATTR_FORMAT_VERSION = "format_version"
ATTR_N_PATCHES = "n_patches"
ATTR_N_FRAMES = "n_frames"
ATTR_PATCH_SIZE = "patch_size"
ATTR_COMPLETE = "complete"  # set last: a shard without it is partial
ATTR_N_SHOTS = "n_shots"  # v2: images per patch
ATTR_N_CHANNELS = "n_channels"  # v2: camera channels

PATCH_ARRAYS = {"image": PATCH_IMAGE, "normal": PATCH_NORMAL, "mask": PATCH_MASK}
STRING_ARRAYS = (FRAME_SCENE_JSON, FRAME_OBJECT, FRAME_MATERIALS, FRAME_CONDITION)


def split_key(key: str) -> tuple[str, str]:
    """'patches/image' -> ('patches', 'image')."""
    group, name = key.split("/")
    return group, name


def all_finite(a: np.ndarray) -> bool:
    """`np.isfinite(a).all()`; for float16 (the stored dtype) read off the exponent bits: numpy's float16
    ufuncs convert every value to float32 first, ~15x slower on a shard's patches."""
    a = np.asarray(a)
    if a.dtype != np.float16:
        return bool(np.isfinite(a).all())
    return a.size == 0 or int((np.ascontiguousarray(a).view(np.uint16) & 0x7C00).max()) < 0x7C00


def any_negative(a: np.ndarray) -> bool:
    """`(a < 0).any()`; for float16 by the bits: below zero is sign bit set, not -0, up to -inf (NaNs are
    neither, as for `<`)."""
    a = np.asarray(a)
    if a.dtype != np.float16:
        return bool((a < 0).any())
    u = np.ascontiguousarray(a).view(np.uint16)
    return bool(((u > 0x8000) & (u <= 0xFC00)).any())


@dataclass
class RowBlocks:
    """One array kept as the row blocks it was built from (a shard's patch images: one block per frame),
    written and checksummed block by block (`dataset/writer.py`, `digest.array_digest`).
    Why: concatenating a shard's patches held them twice at its write, ~60 MB at 96 images per patch;
    `np.asarray` still gives the whole array when a caller needs one."""

    blocks: list[np.ndarray]

    @property
    def shape(self) -> tuple[int, ...]:
        return (sum(len(b) for b in self.blocks),) + self.blocks[0].shape[1:]

    @property
    def dtype(self) -> np.dtype:
        return self.blocks[0].dtype

    @property
    def ndim(self) -> int:
        return self.blocks[0].ndim

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, rows: slice) -> np.ndarray:
        """Rows `start:stop` as one array (only that slice is copied)."""
        start, stop, step = rows.indices(len(self))
        if step != 1:
            raise IndexError("RowBlocks takes contiguous row slices only")
        out, at = [], 0
        for b in self.blocks:
            lo, hi = max(start - at, 0), min(stop - at, len(b))
            if lo < hi:
                out.append(b[lo:hi])
            at += len(b)
        return np.concatenate(out) if out else np.zeros((0,) + self.shape[1:], self.dtype)

    def astype(self, dtype, copy: bool = True) -> "RowBlocks":
        return RowBlocks([b.astype(dtype, copy=copy) for b in self.blocks])

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        a = np.concatenate(self.blocks)
        return a if dtype is None else a.astype(dtype, copy=False)


@dataclass
class Patches:
    """Fixed-size windows of frames (the rows of `patches/*`)."""

    image: np.ndarray | RowBlocks  # (N, P, P, 3) float32, or (N, S, P, P, M) for any rig
    normal: np.ndarray  # (N, P, P, 3) float32
    mask: np.ndarray  # (N, P, P) uint8
    yx: np.ndarray  # (N, 2) int32, top-left corner in the frame
    points: np.ndarray | None = None  # (N, P, P, 3) surface points (rigs with near lights)
    shadow: np.ndarray | None = None  # (N, L, P, P) uint8 per-light shadow codes (store_shadows)

    def __len__(self) -> int:
        return len(self.yx)

    @classmethod
    def empty(cls, size: int) -> "Patches":
        return cls(image=np.zeros((0, size, size, 3), np.float32), normal=np.zeros((0, size, size, 3), np.float32),
                   mask=np.zeros((0, size, size), np.uint8), yx=np.zeros((0, 2), np.int32))

    @classmethod
    def concat(cls, parts: list["Patches"], size: int) -> "Patches":
        if not parts:
            return cls.empty(size)
        points = np.concatenate([p.points for p in parts]) if all(p.points is not None for p in parts) else None
        shadow = np.concatenate([p.shadow for p in parts]) if all(p.shadow is not None for p in parts) else None
        image = RowBlocks([p.image for p in parts if len(p)] or [parts[0].image])  # not concatenated: see RowBlocks
        return cls(image=image, normal=np.concatenate([p.normal for p in parts]),
                   mask=np.concatenate([p.mask for p in parts]), yx=np.concatenate([p.yx for p in parts]),
                   points=points, shadow=shadow)


@dataclass
class FrameRecord:
    """What a shard keeps about one rendered frame (whole images optional)."""

    scene_json: str
    light_dirs: np.ndarray  # (3, 3) rows = toward light k, camera frame
    crosstalk: np.ndarray  # (3, 3)
    light_rgb: np.ndarray  # (3, 3) rows = RGB of light k
    slant_deg: float
    env_ratio: float
    env_rotation_deg: float
    spp: int
    frame_seed: int
    object: str
    materials: str
    condition: str = ""
    image: np.ndarray | None = None
    normal: np.ndarray | None = None
    mask: np.ndarray | None = None
    albedo: np.ndarray | None = None
    blend: np.ndarray | None = None
    per_light: np.ndarray | None = None  # (K, H, W, 3) clean radiance of light k alone (store_per_light)
    env_image: np.ndarray | None = None  # (H, W, 3) the environment light alone; None: no environment
    rig_json: str | None = None  # any rig (format 2): the RigSpec; None: the three-light rig (format 1)
    light_pos: np.ndarray | None = None  # (N, 3), NaN rows: directional
    nominal_dirs: np.ndarray | None = None  # (N, 3)
    nominal_crosstalk: np.ndarray | None = None  # (M, N)
    shots: np.ndarray | None = None  # (S, H, W, M) whole frame's camera images (store_frames)
    points: np.ndarray | None = None  # (H, W, 3) whole frame's surface points (near lights, store_frames)
    shadow: np.ndarray | None = None  # (L, H, W) uint8 whole frame's per-light shadow codes (store_shadows)


@dataclass
class ShardContent:
    patches: Patches
    frame_index: np.ndarray  # (N,) int32 frame of each patch
    frames: list[FrameRecord]
    attrs: dict = field(default_factory=dict)


@dataclass
class WholeFrame:
    """A whole stored frame with its calibration, for per-object evaluation and prediction."""

    image: np.ndarray
    normal: np.ndarray
    mask: np.ndarray
    light_dirs: np.ndarray
    crosstalk: np.ndarray
    object: str
    materials: str
    condition: str
    shard: str
    index: int
    albedo: np.ndarray | None = None  # (H, W, 3) ground-truth diffuse albedo (shards from v0.5 on)
    blend: np.ndarray | None = None  # (H, W) measured-blend weight
    per_light: np.ndarray | None = None  # (K, H, W, 3) light k alone (shards with store_per_light)
    env_image: np.ndarray | None = None  # (H, W, 3) environment alone (None: none, or not stored)
    env_ratio: float = 0.0


@dataclass
class RigFrame:
    """A whole stored frame of a rig shard (format 2): its camera images and both rigs.

    `rig` is what was rendered (truth), `nominal` what a calibration would say (equal unless the
    preset adds calibration errors); both are `msps_render.rig.Rig` values."""

    shots: np.ndarray  # (S, H, W, M) float32 linear radiance, one image per shot
    normal: np.ndarray  # (H, W, 3)
    mask: np.ndarray  # (H, W) bool
    rig: object  # msps_render.rig.Rig (truth)
    nominal: object  # msps_render.rig.Rig (calibration)
    object: str
    materials: str
    condition: str
    shard: str
    index: int
    points: np.ndarray | None = None  # (H, W, 3) surface points (near lights)
    light_rgb: np.ndarray | None = None  # (N, 3) each light's RGB (irradiance; point lights: intensity)
    rig_json: str = ""
    shadow: np.ndarray | None = None  # (L, H, W) uint8 per-light shadow codes (store_shadows)
