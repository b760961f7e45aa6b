"""Issue 21, loader: selectable HDF5 filters per corpus (lzf, gzip, zstd, blosc2-lz4, none)."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from cli_helpers import cli, one_line_error
from msps_render.dataset import open_shard, read_patches, schema as K
from msps_render.dataset.schema import FrameMeta, Patches, ShardContent
from msps_render.dataset.writer import write_shard

FILTERS = ("lzf", "gzip", "zstd", "blosc2-lz4", "none")
# the HDF5 filter ids each value must put on the patch arrays (h5py's names / registered plugin ids)
FILTER_IDS = {"lzf": 32000, "gzip": 1, "zstd": 32015, "blosc2-lz4": 32026}


def _content(n: int = 40, p: int = 8) -> ShardContent:
    rng = np.random.default_rng(0)
    # smooth-ish radiance (compressible like a render) plus noise in the low bits
    base = np.linspace(0.0, 2.0, p * p * 3, dtype=np.float32).reshape(p, p, 3)
    image = (base[None] * rng.uniform(0.5, 1.5, (n, 1, 1, 1)) + rng.normal(0, 0.01, (n, p, p, 3))).astype(np.float32)
    normal = rng.normal(size=(n, p, p, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    mask = (rng.uniform(size=(n, p, p)) > 0.2).astype(np.uint8)
    patches = Patches(image=image, normal=normal, mask=mask, yx=np.zeros((n, 2), np.int32))
    frames = [FrameMeta(light_dirs=np.eye(3, dtype=np.float32), crosstalk=np.eye(3, dtype=np.float32),
                        light_rgb=np.eye(3, dtype=np.float32), slant_deg=30.0, env_ratio=0.0,
                        env_rotation_deg=0.0, spp=4, frame_seed=1, scene_json="{}", object="blob",
                        materials="m", condition="c")]
    return ShardContent(patches=patches, frames=frames, frame_index=np.zeros(n, np.int32), attrs={})
