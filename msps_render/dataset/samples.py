"""Labelled samples of a shard for contact sheets (`msps preview`): whole frames if stored, else patches."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msps_render.dataset import schema as K
from msps_render.dataset.reader import open_shard, shard_errors


@dataclass
class Sample:
    image: np.ndarray  # (H, W, 3) float32 linear
    normal: np.ndarray  # (H, W, 3) float32
    mask: np.ndarray  # (H, W) bool
    shard: str  # file name
    frame: int  # frame index in the shard
    yx: tuple[int, int] | None  # patch origin in the frame; None for a whole frame
    shape_kind: str  # blobby, mesh, primitive, procedural, sphere
    object: str  # shape name (blob003, torus, creased, the mesh's file stem, ...)
    materials: list[str]
    condition: str  # '' without a sweep


def _shape_kind(scene_json: str) -> str:
    try:
        return str(json.loads(scene_json)["shape"]["kind"])
    except (ValueError, KeyError, TypeError):
        return "?"


def patch_cover(h) -> tuple[np.ndarray, list[float]]:
    """(every patch's mask, its object coverage) of an open shard."""
    msk = h[K.PATCH_MASK][()]
    return msk, (msk.reshape(len(msk), -1).mean(1).tolist() if len(msk) else [])


def frame_labels(h) -> tuple:
    """(object, materials, condition, scene JSON) per frame of an open shard: what a sample is labelled with."""
    return tuple(h[k].asstr()[()] for k in (K.FRAME_OBJECT, K.FRAME_MATERIALS, K.FRAME_CONDITION, K.FRAME_SCENE_JSON))


def labelled(labels: tuple, image, normal, mask, shard: str, f: int, yx) -> Sample:
    """A `Sample` of frame `f` with its `frame_labels`."""
    objs, mats, conds, scenes = labels
    return Sample(np.asarray(image, np.float32), np.asarray(normal, np.float32), np.asarray(mask, bool), shard,
                  int(f), yx, _shape_kind(scenes[f]), str(objs[f]), [m for m in str(mats[f]).split(";") if m],
                  str(conds[f]))


def pick_samples(path: str | Path, n: int, rng: np.random.Generator, make, whole_key: str = K.FRAME_IMAGE):
    """Up to `n` samples of a shard (its first whole frames if stored under `whole_key`, else `n` random
    patches in shard order) and the mask coverage of every patch of the shard.  `make(h, labels)` returns
    the builder `sample(image, normal, mask, frame, yx)` (three-light samples, rig samples)."""
    path = Path(path)
    with shard_errors(path), open_shard(path) as h:
        msk, cover = patch_cover(h)
        N = len(msk)
        if n <= 0:
            return [], cover
        sample = make(h, frame_labels(h))
        out = []
        if whole_key in h:
            for i in range(min(len(h[whole_key]), n)):
                out.append(sample(h[whole_key][i], h[K.FRAME_NORMAL][i], h[K.FRAME_MASK][i].astype(bool), i, None))
        elif N:
            fidx = h[K.PATCH_FRAME_INDEX][()]
            yx = h[K.PATCH_YX][()]
            for i in sorted(rng.choice(N, size=min(N, n), replace=False)):
                out.append(sample(h[K.PATCH_IMAGE][i], h[K.PATCH_NORMAL][i], msk[i], fidx[i],
                                  (int(yx[i][0]), int(yx[i][1]))))
        return out, cover


def shard_samples(path: str | Path, n: int, rng: np.random.Generator) -> tuple[list[Sample], list[float]]:
    """Up to `n` samples of a shard and the mask coverage of its patches (`pick_samples`)."""
    name = Path(path).name
    return pick_samples(path, n, rng, lambda h, labels: (
        lambda image, normal, mask, f, yx: labelled(labels, image, normal, mask, name, f, yx)))
