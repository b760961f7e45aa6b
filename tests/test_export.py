"""`msps export` (issue 13): every format read back and compared with the shard it came from.

Tolerances are the formats' quantisation: an integer PNG code is within half a
step of the exact value, i.e. |decoded - exact| <= 0.5 / 65535 (16-bit) or
0.5 / 255 (8-bit) on the exported scale; we allow 0.51 steps for float64
rounding.  Text files carry 9 significant digits, which round-trip float32
(what the shard stores) exactly.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import cli, one_line_error, render_tiny
from msps_render.dataset import schema as K  # the shard's HDF5 keys
from msps_render.errors import InputError

pytestmark = pytest.mark.usefixtures("force_llvm")  # LLVM even where CUDA is preferred (conftest.py)

TINY = """
[dataset]
name = "tiny-export"
seed = 11
n_shards = 2
frames_per_shard = 1
[dataset.patches]
size = 16
stride = 8
[dataset.storage]
store_frames = {frames}
[scene.camera]
width = 32
height = 32
[scene.integrator]
spp = 4
max_depth = 3
"""
STEP16 = 0.51 / 65535
STEP8 = 0.51 / 255


def _render(tmp: Path, frames: bool) -> Path:
    return render_tiny(TINY.format(frames=str(frames).lower()), tmp, f"ds-{frames}")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return _render(tmp_path_factory.mktemp("export"), True)


def _frames(root):
    from msps_render.data import iter_frames

    return list(iter_frames(root))


def _light_rgb(root, fr):
    import h5py

    with h5py.File(Path(root) / "shards" / fr.shard, "r") as h:
        return h[K.FRAME_LIGHT_RGB][fr.index].astype(np.float64)


def test_png16_and_exr_read_back_equal_the_shard(dataset, tmp_path):
    from msps_render.calibration import load_calibration_file
    from msps_render.export import export_dataset
    from msps_render.io.png16 import decode_normal, from_unorm, read_png
    from msps_render.io.images import read_image

    frames = _frames(dataset)
    png = export_dataset(dataset, "png16", tmp_path / "png")
    exr = export_dataset(dataset, "exr", tmp_path / "exr")
    assert png["n_frames"] == exr["n_frames"] == len(frames) == 2
    for fr, ip, ie in zip(frames, png["frames"], exr["frames"]):
        assert (ip["shard"], ip["frame"]) == (fr.shard, fr.index)
        dp, de = tmp_path / "png" / ip["dir"], tmp_path / "exr" / ie["dir"]
        m = fr.mask
        # 16-bit PNG: linear, one exposure per frame (brightest -> 65535), no clipping
        a = read_png(dp / "image.png")
        assert a.dtype == np.uint16 and a.shape == fr.image.shape
        s = ip["png_scale"]
        assert s == pytest.approx(1 / fr.image.max())
        assert np.abs(from_unorm(a) / s - fr.image).max() <= STEP16 / s
        n = decode_normal(read_png(dp / "normal.png"))
        assert np.abs(n[m] - fr.normal[m]).max() <= 2 * STEP16  # (n+1)/2 coded: twice the step in n
        assert np.abs(n[~m]).max() <= 2 * STEP16  # background n = 0 (mid grey)
        # EXR: float32 as stored
        assert np.array_equal(read_image(de / "image.exr"), fr.image)
        assert np.array_equal(read_image(de / "normal.exr")[m], fr.normal[m])
        for d in (dp, de):
            assert np.array_equal(read_png(d / "mask.png") > 0, m)
            L, M = load_calibration_file(d / "calibration.json")  # the schema predict reads
            assert np.array_equal(L.astype(np.float32), fr.light_dirs)  # 9 digits: float32 exact
            assert np.array_equal(M.astype(np.float32), fr.crosstalk)
    idx = json.loads((tmp_path / "png" / "export.json").read_text())
    assert idx["format"] == "png16" and idx["n_frames"] == 2


def _recovered_image(per_light_imgs, intensities, light_rgb):
    """sum_k image_k / intensity_k * light_rgb_k: the radiance the frame's three lights produce."""
    return sum(img / I[None, None, :] * rgb[None, None, :] for img, I, rgb in zip(per_light_imgs, intensities,
                                                                                  light_rgb))


