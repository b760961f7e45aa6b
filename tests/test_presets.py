"""Every preset in scenes/ validates, and the paper presets say what the paper says."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from msps_render.pipeline.config import PRESET_DIR, load_config

PRESETS = sorted(p.stem for p in Path(PRESET_DIR).glob("*.toml"))


def test_presets_exist():
    assert {"demo", "paper-train", "paper-val", "paper-test"} <= set(PRESETS)


@pytest.mark.parametrize("name", PRESETS)
def test_preset_validates(name):
    cfg = load_config(name)
    assert cfg.dataset.patches.size <= cfg.scene.camera.width


def test_paper_presets_match_the_paper():
    tr, va = load_config("paper-train"), load_config("paper-val")
    for c in (tr, va):
        assert c.scene.lights.slant_deg == 30 and c.scene.lights.tilts_deg == [0, 120, 240]
        np.testing.assert_allclose(c.scene.lights.crosstalk, np.full((3, 3), 0.04) + 0.88 * np.eye(3))
        assert c.dataset.patches.size == 40 and not c.scene.environment.enabled
        assert c.scene.materials.min_count >= 2
    assert tr.scene.shape.n_shapes == 9 and va.scene.shape.n_shapes == 1
    assert tr.scene.shape.pool_seed != va.scene.shape.pool_seed  # validation shape unseen in training
    assert load_config("paper-test").dataset.storage.store_frames
