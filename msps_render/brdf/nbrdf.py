"""Built-in measured materials: Neural-BRDF fits of 80 MERL materials, baked into MERL tables.

The weights (`brdf/nbrdf/<name>.h5`, MIT, Sztrajman et al. 2021) are three
small dense layers per material.  Rather than evaluate the network inside the
BSDF (a second plugin, a second code path to keep right), each material is
baked once into a MERL-format table at the bin centres and then rendered by
the same reader/plugin as a real MERL file.  Baking costs ~1 s per material
(`benchmarks/bench_merl.py`), the table is cached on disk like the generated
tables (atomic write, keyed by the weights' hash), and a lookup in the baked
table differs from the network only by MERL's own binning.

Cache format v2 is a float32 `.npy` (17.5 MB; the network computes in float32,
so nothing is lost); v1 caches (float64 MERL `.binary`, 35 MB) are converted on
first use -- the same float32 values, bit for bit -- and left in place for older
msps versions sharing the cache (`rm $cache/nbrdf-*-v1.binary` frees them).
"""
from __future__ import annotations

import functools
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msps_render.brdf import merl
from msps_render.brdf.analytic import cache_dir, cache_writes
from msps_render.errors import InputError
from msps_render.resources import data_dir

BAKE_VERSION = 2  # bump when the baking rule or file format changes (2: float32 .npy)
_LAYERS = (("dense_1", (6, 21)), ("dense_2", (21, 21)), ("dense_3", (21, 3)))


@dataclass(frozen=True)
class NbrdfWeights:
    """The network of one material: (kernel, bias) per layer, float32."""

    path: str
    layers: tuple[tuple[np.ndarray, np.ndarray], ...]
    digest: str  # sha1 of the weights: names the baked table


def read_weights(path: str | os.PathLike) -> NbrdfWeights:
    """Read and validate a Keras HDF5 weights file (raises InputError naming the file)."""
    import h5py

    p = Path(path)
    if not p.is_file():
        raise InputError(p, "Neural-BRDF weights file not found")
    layers = []
    h = hashlib.sha1()
    try:
        with h5py.File(p, "r") as f:
            for name, kshape in _LAYERS:
                try:
                    k = np.asarray(f[f"{name}/{name}/kernel:0"], dtype=np.float32)
                    b = np.asarray(f[f"{name}/{name}/bias:0"], dtype=np.float32)
                except KeyError:
                    raise InputError(p, f"not a Neural-BRDF weights file: no dataset {name}/{name}/kernel:0 "
                                        f"or bias:0") from None
                if k.shape != kshape or b.shape != (kshape[1],):
                    raise InputError(p, f"layer {name} has kernel {k.shape} and bias {b.shape}; "
                                        f"expected {kshape} and ({kshape[1]},)")
                if not (np.all(np.isfinite(k)) and np.all(np.isfinite(b))):
                    raise InputError(p, f"layer {name} has non-finite weights")
                layers.append((k, b))
                h.update(k.tobytes())
                h.update(b.tobytes())
    except OSError as e:
        raise InputError(p, f"cannot read as HDF5 ({str(e).split(chr(10))[0]})") from None
    return NbrdfWeights(str(p), tuple(layers), h.hexdigest()[:16])


def evaluate(w: NbrdfWeights, theta_h, theta_d, phi_d) -> np.ndarray:
    """BRDF (..., 3) in linear RGB, 1/sr, at Rusinkiewicz angles (radians), as the README defines it."""
    th, td, pd = np.broadcast_arrays(*(np.asarray(a, dtype=np.float32) for a in (theta_h, theta_d, phi_d)))
    x = np.stack([np.sin(th), np.zeros_like(th), np.cos(th),
                  np.sin(td) * np.cos(pd), np.sin(td) * np.sin(pd), np.cos(td)], axis=-1)
    (k1, b1), (k2, b2), (k3, b3) = w.layers
    a = np.maximum(x @ k1 + b1, 0.0)
    a = np.maximum(a @ k2 + b2, 0.0)
    y = a @ k3 + b3
    return np.maximum(np.expm1(y), 0.0)


def make_table(w: NbrdfWeights) -> np.ndarray:
    """The network at every MERL bin centre: (3, 90, 90, 180), 1/sr.

    Bins whose incoming direction lies below the horizon (MERL stores -1 there)
    get the network's smooth continuation, as the generated tables do.

    Evaluated one theta_h row at a time: the whole grid at once held ~430 MiB of layer
    activations, in whichever render worker baked a table first; per row the results
    are bit-identical (tests/test_scale_memory.py) and the peak ~10 MiB.
    """
    th, td, pd = merl.bin_centres()
    vals = np.empty((*merl.DIMS, 3), np.float32)
    for i in range(merl.RES_THETA_H):
        vals[i] = evaluate(w, th[i], td[i], pd[i])  # (90, 180, 3)
    return np.ascontiguousarray(np.moveaxis(vals, -1, 0), dtype=np.float64)


def builtin_dir() -> Path:
    """The shipped weights: `brdf/nbrdf/` of the checkout or of the installed package data."""
    return data_dir("brdf") / "nbrdf"


def weights_path(name: str) -> Path | None:
    """`<builtin_dir>/<name>.h5` if it exists."""
    p = builtin_dir() / f"{name}.h5"
    return p if p.is_file() else None


def builtin_names() -> list[str]:
    """Names of the shipped weights (`<name>.h5` files of `builtin_dir`), sorted."""
    try:
        with os.scandir(builtin_dir()) as it:  # one listing (every frame's material pool asks)
            return sorted(e.name[:-3] for e in it if e.name.endswith(".h5") and e.is_file())
    except OSError:
        return []


@functools.lru_cache(maxsize=256)
def _digest(path: str, mtime_ns: int, size: int) -> str:
    """The weights' digest, read once per file version (every frame asks for its tables' paths)."""
    return read_weights(path).digest


def baked_table(weights: str | os.PathLike, directory: str | os.PathLike | None = None) -> Path:
    """Path of the float32 table baked from `weights` (`merl.read_table` reads it), baking it once
    (atomic write) if absent, or converting a v1 float64 cache of the same weights."""
    p = Path(weights)
    if not p.is_file():
        read_weights(p)  # raises the InputError naming the file
    st = p.stat()
    digest = _digest(str(p), st.st_mtime_ns, st.st_size)
    d = Path(directory) if directory is not None else cache_dir()
    path = d / f"nbrdf-{p.stem}-{digest}-v{BAKE_VERSION}{merl.BAKED_SUFFIX}"
    if path.is_file() and path.stat().st_size == merl.BAKED_FILE_BYTES:
        return path
    old = d / f"nbrdf-{p.stem}-{digest}-v1.binary"  # float64 cache of msps <= issue 21
    with cache_writes(d):
        if old.is_file():
            try:
                return merl.write_baked(path, merl.read_merl(old, dtype=np.float32).rgb)
            except InputError:  # damaged or vanished: bake afresh
                pass
        return merl.write_baked(path, make_table(read_weights(p)))


def rusinkiewicz_dirs(theta_h: float, theta_d: float, phi_d: float) -> tuple[np.ndarray, np.ndarray]:
    """(wi, wo) for given half/difference angles with phi_h = 0 (for tests and checks)."""
    wi, wo = merl.half_diff_to_dirs(np.array(theta_h), np.array(theta_d), np.array(phi_d))
    return wi, wo