def test_diligent_layout_read_back(dataset, tmp_path):
    from scipy.io import loadmat

    from msps_render.export import export_dataset
    from msps_render.io.png16 import decode_normal, from_unorm, read_png

    idx = export_dataset(dataset, "pmsData", tmp_path / "dl", rerender=True)
    root = tmp_path / "dl"
    objects = (root / "objects.txt").read_text().split()
    assert objects == [i["dir"] for i in idx["frames"]]
    for fr, info in zip(_frames(dataset), idx["frames"]):
        d = root / info["dir"]
        names = (d / "filenames.txt").read_text().split()
        assert names == ["001.png", "002.png", "003.png"]
        L = np.loadtxt(d / "light_directions.txt")
        assert np.array_equal(L.astype(np.float32), fr.light_dirs)
        I = np.loadtxt(d / "light_intensities.txt")
        s = info["png_scale"]
        rgb = _light_rgb(dataset, fr)
        assert np.allclose(I, rgb * s, rtol=1e-8)
        imgs = [from_unorm(read_png(d / n)) for n in names]
        assert all(read_png(d / n).dtype == np.uint16 for n in names)
        # the re-rendered per-light images sum to the stored frame (same scene, seed and variant)
        assert info["per_light_max_rel_deviation"] <= 1e-5
        rec = _recovered_image(imgs, I, rgb)
        # each image is within half a 16-bit step on the scale s; /I*rgb = /s: 3 images -> 3 steps / s
        tol = 3 * STEP16 / s + info["per_light_max_rel_deviation"] * fr.image.max()
        assert np.abs(rec - fr.image)[fr.mask].max() <= tol
        assert np.array_equal(read_png(d / "mask.png") > 0, fr.mask)
        n_mat = loadmat(d / "Normal_gt.mat")["Normal_gt"]
        assert np.array_equal(n_mat[fr.mask].astype(np.float32), fr.normal[fr.mask])
        n_txt = np.loadtxt(d / "normal.txt").reshape(fr.normal.shape)
        assert np.array_equal(n_txt.astype(np.float32)[fr.mask], fr.normal[fr.mask])
        assert np.abs(decode_normal(read_png(d / "Normal_gt.png"))[fr.mask] - fr.normal[fr.mask]).max() <= 2 * STEP16


def test_psfcn_layout_read_back_as_ps_fcn_does(dataset, tmp_path):
    from msps_render.export import export_dataset
    from msps_render.io.png16 import read_png

    export_dataset(dataset, "psfcn", tmp_path / "ps", rerender=True)
    root = tmp_path / "ps"
    entries = (root / "train_mtrl.txt").read_text().split()
    frames = _frames(dataset)
    assert len(entries) == len(frames)
    for fr, entry in zip(frames, entries):
        shape, mtrl = entry.split("/")  # as PS_Synth_Dataset._getInputPath
        normal = read_png(root / "Images" / shape / f"{shape}_normal.png").astype(np.float32) / 255.0 * 2 - 1
        img_dir = root / "Images" / entry
        rows = [ln.split(" ") for ln in (img_dir / f"{shape}_{mtrl}.txt").read_text().splitlines()]
        lights = np.array([r[1:4] for r in rows], dtype=np.float64)
        assert np.array_equal(lights.astype(np.float32), fr.light_dirs)
        imgs = [read_png(img_dir / r[0]) for r in rows]
        assert all(a.dtype == np.uint8 and a.shape == fr.image.shape for a in imgs)
        # PS-FCN's normalToMask (|n|^2 > 0.01) recovers the mask from the 8-bit normal map
        assert np.array_equal((normal ** 2).sum(-1) > 0.01, fr.mask)
        assert np.abs(normal[fr.mask] - fr.normal[fr.mask]).max() <= 2 * STEP8
        I = np.loadtxt(img_dir / "light_intensities.txt")
        s = float(I[0, 0])
        rgb = _light_rgb(dataset, fr)
        rec = _recovered_image([a / 255.0 for a in imgs], I, rgb)
        # image k = per_light_k / rgb_k * s (8-bit): error per image <= 0.5/255 / s * rgb_k
        tol = STEP8 / s * rgb.sum(0)
        assert (np.abs(rec - fr.image)[fr.mask] <= tol[None, :] + 1e-6).all()


