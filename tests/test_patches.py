"""Frame -> patches (msps_render/patches.py): which windows are kept, and what each holds."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from msps_render.patches import cut_windows, patchify, window_origins


def _gather(a: np.ndarray, origins: np.ndarray, size: int, axis: int) -> np.ndarray:
    """The windows by numpy's advanced indexing (the definition `cut_windows` must equal)."""
    iy = origins[:, 0, None] + np.arange(size)[None, :]
    ix = origins[:, 1, None] + np.arange(size)[None, :]
    return np.moveaxis(a[(slice(None),) * axis + (iy[:, :, None], ix[:, None, :])], axis, 0)


@pytest.mark.parametrize("shape, axis", [((37, 45, 3), 0), ((37, 45), 0), ((4, 37, 45, 2), 1), ((5, 37, 45), 1)])
def test_cut_windows_equals_the_advanced_index_gather(shape, axis):
    rng = np.random.default_rng(1)
    a = rng.normal(size=shape).astype(np.float32)
    origins = window_origins(37, 45, 10, 7)[rng.permutation(len(window_origins(37, 45, 10, 7)))[:9]]
    got = cut_windows(a, origins, 10, axis)
    assert got.shape == (9, *shape[:axis], 10, 10, *shape[axis + 2:]) and got.dtype == a.dtype
    assert np.array_equal(got, _gather(a, origins, 10, axis))
    assert cut_windows(a, origins[:0], 10, axis).shape == (0, *shape[:axis], 10, 10, *shape[axis + 2:])


def test_patchify_keeps_the_covered_windows_and_cuts_every_array_the_same_way():
    """An object covering the left 30 columns of a 40 x 64 frame, 20 px windows at stride 10: the
    windows at x = 0, 10 are fully covered, x = 20 has 10 / 20 covered (kept at 0.5, not at 0.6)."""
    H, W = 40, 64
    mask = np.zeros((H, W), bool)
    mask[:, :30] = True
    rng = np.random.default_rng(2)
    frame = SimpleNamespace(mask=mask, image=rng.random((H, W, 3)).astype(np.float32),
                            normal=rng.normal(size=(H, W, 3)).astype(np.float32),
                            shots=None, points=None, shadow=rng.random((4, H, W)) > 0.5)
    p = patchify(frame, size=20, stride=10, min_coverage=0.5)
    assert sorted(map(tuple, p.yx.tolist())) == [(y, x) for y in (0, 10, 20) for x in (0, 10, 20)]
    assert sorted({x for _, x in patchify(frame, 20, 10, 0.6).yx.tolist()}) == [0, 10]
    for k, (y, x) in enumerate(p.yx.tolist()):
        assert np.array_equal(p.image[k], frame.image[y:y + 20, x:x + 20])
        assert np.array_equal(p.normal[k], frame.normal[y:y + 20, x:x + 20])
        assert np.array_equal(p.mask[k], mask[y:y + 20, x:x + 20].astype(np.uint8))
        assert np.array_equal(p.shadow[k], frame.shadow[:, y:y + 20, x:x + 20].astype(np.uint8))
    assert p.image.dtype == np.float32 and p.mask.dtype == np.uint8 and p.shadow.shape == (9, 4, 20, 20)


def _frame(H=40, W=64, seed=3):
    mask = np.zeros((H, W), bool)
    mask[:, :30] = True
    rng = np.random.default_rng(seed)
    return SimpleNamespace(mask=mask, image=(rng.random((H, W, 3)) * 4).astype(np.float32),
                           normal=rng.normal(size=(H, W, 3)).astype(np.float32), shots=None, points=None, shadow=None)


def test_patches_cut_in_the_stored_dtype_equal_the_float32_windows_cast():
    """The pipeline cuts patches in the shard's dtypes from a frame cast once: the same bytes as the
    float32 windows cast by the writer, as before (a cast is per value); a float64 frame goes by way of
    float32, so no other rounding creeps in."""
    frame = _frame()
    ref = patchify(frame, 20, 10, 0.5)
    got = patchify(frame, 20, 10, 0.5, "float16", "float16")
    assert got.image.dtype == np.float16 and got.normal.dtype == np.float16
    assert got.image.tobytes() == ref.image.astype(np.float16).tobytes()
    assert got.normal.tobytes() == ref.normal.astype(np.float16).tobytes()
    assert np.array_equal(got.mask, ref.mask) and np.array_equal(got.yx, ref.yx)
    f64 = SimpleNamespace(**{**vars(frame), "image": frame.image.astype(np.float64) + 1e-9})
    assert patchify(f64, 20, 10, 0.5, "float16").image.tobytes() == \
        patchify(f64, 20, 10, 0.5).image.astype(np.float16).tobytes()


def test_float16_overflow_is_refused_only_inside_a_kept_window():
    frame = _frame()
    frame.image[5, 5] = 1e6  # inside the kept windows at x = 0
    with pytest.raises(ValueError, match="float16 range"):
        patchify(frame, 20, 10, 0.5, "float16")
    assert patchify(frame, 20, 10, 0.5, "float32").image.max() == np.float32(1e6)
    frame = _frame()
    frame.image[5, 60] = 1e6  # in the background, which no kept window reaches (x <= 39)
    p = patchify(frame, 20, 10, 0.5, "float16")
    assert np.isfinite(p.image).all() and len(p) == 9


def test_float16_value_checks_by_bits_agree_with_numpy_on_every_float16():
    """`all_finite` / `any_negative` read float16's bits (the writer's and `msps verify`'s checks); every one
    of the 65,536 float16 values, alone and inside a finite array, gives numpy's answer."""
    from msps_render.dataset.schema import all_finite, any_negative

    every = np.arange(1 << 16, dtype=np.uint32).astype(np.uint16).view(np.float16)
    with np.errstate(invalid="ignore"):
        finite, negative = np.isfinite(every), every < 0
    base = np.full((3, 4), 0.5, np.float16)
    mism = []
    for i in range(0, 1 << 16, 1):
        a = base.copy()
        a[1, 2] = every[i]
        if all_finite(a) != bool(finite[i]) or any_negative(a) != bool(negative[i]):
            mism.append(hex(i))
    assert not mism, mism[:10]
    assert all_finite(np.zeros((0, 3), np.float16)) and not any_negative(np.zeros(0, np.float16))
    assert not all_finite(np.array([1.0, np.inf])) and any_negative(np.array([0.0, -1e-30]))  # float64 path
    assert all_finite(every[finite][::-1][::2])  # a strided view is checked like a contiguous one
