"""The blob regression number for several checkpoints: the frames of
`tests/test_models.py::test_shipped_checkpoint_predicts_a_rendered_object` (96², analytic diffuse /
plastic / roughplastic blobs, seeds 100-102), MAE per method and the Lambertian baseline.

    python benchmarks/blob_check.py --model new=runs/x/last.pt --model v0.4=models/dualcue-cpu-v0.4.pt
"""
from __future__ import annotations

import argparse

import numpy as np


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", action="append", required=True, help="NAME=PATH")
    args = ap.parse_args(argv)
    from msps_render.calibration import Rig
    from msps_render.models.baseline import lambertian_ps
    from msps_render.models.checkpoint import load_checkpoint
    from msps_render.models.metrics import angular_error_deg
    from msps_render.models.predict import predict_image
    from msps_render.render import render_frame
    from msps_render.render.variant import resolve_variant
    from msps_render.scene.sample import SceneConfig, sample_scene

    scfg = SceneConfig.model_validate({"camera": {"width": 96, "height": 96},
                                       "materials": {"families": ["diffuse", "plastic", "roughplastic"]}})
    variant = resolve_variant("rgb")
    frames = [render_frame(sample_scene(scfg, np.random.default_rng(100 + s)), variant) for s in range(3)]
    models = {name: load_checkpoint(path, expect_preset="cpu")[0]
              for name, path in (m.split("=", 1) for m in args.model)}
    for name, model in models.items():
        e = [angular_error_deg(predict_image(model, f.image, f.mask, rig=Rig.of(f).matrix)[f.mask], f.normal[f.mask]).mean() for f in frames]
        print(f"{name} {np.mean(e):.2f}")
    b = [angular_error_deg(lambertian_ps(f.image, f.light_dirs, f.crosstalk)[f.mask], f.normal[f.mask]).mean()
         for f in frames]
    print(f"lambertian {np.mean(b):.2f}")


if __name__ == "__main__":
    main()
