"""HDF5 shards: write atomically, read, verify.  Format: docs/shard-format.md.

A shard is written under a temporary name in the same directory and renamed
into place only after its `complete` attribute is set and the file is closed
and fsynced, so a crash (or a full disk) never leaves a partial shard under a
final name.  Writing is byte-deterministic: no timestamps (`track_times=False`),
fixed dataset order and fixed chunking, so the same content gives the same file.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from msps_render.patches import Patches

FORMAT_VERSION = 1
COMPRESSIONS = ("lzf", "gzip", "none")
PATCH_CHUNK = 16  # patches per HDF5 chunk: small enough for cheap random access


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


@dataclass
class ShardContent:
    patches: Patches
    frame_index: np.ndarray  # (N,) int32 frame of each patch
    frames: list[FrameRecord]
    attrs: dict = field(default_factory=dict)


def _dataset(g, name, data, compression: str, chunks=None):
    kw = {"track_times": False}
    if compression != "none" and data.ndim >= 1 and data.size > 0:
        kw.update(compression="gzip" if compression == "gzip" else "lzf", shuffle=True, fletcher32=True,
                  chunks=chunks or True)
        if compression == "gzip":
            kw["compression_opts"] = 4
    elif data.size > 0 and data.ndim >= 1:
        kw.update(fletcher32=True, chunks=chunks or True)
    return g.create_dataset(name, data=data, **kw)


def array_digest(arr: np.ndarray) -> str:
    """Checksum of an array's values (dtype + shape + bytes): what determinism is judged on."""
    h = hashlib.sha256()
    a = np.ascontiguousarray(arr)
    h.update(f"{a.dtype.str}{a.shape}".encode())
    h.update(a.tobytes())
    return h.hexdigest()