def test_export_refuses_bad_input_with_one_line_and_writes_nothing(dataset, tmp_path, monkeypatch):
    import dataclasses

    from msps_render.export import FORMATS, export_dataset

    no_frames = _render(tmp_path, False)
    r = cli("export", no_frames, "--format", "png16", "--out", tmp_path / "a")
    assert "shard-00000.h5" in one_line_error(r) and "store_frames" in r.stderr
    r = cli("export", dataset, "--format", "psfcn", "--out", tmp_path / "b")
    assert "per-light" in one_line_error(r) and "--rerender" in r.stderr
    r = cli("export", dataset, "--format", "png", "--out", tmp_path / "c")
    assert "unknown export format 'png'" in one_line_error(r)
    r = cli("export", tmp_path, "--format", "exr", "--out", tmp_path / "d")
    assert "no dataset.json" in one_line_error(r)
    full = tmp_path / "full"
    full.mkdir()
    (full / "keep.txt").write_text("mine")
    r = cli("export", dataset, "--format", "exr", "--out", full)
    assert "not empty" in one_line_error(r) and str(full) in r.stderr
    assert [p.name for p in full.iterdir()] == ["keep.txt"]
    assert not any((tmp_path / x).exists() for x in "abcd")

    # a failure half-way (here: the second frame) leaves no output and no temporary directory
    import msps_render.export.images as E

    real, calls = E.write_png16, []

    def fail_second(ef, root):
        calls.append(ef.id)
        if len(calls) == 2:
            raise InputError(ef.id, "simulated failure")
        return real(ef, root)

    monkeypatch.setitem(FORMATS, "png16", dataclasses.replace(FORMATS["png16"], write_frame=fail_second))
    with pytest.raises(InputError, match="simulated"):
        export_dataset(dataset, "png16", tmp_path / "half")
    assert len(calls) == 2
    assert not (tmp_path / "half").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_png16_export_feeds_predict_with_linear(dataset, tmp_path):
    """`msps predict --linear` reads the 16-bit export as radiance: same normals as from the EXR."""
    from msps_render.export import export_dataset
    from msps_render.models.metrics import angular_error_deg
    from msps_render.models.predict import load_rig, predict_main, predict_method, read_inputs

    png = export_dataset(dataset, "png16", tmp_path / "png")
    exr = export_dataset(dataset, "exr", tmp_path / "exr")
    dp, de = tmp_path / "png" / png["frames"][0]["dir"], tmp_path / "exr" / exr["frames"][0]["dir"]
    img, _ = read_inputs(dp / "image.png", None, linear=True)
    ref, _ = read_inputs(de / "image.exr", None)
    s = png["frames"][0]["png_scale"]
    assert np.abs(img / s - ref).max() <= STEP16 / s + 1e-7  # all 16 bits kept (Pillow keeps 8)
    for d, name in ((dp, "image.png"), (de, "image.exr")):
        predict_main(d / name, tmp_path / d.parent.name, predict_method("lambertian"), load_rig(d / "calibration.json"),
                     mask=d / "mask.png", linear=True, warn=lambda m: None)
    a, b = np.load(tmp_path / "png.npy"), np.load(tmp_path / "exr.npy")
    m = np.linalg.norm(b, axis=-1) > 0
    # same linear image up to 16-bit quantisation (and an exposure Lambertian PS ignores)
    e = angular_error_deg(a[m], b[m])
    # measured: mean 0.001 deg, max 0.02 deg (the darkest pixels, where 16-bit steps are relatively largest)
    assert e.mean() < 0.01 and e.max() < 0.2


