"""The reference dual-cue network (Ju et al. 2020), its losses, the Lambertian baseline,
training, evaluation and prediction.  `baseline` is numpy-only; everything else needs torch
and is imported lazily, so `import msps_render.models` stays light."""
