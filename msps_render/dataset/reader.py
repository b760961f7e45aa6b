"""Read shards: patch arrays, per-frame calibration, whole frames, digests, a summary.

h5py is imported inside the functions so that `import msps_render.dataset` stays light.
A corrupted or truncated shard raises `InputError` naming the file (see `shard_errors`).
"""
from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Iterator

import numpy as np

from msps_render.dataset import schema as K
from msps_render.dataset.digest import array_digest
from msps_render.dataset.schema import Patches, RigFrame, WholeFrame
from msps_render.errors import InputError, brief


@contextlib.contextmanager
def shard_errors(path: str | Path):
    """A corrupted or truncated shard (h5py's bare OSError/KeyError) -> InputError naming the file."""
    try:
        yield
    except (OSError, KeyError) as e:
        text = str(e).lower()
        if "not registered" in text or "can't open directory" in text:  # zstd / Blosc2 without hdf5plugin loaded
            raise InputError(path, f"cannot decode the shard's compressed arrays ({brief(str(e))}): shards are "
                                   "zstd-compressed by default; `pip install hdf5plugin` (msps's readers import it; "
                                   "a plain h5py script needs `import hdf5plugin` first)") from None
        raise InputError(path, f"unreadable shard ({brief(str(e))}); run `msps verify` on the dataset "
                               "and re-render bad shards with `msps render ... --resume`") from None


def open_shard(path: str | Path, mode: str = "r", chunk_cache: bool = True):
    """An open h5py.File of a shard (the caller closes it).

    `chunk_cache=False` for whole-array reads: HDF5 then decompresses each chunk straight
    into the caller's array instead of through its chunk cache (~10% less CPU per shard).
    """
    import h5py

    try:  # registers the zstd / Blosc2 filters a shard may use; lzf/gzip shards read without it
        import hdf5plugin  # noqa: F401  (an offline GPU node may lack it: scripts/build_wheelhouse.py)
    except ImportError:
        pass

    return h5py.File(path, mode) if chunk_cache else h5py.File(path, mode, rdcc_nbytes=0)


def format_version(h) -> int:
    """The shard's format version, or InputError naming the file when this msps cannot read it."""
    v = h.attrs.get(K.ATTR_FORMAT_VERSION)
    if v is None or int(v) not in K.READABLE_VERSIONS:
        raise InputError(h.filename, f"unknown shard format version {v} (this msps reads "
                                     f"{', '.join(map(str, K.READABLE_VERSIONS))}); a newer msps wrote it?")
    return int(v)


def rig_shape(h) -> tuple[int, int]:
    """(images per patch, channels) of an open shard: (1, 3) for the three-light rig (format 1)."""
    if format_version(h) == K.FORMAT_VERSION:
        return 1, 3
    shape = h[K.PATCH_IMAGE].shape
    return int(shape[1]), int(shape[-1])


def _three_light_image(h):
    """The image array of a shard as the three-light readers see it, (N, P, P, 3): a format-2 shard of one
    shot of three channels reads unchanged; any other rig is refused in one line."""
    d = h[K.PATCH_IMAGE]
    if d.ndim == 4:
        format_version(h)
        return d, d.shape
    s, m = rig_shape(h)
    if (s, m) != (1, 3):
        raise InputError(h.filename, f"a rig shard of {s} image(s) x {m} channel(s) per patch; the dual-cue "
                                     "network reads one 3-channel image per patch (train a classic-PS network "
                                     "on this rig, or render a three-light rig)")
    return d, (d.shape[0],) + d.shape[2:]


def read_patches(h) -> dict[str, np.ndarray]:
    """{'image', 'normal', 'mask'}: every patch of an open shard, decoded (three-light readers)."""
    img, shape = _three_light_image(h)
    out = {name: h[key][()] for name, key in K.PATCH_ARRAYS.items() if name != "image"}
    return {"image": img[()].reshape(shape), **out}


def read_patch_layout(h) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """{'image', 'normal', 'mask'}: (shape, dtype) of an open shard's patch arrays, nothing decoded."""
    img, shape = _three_light_image(h)
    out = {name: (h[key].shape, h[key].dtype) for name, key in K.PATCH_ARRAYS.items()}
    out["image"] = (shape, img.dtype)
    return out


def read_patches_into(h, out: dict[str, np.ndarray]) -> None:
    """Decode every patch of an open shard into the leading rows of preallocated C-contiguous
    arrays of the stored dtypes: reused buffers skip the page faults of fresh ones."""
    for name, key in K.PATCH_ARRAYS.items():
        d = h[key]
        if len(d):
            if d.ndim == out[name].ndim:
                d.read_direct(out[name], dest_sel=np.s_[:len(d)])
            else:  # a one-shot format-2 shard: (N, 1, P, P, 3) into (N, P, P, 3) rows
                d.read_direct(out[name][:len(d)].reshape(d.shape))