# ------------------------------------------------------------------ read the way other tools read
def read_png16(path) -> np.ndarray:
    """pypng: the stored integers in RGB order (imageio/Pillow return 8 bits for 16-bit RGB PNGs)."""
    import png

    w, h, rows, info = png.Reader(filename=str(path)).asDirect()
    a = np.array([np.asarray(r) for r in rows], np.uint16 if info["bitdepth"] > 8 else np.uint8)
    return a.reshape(h, w, info["planes"]).squeeze()


def read_exr_rgb(path) -> np.ndarray:
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        return np.asarray(f.channels()["RGB"].pixels)


def test_exports_read_with_pypng_opencv_and_openexr(dataset, tmp_path):
    """docs/recipes.md's readers: pypng and OpenCV (BGR!) for 16-bit PNG, OpenEXR for EXR."""
    import cv2
    from PIL import Image

    from msps_render.export import export_dataset

    frames = _frames(dataset)
    png = export_dataset(dataset, "png16", tmp_path / "png")
    export_dataset(dataset, "exr", tmp_path / "exr")
    dl = export_dataset(dataset, "diligent", tmp_path / "dl", rerender=True)
    for fr, ip, idl in zip(frames, png["frames"], dl["frames"]):
        d = tmp_path / "png" / ip["dir"]
        a = read_png16(d / "image.png")
        bgr = cv2.imread(str(d / "image.png"), cv2.IMREAD_UNCHANGED)
        assert a.dtype == bgr.dtype == np.uint16 and np.array_equal(bgr[..., ::-1], a)
        assert np.abs(a / 65535 / ip["png_scale"] - fr.image).max() <= STEP16 / ip["png_scale"]
        assert np.asarray(Image.open(d / "image.png")).dtype == np.uint8  # the pitfall the recipe warns of
        n = read_png16(d / "normal.png") / 65535 * 2 - 1
        assert np.abs(n[fr.mask] - fr.normal[fr.mask]).max() <= 2 * STEP16
        mask = cv2.imread(str(d / "mask.png"), cv2.IMREAD_UNCHANGED)
        assert mask.ndim == 2 and np.array_equal(mask > 0, fr.mask)
        e = tmp_path / "exr" / ip["dir"]
        assert np.array_equal(read_exr_rgb(e / "image.exr"), fr.image)
        assert np.array_equal(read_exr_rgb(e / "normal.exr")[fr.mask], fr.normal[fr.mask])
        # DiLiGenT: 16-bit per-light images / their intensities = the object under unit white lights
        g = tmp_path / "dl" / idl["dir"]
        I = np.loadtxt(g / "light_intensities.txt")
        imgs = [cv2.imread(str(g / name), cv2.IMREAD_UNCHANGED)[..., ::-1] / 65535 for name in
                (g / "filenames.txt").read_text().split()]
        rec = _recovered_image(imgs, I, _light_rgb(dataset, fr))
        tol = 3 * STEP16 / idl["png_scale"] + idl["per_light_max_rel_deviation"] * fr.image.max()
        assert np.abs(rec - fr.image)[fr.mask].max() <= tol


GREY = """
[dataset]
name = "grey-lambertian"
seed = 7
n_shards = 1
frames_per_shard = 3
[dataset.patches]
size = 16
stride = 16
[dataset.storage]
store_frames = true
store_per_light = true
[scene.materials]
families = ["grey"]
[scene.camera]
width = 64
height = 64
[scene.integrator]
spp = 4
max_depth = 2
"""


def _ps_fcn_read_list(path, sort: bool = True) -> list[str]:
    """PS-FCN's `util.readList`: the file's lines, naturally sorted."""
    import re

    lines = Path(path).read_text().splitlines()
    if sort:
        lines.sort(key=lambda t: [int(c) if c.isdigit() else c for c in re.split(r"(\d+)", t)])
    return lines


