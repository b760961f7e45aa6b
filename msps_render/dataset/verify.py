"""Checks of shards and datasets: complete flag, format version, checksums, finite values,
unit normals inside the mask, usable crosstalk, not all black.

`dataset_status` is the one definition of a dataset's state that `msps inspect`, `msps verify`
and training's dataset check share: *complete* = the manifest's (`manifest_problems`) and every
recorded shard intact; a *damaged* shard is recorded but missing, of another size (truncated),
unreadable or (deep check) fails its checksum or contents.  Each problem names its shard.
"""
from __future__ import annotations

import shlex
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msps_render.calibration import crosstalk_problem
from msps_render.dataset import schema as K
from msps_render.dataset.digest import file_digest
from msps_render.dataset.manifest import MANIFEST, SHARD_DIR, at_fault, manifest_problems, read_manifest
from msps_render.dataset.reader import open_shard
from msps_render.dataset.schema import all_finite, any_negative
from msps_render.errors import not_a_dataset


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
            if h.attrs.get(K.ATTR_FORMAT_VERSION) not in K.READABLE_VERSIONS:
                problems.append(f"format_version {h.attrs.get(K.ATTR_FORMAT_VERSION)} is not one this msps reads "
                                f"({', '.join(map(str, K.READABLE_VERSIONS))})")
            n = int(h.attrs.get(K.ATTR_N_PATCHES, -1))
            img = h[K.PATCH_IMAGE][()]
            nrm = h[K.PATCH_NORMAL][()].astype(np.float32)
            msk = h[K.PATCH_MASK][()].astype(bool)
            if len(img) != n or len(nrm) != n or len(msk) != n:
                problems.append(f"patch count mismatch (attr {n}, arrays {len(img)}/{len(nrm)}/{len(msk)})")
            if not all_finite(img):
                problems.append(f"{int((~np.isfinite(img)).any(axis=tuple(range(1, img.ndim))).sum())} patches "
                                "with NaN/inf radiance")
            if any_negative(img):
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


@dataclass(frozen=True)
class DatasetStatus:
    """What a dataset directory holds and what is wrong with it, shard by shard."""

    root: Path
    planned: int
    recorded: int
    n_patches: int
    problems: dict[str, list[str]]  # {shard name | 'dataset.json': problems}; empty = good
    damaged: tuple[str, ...]  # recorded shards whose file is missing or bad

    @property
    def complete(self) -> bool:
        """Every planned shard rendered, recorded and intact (an empty dataset is complete but not ok)."""
        return not any(n != MANIFEST or not p[0].startswith("holds 0 patches") for n, p in self.problems.items())

    @property
    def ok(self) -> bool:
        return not self.problems

    def lines(self, limit: int | None = None) -> list[str]:
        """'BAD|INCOMPLETE PATH: problem; problem' per file at fault (BAD: damaged shards, an empty
        dataset; INCOMPLETE: not rendered yet), the first `limit`, then a count of the rest."""
        names = sorted(self.problems)
        out = [f"{'BAD' if n in self.damaged or self.complete else 'INCOMPLETE'} {at_fault(self.root, n)}: "
               f"{'; '.join(self.problems[n])}" for n in names[:limit]]
        if limit is not None and len(names) > limit:
            out.append(f"... and {len(names) - limit} more (`msps verify {shlex.quote(str(self.root))}` lists them)")
        return out


def _quick_problems(path: Path, entry: dict) -> list[str]:
    """Cheap checks of a recorded shard (no hashing): present, the recorded size, an HDF5 that opens."""
    if not path.is_file():
        return ["missing (recorded in dataset.json, not on disk)"]
    size, want = path.stat().st_size, entry.get("bytes")
    if want is not None:
        if size != want:
            return [f"damaged: {size} bytes on disk, dataset.json records {want} (truncated or replaced)"]
        return []
    try:
        with open_shard(path) as h:
            if not bool(h.attrs.get(K.ATTR_COMPLETE, False)):
                return ["damaged: not complete (no complete flag)"]
    except (OSError, KeyError) as e:
        return [f"damaged: unreadable HDF5 ({str(e).splitlines()[0][:120]})"]
    return []


def dataset_status(root: str | Path, deep: bool = True) -> DatasetStatus:
    """The state of the dataset in `root`.  `deep`: also checksum and check the values of every shard
    (`msps verify`, training); otherwise only presence, size and readability (`msps inspect`)."""
    root = Path(root)
    m = read_manifest(root)
    if m is None:
        raise not_a_dataset(root)
    shards = m.get("shards") or {}
    problems: dict[str, list[str]] = {}
    for name, entry in sorted(shards.items()):
        path = root / SHARD_DIR / name
        if deep:
            probs = verify_shard(path, entry.get("file_sha256"))
            if not probs:
                try:
                    probs = _content_problems(path, entry)
                except (OSError, KeyError) as e:
                    probs = [f"unreadable HDF5 ({str(e).splitlines()[0][:120]})"]
            if probs and probs != ["missing"] and not probs[0].startswith("damaged"):
                probs = ["damaged: " + probs[0]] + probs[1:]
            elif probs == ["missing"]:
                probs = ["missing (recorded in dataset.json, not on disk)"]
        else:
            probs = _quick_problems(path, entry)
        if probs:
            problems[name] = probs
    damaged = tuple(sorted(problems))
    for name, probs in manifest_problems(m).items():
        problems.setdefault(name, []).extend(probs)
    n_patches = sum(int(e.get("n_patches", 0)) for e in shards.values())
    if not problems and n_patches == 0:
        problems[MANIFEST] = ["holds 0 patches (no frame had a window with enough object coverage: "
                              "dataset.patches.min_coverage); re-render with smaller patches or larger frames"]
    return DatasetStatus(root, len(m.get("planned_shards", list(shards))), len(shards), n_patches, problems,
                         damaged)


def verify_dataset(root: str | Path) -> dict[str, list[str]]:
    """{shard name | 'dataset.json': problems} for everything at fault (empty dict = dataset is good);
    `manifest.at_fault(root, name)` is the file each is about."""
    return dataset_status(root, deep=True).problems


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
