"""Will the dataset fit?  `msps render` compares the free space under `--out` with its estimate
of what the shards still to render take, before rendering any (docs/reliability.md).

Two steps, so that a render with room to spare pays nothing: a generous bound from the plan alone
(every patch window kept, arrays uncompressed, whole frames raw); only when that bound does not fit
does the estimate `msps config show --probe` makes run (one frame rendered into a temp dir, masks
of a few frames counted: `describe.describe`).
"""
from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

from msps_render.pipeline.config import DatasetConfig
from msps_render.pipeline.plan import Task

# Allowances for what the bound cannot count from the plan: HDF5 metadata of a shard, one frame's
# record (scene JSON and strings), and filters that grow incompressible data (fletcher32, lzf).
SHARD_OVERHEAD = 256 * 1024
FRAME_RECORD = 64 * 1024
FILTER_GROWTH = 1.1
WARN_SHARE = 0.8  # warn when the estimate takes more than this share of the free space
_ITEM = {"float16": 2, "float32": 4}


def bound_bytes(cfg: DatasetConfig, n_shards: int) -> int:
    """More than `n_shards` shards of `cfg` can take: every window a patch, nothing compressed."""
    from msps_render.dataset.sizes import raw_patch_bytes
    from msps_render.patches import window_origins

    d, cam = cfg.dataset, cfg.scene.camera
    st = d.storage
    frames = n_shards * d.frames_per_shard
    windows = len(window_origins(cam.height, cam.width, d.patches.size, d.patches.stride))
    pixel = 0
    rig = cfg.scene.rig
    lights, shots, channels, near = rig.image_shape() if rig is not None else (3, 1, 3, False)
    shadows = lights if st.store_shadows else 0  # one uint8 code per light and pixel
    if st.store_frames:  # image, normal (float32), mask, albedo (float16 x3), blend (float16)
        pixel += 12 + 12 + 1 + 6 + 2
        if rig is not None:  # the rig's shots, the surface points of near lights, shadow codes
            pixel += shots * channels * _ITEM[st.image_dtype] + (12 if near else 0) + shadows
    if st.store_per_light:  # three lights + the environment, 3 channels each
        pixel += 4 * 3 * _ITEM[st.image_dtype]
    per_frame = windows * raw_patch_bytes(d.patches.size, st.image_dtype, st.normal_dtype, shots, channels, near,
                                          shadows) \
        + cam.width * cam.height * pixel + FRAME_RECORD
    return int(FILTER_GROWTH * frames * per_frame + n_shards * SHARD_OVERHEAD)


@dataclass(frozen=True)
class SpaceCheck:
    free: int  # bytes free under --out
    needed: int | None  # the estimate for the shards still to render (None: the bound fits)
    basis: str  # what `needed` rests on

    @property
    def fits(self) -> bool:
        return self.needed is None or self.needed <= self.free

    @property
    def tight(self) -> bool:
        return self.needed is not None and self.needed > WARN_SHARE * self.free


def free_bytes(path: Path) -> int:
    """Free bytes for this user on the filesystem holding `path` (its nearest existing parent)."""
    p = Path(path)
    while not p.exists() and p != p.parent:
        p = p.parent
    return shutil.disk_usage(p).free


def check_space(cfg: DatasetConfig, tasks: list[Task], todo: int, out: Path, variant: str | None,
                threads: int | None, reclaim: int = 0) -> SpaceCheck:
    """Free space under `out` (+ `reclaim`: bytes of old shards this render deletes first) against the
    size of `todo` of the plan's `tasks` shards."""
    free = free_bytes(out) + reclaim
    if todo == 0 or bound_bytes(cfg, todo) <= free:
        return SpaceCheck(free, None, "bound")
    from msps_render.pipeline.describe import describe

    est = describe(cfg, probe=1, variant=variant, threads=threads, masks=8).estimate
    return SpaceCheck(free, int(est.disk_bytes * todo / len(tasks)),
                      f"`msps config show --probe 1` estimate for {todo} of {len(tasks)} shards")


def space_line(check: SpaceCheck) -> str:
    """'the shards to render need ~X and Y is free (what X rests on)': the warning's and the refusal's words."""
    from msps_render.pipeline.describe import _bytes

    return (f"the shards to render need ~{_bytes(check.needed or 0)} and {_bytes(check.free)} is free "
            f"({check.basis})")