def _ps_fcn_item(root: Path, entry: str) -> dict:
    """PS-FCN's `PS_Synth_Dataset.__getitem__` (no crop, no augmentation): its reading code, step by step."""
    from PIL import Image  # imageio's PNG reader (what PS-FCN's `imread` is) is Pillow: fine for 8-bit

    def imread(p):
        return np.asarray(Image.open(p))

    shape, mtrl = entry.split("/")
    normal_path = root / "Images" / shape / f"{shape}_normal.png"
    img_dir = root / "Images" / entry
    data = np.genfromtxt(_ps_fcn_read_list(img_dir / f"{shape}_{mtrl}.txt"), dtype="str", delimiter=" ")
    imgs = [img_dir / name for name in data[:, 0]]
    lights = data[:, 1:4].astype(np.float32)
    normal = imread(normal_path).astype(np.float32) / 255.0 * 2 - 1
    img = np.concatenate([imread(p).astype(np.float32) / 255.0 for p in imgs], 2)
    mask = (np.square(normal).sum(2, keepdims=True) > 0.01).astype(np.float32)  # normalToMask
    normal = normal * mask.repeat(3, 2)
    normal = normal / (np.sqrt((normal * normal).sum(2, keepdims=True)) + 1e-10)
    return {"N": normal, "img": img, "mask": mask, "light": lights}


def _lambertian_ps(img: np.ndarray, lights: np.ndarray) -> np.ndarray:
    """Calibrated Lambertian PS on K RGB images (H, W, 3K) under unit white lights: grey I = L g, least
    squares (K = 3: L's inverse; any K >= 3: tests/test_rig_export.py)."""
    H, W, _ = img.shape
    grey = img.reshape(H, W, len(lights), 3).mean(-1)
    g = np.einsum("ij,hwj->hwi", np.linalg.pinv(lights.astype(np.float64)), grey)
    return g / (np.linalg.norm(g, axis=-1, keepdims=True) + 1e-12)


def test_psfcn_export_through_ps_fcn_loader_recovers_lambertian_normals(tmp_path):
    """Read as PS-FCN's PS_Synth_Dataset does, a grey Lambertian render gives back its normals.

    Bound: median angular error < 2 deg.  Direct light only (max_depth = 2) on a Lambertian
    surface makes I_k = rho (n . l_k) exact wherever every light is above the horizon, so what
    is left is 8-bit quantisation (half a step of 255 at the brightest pixel: <= 1% of a typical
    value, < 1 deg for slant-30 lights) and pixel-footprint averaging; attached shadows
    (n . l_k < 0, the silhouette rim) break the model but are a minority of the mask, so they do
    not move the median.  Measured: 0.56-0.59 deg per frame.  A mis-read layout (lights paired
    with the wrong images, or y flipped) gives > 10 deg.
    """
    from msps_render.export import export_dataset
    from msps_render.pipeline.config import load_config
    from msps_render.pipeline.run import render_dataset
    from msps_render.render.variant import resolve_variant

    v = resolve_variant("rgb")
    if not v.startswith("llvm"):
        pytest.skip("LLVM variant unavailable: rendering would be too slow")
    (tmp_path / "grey.toml").write_text(GREY)
    render_dataset(load_config(tmp_path / "grey.toml"), tmp_path / "grey", workers=1, progress=False, variant=v)
    export_dataset(tmp_path / "grey", "psfcn", tmp_path / "ps")  # per-light images stored: no --rerender
    root = tmp_path / "ps"
    entries = _ps_fcn_read_list(root / "train_mtrl.txt")
    assert len(entries) == 3

    def error_deg(n, gt, m):
        return np.degrees(np.arccos(np.clip((n * gt).sum(-1), -1.0, 1.0)))[m]

    for entry in entries:
        item = _ps_fcn_item(root, entry)
        m = item["mask"][..., 0] > 0
        assert item["img"].shape == m.shape + (9,) and m.sum() > 500
        err = error_deg(_lambertian_ps(item["img"], item["light"]), item["N"], m)
        assert np.median(err) < 2.0, (entry, float(np.median(err)))
        # the test can fail: lights read for the wrong images, or y flipped, are far off
        wrong = error_deg(_lambertian_ps(item["img"], item["light"][[1, 2, 0]]), item["N"], m)
        flipped = error_deg(_lambertian_ps(item["img"], item["light"] * [1, -1, 1]), item["N"], m)
        assert np.median(wrong) > 10 and np.median(flipped) > 10
