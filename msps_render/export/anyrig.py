"""`msps export` of a rig dataset (format-2 shards, `[scene.rig]`): the frames, the checks, the index.

A rig dataset stores each whole frame as the camera's shots (`frames/shots`, S x H x W x M) with the
true and the nominal (calibration) rig beside them (`msps_render.dataset.reader.iter_rig_frames`).
The per-light layouts (`diligent`, `psfcn`) need one image per light, so they take a *sequential*
capture (every shot one light, every light in one shot): shot s = (k,) is written as light k's image,
in light order.  A rig whose shots hold several lights (multiplexed, or a custom capture) is refused
in one line naming the dataset, before anything is written; so is a camera of other than 1 (grey)
or 3 (RGB) channels, which no PNG can hold.

The stored shots are the camera's images: an environment light (a frame with `env_ratio` > 0) is in
every one of them, as ambient light is in a real capture, and a sensor model's noise too; they are
written as they are (export.json records env_ratio per frame and the dataset's sensor model).
Three-light datasets (format 1) do not come here: `msps_render.export.export_dataset` sends them
through the format modules' three-light writers, unchanged.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from msps_render.dataset import schema as K
from msps_render.dataset import load_manifest, open_shard, read_manifest, shard_errors
from msps_render.dataset.reader import format_version, is_rig_shard, iter_rig_frames, read_rigs
from msps_render.errors import InputError
from msps_render.export.formats import write_frames
from msps_render.export.source import safe_name, sensor_model, write_json
from msps_render.io.staging import check_new_out, staged_dir

PNG_CHANNELS = (1, 3)  # grey or RGB: what a PNG holds (no alpha)


@dataclass
class RigExportFrame:
    """A whole frame of a sequential-capture rig dataset, one image per light."""

    id: str  # unique, file-name safe: "0003-torus"
    images: np.ndarray  # (N, H, W, M) float32 linear radiance: image k = the shot of light k alone
    normal: np.ndarray  # (H, W, 3) camera frame
    mask: np.ndarray  # (H, W) bool
    rig: object  # msps_render.rig.Rig, what was rendered (truth)
    nominal: object  # msps_render.rig.Rig, what a calibration says
    light_rgb: np.ndarray  # (N, 3) each light's RGB (irradiance; point lights: intensity)
    points: np.ndarray | None  # (H, W, 3) surface points, camera frame (near lights), else None
    object: str
    materials: str
    condition: str
    shard: str
    index: int
    env_ratio: float = 0.0

    @property
    def n_lights(self) -> int:
        return int(self.images.shape[0])

    @property
    def n_channels(self) -> int:
        return int(self.images.shape[-1])

    @property
    def near(self) -> bool:
        return bool(self.rig.has_point_lights)

    def info(self) -> dict:
        return {"id": self.id, "object": self.object, "materials": self.materials, "condition": self.condition,
                "shard": self.shard, "frame": self.index, "height": int(self.mask.shape[0]),
                "width": int(self.mask.shape[1]), "env_ratio": round(float(self.env_ratio), 6),
                "rig": self.rig.describe(), "n_lights": self.n_lights, "n_channels": self.n_channels,
                "calibration_error_max_deg": round(calibration_error_deg(self), 6)}


def calibration_error_deg(ef: RigExportFrame) -> float:
    """Largest angle between a light's nominal and true direction (0 without calibration errors)."""
    a = np.asarray(ef.nominal.light_dirs, np.float64)
    b = np.asarray(ef.rig.light_dirs, np.float64)
    c = (a * b).sum(-1) / np.maximum(np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1), 1e-12)
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))).max()) if len(c) else 0.0


def is_rig_dataset(root: str | Path) -> bool:
    """Whether the dataset's shards are format 2 (any rig); InputError when its shards mix formats."""
    m = load_manifest(root)
    kinds = {}
    for e in m.shards_of():
        path = m.shard_path(e.name)
        with shard_errors(path), open_shard(path) as h:
            kinds.setdefault(is_rig_shard(h), path)
    if len(kinds) > 1:
        raise InputError(root, f"shards of two formats ({kinds[False].name}: three-light, {kinds[True].name}: "
                               "rig); export each kind from a dataset of its own")
    return True in kinds


def light_order(shots, n_lights: int) -> list[int] | None:
    """Shot index of each light (light order) when every shot is one light and every light is in exactly
    one shot; None otherwise."""
    if any(len(s) != 1 for s in shots):
        return None
    lights = [int(s[0]) for s in shots]
    if sorted(lights) != list(range(n_lights)):
        return None
    return [lights.index(k) for k in range(n_lights)]


def check_rig_dataset(root: str | Path, fmt: str) -> None:
    """InputError naming the dataset (one line) unless every frame is a sequential capture of one rig size
    whose camera PNG can hold: checked from the frames' rig tables before any image is read."""
    root = Path(root)
    m = load_manifest(root)
    sizes = set()
    for e in m.shards_of():
        path = m.shard_path(e.name)
        with shard_errors(path), open_shard(path) as h:
            format_version(h)
            for i, rig in enumerate(read_rigs(h)[0]):
                shots = rig.shot_list
                if light_order(shots, rig.n_lights) is None:
                    many = next((s for s in shots if len(s) != 1), None)
                    what = (f"shots of {len(many)} lights (shot {shots.index(many)}: lights "
                            f"{', '.join(map(str, many))})" if many is not None else
                            f"{len(shots)} one-light shots for {rig.n_lights} lights (a light twice or missing)")
                    raise InputError(root, f"the {fmt} format needs one image per light (a sequential capture: "
                                           f"scene.rig.capture = \"sequential\"); this dataset's rig "
                                           f"({rig.describe()}) takes {what} ({path.name}, frame {i})")
                if rig.n_channels not in PNG_CHANNELS:
                    raise InputError(root, f"the {fmt} format writes grey (1-channel) or RGB (3-channel) PNGs; "
                                           f"this dataset's camera has {rig.n_channels} channels "
                                           f"({path.name}, frame {i})")
                sizes.add((rig.n_lights, rig.n_channels))
    if len(sizes) > 1:
        raise InputError(root, f"frames of different rig sizes (lights x channels: "
                               f"{', '.join(f'{n} x {c}' for n, c in sorted(sizes))}); the {fmt} layout "
                               "lists one set of image names")


