"""Mirror ensemble (models/symmetry.py): the rig's mirror symmetry, against closed forms.

A Lambertian object of albedo rho reads c = diag(rho) M max(0, L n).  For the paper's rig the
mirrored image with channels 1 and 2 swapped must equal, exactly, the render of the mirrored
object with its albedo's channels 1 and 2 swapped; the ensemble of an exact predictor must stay
exact; and the ensemble of any network must be exactly mirror-equivariant (tiles symmetric).
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from cli_helpers import cli, render_tiny
from msps_render.calibration import PAPER_CROSSTALK, direction_from_slant_tilt
from msps_render.errors import InputError
from msps_render.models.baseline import lambertian_ps, unshadowed
from msps_render.models.metrics import angular_error_deg
from msps_render.models.symmetry import Mirror, find_mirror, mirror_ensemble, require_mirror

M = PAPER_CROSSTALK
RHO = np.array([0.8, 0.5, 0.2])


def rig(tilts=(0.0, 120.0, 240.0), slant=30.0) -> np.ndarray:
    return np.stack([direction_from_slant_tilt(slant, t) for t in tilts])


def sphere(size: int, cy: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals of a sphere (camera frame: rows are -y), centred `cy` (in radii) above the middle."""
    y, x = np.mgrid[:size, :size]
    u, v = (x + 0.5) / size * 2 - 1, 1 - (y + 0.5) / size * 2 - cy
    mask = u ** 2 + v ** 2 < 0.7 ** 2
    n = np.zeros((size, size, 3))
    n[..., 0], n[..., 1] = u / 0.7, v / 0.7
    n[..., 2] = np.sqrt(np.clip(1 - n[..., 0] ** 2 - n[..., 1] ** 2, 0, 1))
    n[~mask] = 0
    return n, mask


def render(n: np.ndarray, mask: np.ndarray, L: np.ndarray, rho=RHO) -> np.ndarray:
    return (np.asarray(rho) * (np.maximum(n @ L.T, 0.0) @ M.T) * mask[..., None]).astype(np.float32)


def test_the_papers_rig_mirrors_about_the_image_x_axis():
    m = find_mirror(rig(), M)
    assert m == Mirror(axis=0, perm=(0, 2, 1))
    assert find_mirror(rig((90.0, 210.0, 330.0)), M) == Mirror(axis=1, perm=(0, 2, 1))  # about the y-axis
    assert find_mirror(rig((10.0, 130.0, 250.0)), M) is None  # symmetric, but not about an image axis
    skew = M.copy()
    skew[1, 0] = 0.08  # channel 1 picks up more of light 0 than channel 2 does
    assert find_mirror(rig(), skew) is None
    with pytest.raises(InputError, match="mirror symmetry"):
        require_mirror(rig((10.0, 130.0, 250.0)), M)


def test_mirrored_image_is_the_render_of_the_mirrored_object():
    """Off-centre sphere, coloured albedo: exact equality up to float32 rounding."""
    L = rig()
    n, mask = sphere(64, cy=0.2)
    mr = find_mirror(L, M)
    mirrored_n = mr.normals_back(n)  # the mirror is its own inverse
    want = render(mirrored_n, mr.mask(mask), L, RHO[[0, 2, 1]])
    np.testing.assert_allclose(mr.image(render(n, mask, L)), want, atol=1e-6)


def test_ensemble_of_an_exact_predictor_is_exact():
    L = rig()
    n, mask = sphere(64, cy=0.2)
    img = render(n, mask, L, np.full(3, 0.6))
    out = mirror_ensemble(lambda x, m: lambertian_ps(x, L, M, m), img, mask, find_mirror(L, M))
    lit = unshadowed(n, L, mask)  # the mirror maps lit pixels onto lit pixels
    assert lit.sum() > 1000
    assert angular_error_deg(out[lit], n[lit]).max() < 1e-3
    assert (out[~mask] == 0).all()


def test_ensemble_of_the_network_is_mirror_equivariant():
    """E(mirror x) = mirror E(x) for the shipped network: 240 px makes the 40/20 tiles symmetric."""
    from msps_render.models.checkpoint import load_checkpoint
    from msps_render.models.predict import default_checkpoint, predict_image

    model = load_checkpoint(default_checkpoint())[0]
    L = rig()
    mr = find_mirror(L, M)
    n, mask = sphere(240, cy=0.15)
    img = render(n, mask, L)
    pred = lambda x, m: predict_image(model, x, m, rig=M @ L)  # noqa: E731
    a = mirror_ensemble(pred, img, mask, mr)
    b = mirror_ensemble(pred, mr.image(img), mr.mask(mask), mr)
    np.testing.assert_allclose(mr.normals_back(b), a, atol=1e-5)
    single = pred(img, mask)
    assert angular_error_deg(single[mask], a[mask]).mean() > 0.1  # the network alone is not equivariant


