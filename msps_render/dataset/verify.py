"""Checks of shards and datasets: complete flag, format version, checksums, finite values,
unit normals inside the mask, usable crosstalk, not all black."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from msps_render.calibration import crosstalk_problem
from msps_render.dataset import schema as K
from msps_render.dataset.digest import file_digest
from msps_render.dataset.manifest import SHARD_DIR, read_manifest
from msps_render.dataset.reader import open_shard
from msps_render.errors import InputError


def verify_shard(path: str | Path, expected_sha256: str | None = None, normal_tol: float = 2e-3) -> list[str]:
    """Problems found in a shard (empty list = good)."""
    path = Path(path)
    if not path.is_file():
        return ["missing"]
    if expected_sha256 and file_digest(path) != expected_sha256:
        problems = ["checksum does not match the manifest"]
    else:
        problems = []
    try:
        with open_shard(path) as h:
            if not bool(h.attrs.get(K.ATTR_COMPLETE, False)):
                problems.append("not complete (no complete flag)")
            if h.attrs.get(K.ATTR_FORMAT_VERSION) != K.FORMAT_VERSION:
                problems.append(f"format_version {h.attrs.get(K.ATTR_FORMAT_VERSION)} != {K.FORMAT_VERSION}")
            n = int(h.attrs.get(K.ATTR_N_PATCHES, -1))
            img = h[K.PATCH_IMAGE][()]
            nrm = h[K.PATCH_NORMAL][()].astype(np.float32)
            msk = h[K.PATCH_MASK][()].astype(bool)
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
            nf = int(h.attrs.get(K.ATTR_N_FRAMES, -1))
            fi = h[K.PATCH_FRAME_INDEX][()]
            if len(fi) and (fi.min() < 0 or fi.max() >= nf):
                problems.append("frame_index out of range")
            for key in (K.FRAME_LIGHT_DIRS, K.FRAME_CROSSTALK):
                if len(h[key]) != nf:
                    problems.append(f"{key} has the wrong length")
    except OSError as e:
        problems.append(f"unreadable HDF5 ({str(e).splitlines()[0][:120]})")
    except KeyError as e:
        problems.append(f"missing dataset {e}")
    return problems


def verify_dataset(root: str | Path) -> dict[str, list[str]]:
    """{shard name: problems} for every bad shard (empty dict = dataset is good)."""
    root = Path(root)
    m = read_manifest(root)
    if m is None:
        raise InputError(root, "no dataset.json here (not a dataset directory)")
    bad: dict[str, list[str]] = {}
    planned = m.get("planned_shards", list(m["shards"]))
    for name in planned:
        entry = m["shards"].get(name)
        if entry is None:
            bad[name] = ["not rendered (run `msps render ... --resume`)"]
            continue
        probs = verify_shard(root / SHARD_DIR / name, entry.get("file_sha256"))
        if not probs:
            probs += _content_problems(root / SHARD_DIR / name, entry)
        if probs:
            bad[name] = probs
    return bad


def _content_problems(path: Path, entry: dict) -> list[str]:
    """Checks that need the values: patch count, usable crosstalk, not all black."""
    probs = []
    with open_shard(path) as h:
        if entry.get("n_patches") is not None and int(h.attrs[K.ATTR_N_PATCHES]) != entry["n_patches"]:
            probs.append("patch count differs from the manifest")
        for j, M in enumerate(h[K.FRAME_CROSSTALK][()]):
            why = crosstalk_problem(M)
            if why:
                probs.append(f"frame {j}: crosstalk {why}")
                break
        img = h[K.PATCH_IMAGE]
        if len(img) and not np.any(img[()]):
            probs.append("every patch image is black (all zero)")
    return probs