def read_calibration(h) -> dict[str, np.ndarray]:
    """{'frame_index', 'yx' (per patch: its frame, its top-left corner there), 'light_dirs', 'crosstalk'
    (per frame)} of an open shard."""
    return {"frame_index": h[K.PATCH_FRAME_INDEX][()], "yx": h[K.PATCH_YX][()].astype(np.int64),
            "light_dirs": h[K.FRAME_LIGHT_DIRS][()],
            "crosstalk": h[K.FRAME_CROSSTALK][()]}


def scene_is_lambertian(scene: dict) -> bool:
    """Is a frame's image linear in each material's albedo, channel by channel?  RGB mode, every
    material Lambertian (kind "diffuse", textured or not) and no camera response: then multiplying
    channel c by a field is exactly the image of the same object re-coloured (direct light and the
    environment; `models/augment.py`).  A measured or glossy material's highlight would be tinted too,
    which no dielectric does."""
    return (scene.get("mode", "rgb") == "rgb" and scene.get("camera_response") is None
            and all(m.get("kind") == "diffuse" and not m.get("blend") for m in scene.get("materials", ())))


def read_frame_lambertian(h) -> np.ndarray:
    """(F,) bool per frame of an open shard: `scene_is_lambertian` of its stored scene."""
    import json

    return np.array([scene_is_lambertian(json.loads(s)) for s in h[K.FRAME_SCENE_JSON].asstr()[()]], bool)


def read_shard_patches(path: str | Path) -> dict[str, np.ndarray]:
    with shard_errors(path), open_shard(path, chunk_cache=False) as h:
        return read_patches(h)


def read_shard_calibration(path: str | Path) -> dict[str, np.ndarray]:
    with shard_errors(path), open_shard(path) as h:
        return read_calibration(h)


def read_patch_rows(path: str | Path) -> tuple[Patches, np.ndarray]:
    """(Patches as float32, frame_index): the `patches/*` rows of a shard, as written."""
    with shard_errors(path), open_shard(path) as h:
        pat = Patches(h[K.PATCH_IMAGE][()].astype(np.float32), h[K.PATCH_NORMAL][()].astype(np.float32),
                      h[K.PATCH_MASK][()], h[K.PATCH_YX][()])
        return pat, h[K.PATCH_FRAME_INDEX][()]


def read_frame_table(path: str | Path) -> dict[str, list]:
    """Per-frame descriptors: slant_deg, materials (';'-joined), object, condition."""
    with shard_errors(path), open_shard(path) as h:
        return {"slant_deg": h[K.FRAME_SLANT_DEG][()].tolist(),
                "materials": h[K.FRAME_MATERIALS].asstr()[()].tolist(),
                "object": h[K.FRAME_OBJECT].asstr()[()].tolist(),
                "condition": h[K.FRAME_CONDITION].asstr()[()].tolist()}


def read_frame_scenes(path: str | Path) -> tuple[np.ndarray, list[str]]:
    """(light_rgb (F, 3, 3), SceneSpec JSON per frame) of a shard."""
    with shard_errors(path), open_shard(path) as h:
        return h[K.FRAME_LIGHT_RGB][()], h[K.FRAME_SCENE_JSON].asstr()[()].tolist()


def has_whole_frames(h) -> bool:
    return K.FRAME_IMAGE in h