def file_digest(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def write_shard(path: str | Path, content: ShardContent, compression: str = "lzf",
                image_dtype: str = "float16", normal_dtype: str = "float16") -> dict:
    """Write `content` to `path` atomically; returns {'file_sha256', 'arrays': {name: sha256}, ...}."""
    import h5py

    if compression not in COMPRESSIONS:
        raise ValueError(f"compression must be one of {COMPRESSIONS}, got {compression!r}")
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    p = content.patches
    P = p.image.shape[1] if len(p) else 0
    img = p.image.astype(image_dtype)
    if image_dtype == "float16" and len(p) and not np.isfinite(img).all():
        raise ValueError("radiance exceeds float16 range; use image_dtype='float32'")
    arrays = {
        "patches/image": img,
        "patches/normal": p.normal.astype(normal_dtype),
        "patches/mask": p.mask.astype(np.uint8),
        "patches/frame_index": content.frame_index.astype(np.int32),
        "patches/yx": p.yx.astype(np.int32),
    }
    fr = content.frames
    arrays.update({
        "frames/light_dirs": np.array([f.light_dirs for f in fr], np.float32).reshape(-1, 3, 3),
        "frames/crosstalk": np.array([f.crosstalk for f in fr], np.float32).reshape(-1, 3, 3),
        "frames/light_rgb": np.array([f.light_rgb for f in fr], np.float32).reshape(-1, 3, 3),
        "frames/slant_deg": np.array([f.slant_deg for f in fr], np.float32),
        "frames/env_ratio": np.array([f.env_ratio for f in fr], np.float32),
        "frames/env_rotation_deg": np.array([f.env_rotation_deg for f in fr], np.float32),
        "frames/spp": np.array([f.spp for f in fr], np.int32),
        "frames/frame_seed": np.array([f.frame_seed for f in fr], np.int64),
    })
    if fr and fr[0].image is not None:
        arrays["frames/image"] = np.stack([f.image for f in fr]).astype(np.float32)
        arrays["frames/normal"] = np.stack([f.normal for f in fr]).astype(np.float32)
        arrays["frames/mask"] = np.stack([f.mask for f in fr]).astype(np.uint8)
    strings = {"frames/scene_json": [f.scene_json for f in fr], "frames/object": [f.object for f in fr],
               "frames/materials": [f.materials for f in fr], "frames/condition": [f.condition for f in fr]}
    try:
        with h5py.File(tmp, "w", track_order=True) as h:
            for k, v in sorted(content.attrs.items()):
                h.attrs[k] = v
            h.attrs["format_version"] = FORMAT_VERSION
            h.attrs["n_patches"] = len(p)
            h.attrs["n_frames"] = len(fr)
            h.attrs["complete"] = False
            for name, a in arrays.items():
                g, n = name.split("/")
                grp = h.require_group(g)
                chunks = None
                if g == "patches" and a.ndim >= 1 and len(a):
                    chunks = (min(PATCH_CHUNK, len(a)),) + a.shape[1:]
                elif g == "frames" and a.ndim >= 3 and len(a):
                    chunks = (1,) + a.shape[1:]
                _dataset(grp, n, a, compression, chunks)
            sdt = h5py.string_dtype("utf-8")
            for name, vals in strings.items():
                g, n = name.split("/")
                h.require_group(g).create_dataset(n, data=np.array(vals, dtype=object), dtype=sdt,
                                                  track_times=False)
            h.attrs["patch_size"] = P
            h.attrs["complete"] = True  # last: a shard without it is partial
            h.flush()
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return {"file_sha256": file_digest(path), "n_patches": int(len(p)), "n_frames": len(fr),
            "arrays": {k: array_digest(v) for k, v in arrays.items()}}


def read_digests(path: str | Path) -> dict[str, str]:
    """Array checksums of a shard as stored (numeric datasets)."""
    import h5py

    out = {}
    with h5py.File(path, "r") as h:
        for g in ("patches", "frames"):
            for n, ds in h[g].items():
                if ds.dtype.kind in "fiub":
                    out[f"{g}/{n}"] = array_digest(ds[()])
    return out


def verify_shard(path: str | Path, expected_sha256: str | None = None, normal_tol: float = 2e-3) -> list[str]:
    """Problems found in a shard (empty list = good)."""
    import h5py

    path = Path(path)
    if not path.is_file():
        return ["missing"]
    if expected_sha256 and file_digest(path) != expected_sha256:
        problems = ["checksum does not match the manifest"]
    else:
        problems = []
    try:
        with h5py.File(path, "r") as h:
            if not bool(h.attrs.get("complete", False)):
                problems.append("not complete (no complete flag)")
            if h.attrs.get("format_version") != FORMAT_VERSION:
                problems.append(f"format_version {h.attrs.get('format_version')} != {FORMAT_VERSION}")
            n = int(h.attrs.get("n_patches", -1))
            img = h["patches/image"][()]
            nrm = h["patches/normal"][()].astype(np.float32)
            msk = h["patches/mask"][()].astype(bool)
            if len(img) != n or len(nrm) != n or len(msk) != n:
                problems.append(f"patch count mismatch (attr {n}, arrays {len(img)}/{len(nrm)}/{len(msk)})")
            if not np.isfinite(img).all():
                problems.append(f"{int((~np.isfinite(img)).any(axis=(1, 2, 3)).sum())} patches with NaN/inf radiance")
            if (img < 0).any():
                problems.append("negative radiance")
            if not np.isfinite(nrm).all():
                problems.append("NaN/inf normals")
            else:
                ln = np.linalg.norm(nrm, axis=-1)
                if len(ln) and np.abs(ln[msk] - 1).max(initial=0) > normal_tol:
                    problems.append(f"normals not unit length inside the mask (max |1-|n||="
                                    f"{np.abs(ln[msk] - 1).max():.4f})")
                if len(ln) and np.abs(ln[~msk]).max(initial=0) > 0:
                    problems.append("non-zero normals outside the mask")
            if len(msk) and (msk.reshape(len(msk), -1).sum(1) == 0).any():
                problems.append("patch with an empty mask")
            nf = int(h.attrs.get("n_frames", -1))
            fi = h["patches/frame_index"][()]
            if len(fi) and (fi.min() < 0 or fi.max() >= nf):
                problems.append("frame_index out of range")
            for name in ("light_dirs", "crosstalk"):
                if len(h[f"frames/{name}"]) != nf:
                    problems.append(f"frames/{name} has the wrong length")
    except OSError as e:
        problems.append(f"unreadable HDF5 ({str(e).splitlines()[0][:120]})")
    except KeyError as e:
        problems.append(f"missing dataset {e}")
    return problems


def shard_summary(path: str | Path) -> dict:
    import h5py

    with h5py.File(path, "r") as h:
        info = {k: (v.item() if hasattr(v, "item") else v) for k, v in h.attrs.items()}
        info["datasets"] = {}
        h.visititems(lambda n, o: info["datasets"].__setitem__(n, (o.shape, str(o.dtype), o.compression))
                     if isinstance(o, h5py.Dataset) else None)
    return info


def json_attr(d: dict) -> str:
    return json.dumps(d, sort_keys=True)