MIRROR_SET = """
[dataset]
name = "tiny-mirror"
seed = 6
n_shards = 1
frames_per_shard = 2
[dataset.patches]
size = 40
stride = 20
[dataset.storage]
store_frames = true
[scene.shape]
source = "primitive"
primitives = ["superellipsoid"]
[scene.materials]
min_count = 1
max_count = 1
merl_fraction = 0.0
families = ["diffuse"]
[scene.lights]
crosstalk = [[0.92, 0.04, 0.04], [0.04, 0.92, 0.04], [0.04, 0.04, 0.92]]
[scene.environment]
enabled = false
[scene.camera]
width = 80
height = 80
[scene.integrator]
spp = 16
max_depth = 2
"""


def test_msps_eval_mirror_columns(tmp_path):
    """Renders through `msps eval --mirror --refine`: the columns exist, differ from the network's, and
    the mirror column on whole frames equals `msps predict --mirror` on the same image."""
    render_tiny(MIRROR_SET, tmp_path)
    r = cli("eval", "--data", tmp_path / "ds", "--out", tmp_path / "ev", "--mirror", "--refine")
    assert r.returncode == 0, r.stderr
    m = json.loads((tmp_path / "ev" / "metrics.json").read_text())["methods"]
    assert set(m) == {"net", "net+mirror", "net+refine", "net+mirror+refine"}
    (plain,) = m["net"]["conditions"].values()
    (mir,) = m["net+mirror"]["conditions"].values()
    assert mir["frames"]["mae_deg"] != pytest.approx(plain["frames"]["mae_deg"], abs=1e-3)
    assert mir["patches"]["mae_deg"] != pytest.approx(plain["patches"]["mae_deg"], abs=1e-3)


def _inputs(tmp_path, tilts):
    n, mask = sphere(48)
    np.save(tmp_path / "img.npy", render(n, mask, rig(tilts)))
    return ["--light-dirs", json.dumps(rig(tilts).tolist()), "--crosstalk", json.dumps(M.tolist())]


def test_predict_mirror_refusals_are_one_line(tmp_path):
    r = cli("predict", tmp_path / "img.npy", "--out", tmp_path / "o", *_inputs(tmp_path, (10.0, 130.0, 250.0)),
            "--mirror")
    assert r.returncode == 1
    err = r.stderr.strip().splitlines()
    assert len(err) == 1 and "--mirror" in err[0] and "symmetry" in err[0]
    assert not list(tmp_path.glob("o*"))
    r = cli("predict", tmp_path / "img.npy", "--out", tmp_path / "o", *_inputs(tmp_path, (0.0, 120.0, 240.0)),
            "--method", "lambertian", "--mirror")
    assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1 and "--mirror" in r.stderr
    assert not list(tmp_path.glob("o*"))


def test_mirror_augmentation_is_exact_for_any_rig():
    """A training batch's mirror image equals the render of the mirrored object under the mirrored rig, for a
    rig with no symmetry of its own (tilts 10/130/250, skewed crosstalk) and a coloured albedo."""
    import torch

    from msps_render.models.symmetry import mirror_batch

    L = rig((10.0, 130.0, 250.0), slant=25.0)
    skew = np.array([[0.90, 0.07, 0.02], [0.03, 0.85, 0.09], [0.05, 0.04, 0.93]])
    n, mask = sphere(40, cy=0.2)
    img = (RHO * (np.maximum(n @ L.T, 0.0) @ skew.T) * mask[..., None]).astype(np.float32)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, np.float32))  # noqa: E731
    batch = {"image": t(np.stack([img, img]).transpose(0, 3, 1, 2)), "normal": t(np.stack([n, n]).transpose(0, 3, 1, 2)),
             "mask": t(np.stack([mask, mask])[:, None]), "light_dirs": t(np.stack([L, L])),
             "crosstalk": t(np.stack([skew, skew]))}
    out = mirror_batch(batch, [False, True])
    for k in batch:  # the first patch untouched
        assert torch.equal(out[k][0], batch[k][0])
    n2 = out["normal"][1].numpy().transpose(1, 2, 0)
    L2, M2 = out["light_dirs"][1].numpy(), out["crosstalk"][1].numpy()
    m2 = out["mask"][1, 0].numpy() > 0
    want = RHO[[0, 2, 1]] * (np.maximum(n2 @ L2.T, 0.0) @ M2.T) * m2[..., None]
    np.testing.assert_allclose(out["image"][1].numpy().transpose(1, 2, 0), want, atol=1e-6)
    assert not np.allclose(L2, L) and not np.allclose(M2, skew)  # the rig was mirrored with the image
    np.testing.assert_allclose(np.linalg.norm(n2[m2], axis=-1), 1.0, atol=1e-6)
