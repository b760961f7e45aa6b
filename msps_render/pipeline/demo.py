"""`msps demo`: the tiny end-to-end run the README starts with."""
from __future__ import annotations

from pathlib import Path

from msps_render.dataset.verify import verify_dataset
from msps_render.errors import InputError
from msps_render.pipeline.config import load_config
from msps_render.pipeline.preview import preview_dataset
from msps_render.pipeline.run import render_dataset


def run_demo(out_dir: str | Path, workers: int = 1) -> Path:
    """Render the `demo` preset into `out_dir/dataset`, verify it, write `out_dir/preview.png`."""
    out = Path(out_dir)
    cfg = load_config("demo")
    render_dataset(cfg, out / "dataset", workers=workers, force=True)
    bad = verify_dataset(out / "dataset")
    if bad:
        raise InputError(out / "dataset", f"demo dataset failed verification: {bad}")
    return preview_dataset(out / "dataset", out / "preview.png")
