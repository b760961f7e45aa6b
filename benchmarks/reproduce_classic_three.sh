#!/usr/bin/env bash
# The seed paper's comparison (Ju et al. 2020, Fig. 4) on toolkit-generated data: the dual-cue network
# against a PS-FCN-design network trained on the SAME three-light corpus with each colour channel read
# as one grey image under its light ("PS-FCN trained on the three channels as three images"), and the
# calibrated Lambertian baseline, on the same unseen test shapes (paper-test: torus, capsule,
# superellipsoid, vase; all five material families, the conductors held out of training).
# The corpus and the dual-cue run are benchmarks/reproduce.sh's (the v0.1 protocol: 100 paper-train
# shards, analytic materials, 28 min of training); the classic network gets the same 28 minutes.
# ~40 min on a 2-core CPU (renders ~6 min, training 28 min, evaluation ~2 min); resumable.
# Usage: bash benchmarks/reproduce_classic_three.sh [DATA_DIR] [RUN_DIR] [DUALCUE_CHECKPOINT]
set -euo pipefail
DATA=${1:-data}
RUNS=${2:-runs}
DUAL=${3:-models/dualcue-cpu-v0.1.pt}   # the paper-protocol dual-cue run (equal steps, docs/history.md)
MSPS=${MSPS:-.venv/bin/msps}
FAMILIES='materials.families=["diffuse","plastic","roughplastic","principled"]'  # roughconductor held out
R="--resume --quiet"
$MSPS render paper-train --out "$DATA/train" --set dataset.n_shards=100 --set "$FAMILIES" --set materials.merl_fraction=0.0 $R
$MSPS render paper-val --out "$DATA/val" --set dataset.n_shards=8 --set "$FAMILIES" --set materials.merl_fraction=0.0 $R
$MSPS render paper-test --out "$DATA/test" --set materials.merl_fraction=0.0 $R

how=""
[ -f "$RUNS/classic-three/last.pt" ] && how="--resume"
$MSPS train classic-three --data "$DATA/train" --val "$DATA/val" --out "$RUNS/classic-three" --threads 2 $how

# one table: every method on the same patches and whole frames, the raw networks (the paper's protocol)
rm -rf "$RUNS/eval-classic-three"
$MSPS eval --data "$DATA/test" --out "$RUNS/eval-classic-three" --steps none \
  --checkpoint "dual-cue=$DUAL" --checkpoint "ps-fcn-three=$RUNS/classic-three/best.pt" --method lambertian
