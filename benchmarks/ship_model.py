"""Export a training run's checkpoint as a shipped model (models/README.md), light range widened by its --init's.

    python benchmarks/ship_model.py runs/s12a/last.pt models/dualcue-cpu.pt --init models/dualcue-cpu-v0.4.pt

Why: a fine-tune records the light geometry of its own data only (before `train.start_run` merged the
--init checkpoint's); the network has seen the init's range too, and `msps predict` warns outside it.
"""
from __future__ import annotations

import argparse
from pathlib import Path


def main(argv=None) -> None:
    from msps_render.dataset.manifest import merge_training_lights
    from msps_render.models.checkpoint import export_checkpoint, load_checkpoint

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src", type=Path)
    ap.add_argument("dst", type=Path)
    ap.add_argument("--init", type=Path, help="the checkpoint the run was warm-started from")
    a = ap.parse_args(argv)
    lights = load_checkpoint(a.src)[2].get("train_lights")
    if a.init:
        lights = merge_training_lights(lights, load_checkpoint(a.init)[2].get("train_lights"))
    export_checkpoint(a.src, a.dst, lights)
    print(f"wrote {a.dst}: train_lights {lights}")


if __name__ == "__main__":
    main()