def iter_rig_export_frames(root: str | Path) -> Iterator[RigExportFrame]:
    """Every whole frame of a rig dataset, its shots put in light order (`check_rig_dataset` first)."""
    m = load_manifest(root)
    n = 0
    for e in m.shards_of():
        path = m.shard_path(e.name)
        with shard_errors(path), open_shard(path) as h:
            env = h[K.FRAME_ENV_RATIO][()]
        for fr in iter_rig_frames(path):
            order = light_order(fr.rig.shot_list, fr.rig.n_lights)
            images = np.asarray(fr.shots, np.float32)[order]
            yield RigExportFrame(id=f"{n:04d}-{safe_name(fr.object)}", images=images,
                                 normal=np.asarray(fr.normal, np.float32), mask=np.asarray(fr.mask, bool),
                                 rig=fr.rig, nominal=fr.nominal,
                                 light_rgb=np.asarray(fr.light_rgb, np.float64),
                                 points=None if fr.points is None else np.asarray(fr.points, np.float32),
                                 object=fr.object, materials=fr.materials, condition=fr.condition, shard=fr.shard,
                                 index=fr.index, env_ratio=float(env[fr.index]))
            n += 1


# ------------------------------------------------------------------ what the writers share
def intensity_rows(crosstalk: np.ndarray, scale: float) -> np.ndarray:
    """(N, 3) light_intensities.txt rows: column m of row n = C[m, n] * scale (channel m's reading of light n
    on the images' scale); a grey camera's one value in all three columns (DiLiGenT files are R G B)."""
    rows = np.asarray(crosstalk, np.float64).T * scale  # (N, M)
    return np.repeat(rows, 3, axis=1) if rows.shape[1] == 1 else rows


def light_positions(rig) -> np.ndarray | None:
    """(N, 3) point lights' positions (camera frame, scene units; NaN rows: directional), or None."""
    return None if not rig.has_point_lights else np.asarray(rig.positions, np.float64)


RIG_CONVENTIONS = {
    "frame": "camera frame: x right, y up, z toward the camera (normals, light directions, light positions, "
             "surface points)",
    "radiance": "linear (no gamma); PNG value / 65535 (or / 255) / png_scale = the stored shot's radiance "
                "(psfcn: divided by the light's reading first)",
    "normal_png": "(n + 1) / 2 * 65535 (or * 255); n = 0 (mid grey) outside the mask",
    "images": "image k is the camera's shot of light k alone (a sequential capture), in light order; a grey "
              "camera's images are 1-channel PNGs (psfcn: the grey value in all three channels)",
    "light_directions": "light_directions.txt: the NOMINAL rig (what a calibration gives); "
                        "light_directions_true.txt: what was rendered (equal unless the preset adds "
                        "scene.rig.errors); point lights: the direction from the object centre",
    "light_intensities": "row k: channel m's reading of light k on a white surface at the object centre "
                         "(nominal; _true: rendered), times png_scale: image_k / intensity_k is the image under "
                         "a unit white light (near lights: still with their fall-off); grey camera: the one "
                         "value in all three columns",
    "near_lights": "point lights: light_positions.txt (nominal) and light_positions_true.txt, x y z per light in "
                   "scene units; points.npy (H, W, 3) float32 surface point of each pixel centre (0 off the "
                   "object); light_anisotropy.txt (LEDs with anisotropy_mu): mu per light, radiant intensity "
                   "cos^mu of the angle off the LED's axis, which points at the object centre",
}


def export_rig_dataset(root: str | Path, f, out: str | Path, rerender: bool = False,
                       progress: Callable[[int, RigExportFrame], None] | None = None) -> dict:
    """`export_dataset` for a rig dataset with format `f` (an `ExportFormat`); returns the index."""
    root, out = Path(root), Path(out)
    if f.write_rig_frame is None:
        raise InputError(root, f"a rig dataset (format-2 shards); the {f.name} format writes three-light frames: "
                               "export it with --format diligent or psfcn")
    if rerender:
        raise InputError("--rerender", "a rig dataset stores every shot (one image per light of a sequential "
                                       "capture): export it without --rerender")
    check_rig_dataset(root, f.name)
    check_new_out(out)
    with staged_dir(out) as stage:
        infos = write_frames(iter_rig_export_frames(root), f.write_rig_frame, stage, progress)
        if f.finish:
            f.finish(stage, infos)
        m = read_manifest(root) or {}
        index = {"format": f.name, "dataset": str(root.resolve()), "config_hash": m.get("config_hash"),
                 "n_frames": len(infos), "conventions": RIG_CONVENTIONS, "sensor_model": sensor_model(root),
                 "images": {"source": "stored in the shards (frames/shots, one shot per light)",
                            "contents": "the camera's images as rendered: an environment light (env_ratio > 0) "
                                        "and a sensor model's effects are in every image",
                            "files": f.rig_light_files},
                 "frames": infos}
        write_json(stage / "export.json", index)
    return index