def read_whole_frame(h, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image, normal, mask bool) of stored whole frame i of an open shard."""
    return h[K.FRAME_IMAGE][i], h[K.FRAME_NORMAL][i], h[K.FRAME_MASK][i].astype(bool)


def n_whole_frames(h) -> int:
    return len(h[K.FRAME_IMAGE]) if has_whole_frames(h) else 0


def has_per_light(h) -> bool:
    """True for shards written with store_per_light (older shards have no per-light images)."""
    return K.FRAME_PER_LIGHT in h


def iter_whole_frames(path: str | Path, per_light: bool = False) -> Iterator[WholeFrame]:
    """The whole frames of a shard written with `store_frames = true`; `per_light=True` also reads
    the stored per-light and environment images (None where the shard has none; the environment
    image is 0 in frames without one)."""
    path = Path(path)
    with shard_errors(path), open_shard(path) as h:
        if not has_whole_frames(h):
            raise InputError(path, "shard has no whole frames (render the preset with store_frames = true)")
        objs = h[K.FRAME_OBJECT].asstr()[()]
        mats = h[K.FRAME_MATERIALS].asstr()[()]
        conds = h[K.FRAME_CONDITION].asstr()[()]
        env_ratio = h[K.FRAME_ENV_RATIO][()]
        appearance = K.FRAME_ALBEDO in h  # shards before v0.5 have none
        lights = per_light and has_per_light(h)
        env = lights and K.FRAME_ENV_IMAGE in h
        for i in range(n_whole_frames(h)):
            image, normal, mask = read_whole_frame(h, i)
            yield WholeFrame(image, normal, mask, h[K.FRAME_LIGHT_DIRS][i], h[K.FRAME_CROSSTALK][i],
                             str(objs[i]), str(mats[i]), str(conds[i]), path.name, i,
                             h[K.FRAME_ALBEDO][i].astype(np.float32) if appearance else None,
                             h[K.FRAME_BLEND][i].astype(np.float32) if appearance else None,
                             h[K.FRAME_PER_LIGHT][i].astype(np.float32) if lights else None,
                             h[K.FRAME_ENV_IMAGE][i].astype(np.float32) if env else None,
                             float(env_ratio[i]))


def is_rig_shard(h) -> bool:
    """Format 2 (any rig)."""
    return format_version(h) == K.RIG_FORMAT_VERSION


def read_rigs(h) -> tuple[list, list]:
    """(true rigs, nominal rigs) per frame of an open format-2 shard (`msps_render.rig.Rig`)."""
    import json

    from msps_render.rig import Rig

    dirs, C, pos = h[K.FRAME_LIGHT_DIRS][()], h[K.FRAME_CROSSTALK][()], h[K.FRAME_LIGHT_POS][()]
    ndirs, nC = h[K.FRAME_NOMINAL_DIRS][()], h[K.FRAME_NOMINAL_CROSSTALK][()]
    true, nominal = [], []
    for i, rj in enumerate(h[K.FRAME_RIG_JSON].asstr()[()]):
        r = json.loads(rj)
        shots = tuple(tuple(s) for s in r["shots"])
        mu = np.asarray(r["anisotropy"], np.float64) if r.get("anisotropy") else None
        p = pos[i].astype(np.float64)
        p = p if np.isfinite(p).any() else None
        true.append(Rig(dirs[i].astype(np.float64), C[i].astype(np.float64), shots=shots, positions=p, anisotropy=mu))
        np_ = None if p is None else np.where(np.isfinite(p), ndirs[i] * np.linalg.norm(np.nan_to_num(p), axis=1)[:, None], np.nan)
        nominal.append(Rig(ndirs[i].astype(np.float64), nC[i].astype(np.float64), shots=shots, positions=np_,
                           anisotropy=mu))
    return true, nominal


def iter_rig_frames(path: str | Path) -> Iterator[RigFrame]:
    """The whole frames of a format-2 shard written with `store_frames = true`."""
    path = Path(path)
    with shard_errors(path), open_shard(path) as h:
        if not is_rig_shard(h):
            raise InputError(path, "a three-light shard (format 1): read it with iter_whole_frames")
        if K.FRAME_SHOTS not in h:
            raise InputError(path, "shard has no whole frames (render the preset with store_frames = true)")
        true, nominal = read_rigs(h)
        objs = h[K.FRAME_OBJECT].asstr()[()]
        mats = h[K.FRAME_MATERIALS].asstr()[()]
        conds = h[K.FRAME_CONDITION].asstr()[()]
        rjs = h[K.FRAME_RIG_JSON].asstr()[()]
        rgb = h[K.FRAME_LIGHT_RGB][()]
        pts, shd = K.FRAME_POINTS in h, K.FRAME_SHADOW in h
        for i in range(len(h[K.FRAME_SHOTS])):
            yield RigFrame(h[K.FRAME_SHOTS][i].astype(np.float32), h[K.FRAME_NORMAL][i],
                           h[K.FRAME_MASK][i].astype(bool), true[i], nominal[i], str(objs[i]), str(mats[i]),
                           str(conds[i]), path.name, i, h[K.FRAME_POINTS][i] if pts else None,
                           rgb[i].astype(np.float64), str(rjs[i]), h[K.FRAME_SHADOW][i] if shd else None)


def read_rig_patches(h) -> dict[str, np.ndarray]:
    """{'image' (N, S, P, P, M), 'normal', 'mask', 'frame_index', 'points' (near lights, else absent),
    'shadow' (N, L, P, P) per-light codes (store_shadows, else absent)} of an open format-2 shard, decoded."""
    if not is_rig_shard(h):
        raise InputError(h.filename, "a three-light shard (format 1): read it with read_patches")
    out = {name: h[key][()] for name, key in K.PATCH_ARRAYS.items()}
    out["frame_index"] = h[K.PATCH_FRAME_INDEX][()]
    if K.PATCH_POINTS in h:
        out["points"] = h[K.PATCH_POINTS][()]
    if K.PATCH_SHADOW in h:
        out["shadow"] = h[K.PATCH_SHADOW][()]
    return out


def read_digests(path: str | Path) -> dict[str, str]:
    """Array checksums of a shard as stored (numeric datasets)."""
    out = {}
    with open_shard(path) as h:
        for g in (K.PATCHES, K.FRAMES):
            for n, ds in h[g].items():
                if ds.dtype.kind in "fiub":
                    out[f"{g}/{n}"] = array_digest(ds[()])
    return out


def shard_summary(path: str | Path) -> dict:
    """File attributes and {dataset: (shape, dtype, compression)} of a shard."""
    import h5py

    with open_shard(path) as h:
        info = {k: (v.item() if hasattr(v, "item") else v) for k, v in h.attrs.items()}
        info["datasets"] = {}
        h.visititems(lambda n, o: info["datasets"].__setitem__(n, (o.shape, str(o.dtype), o.compression))
                     if isinstance(o, h5py.Dataset) else None)
    return info
