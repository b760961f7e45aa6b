#!/usr/bin/env bash
# Train on corpora that teach real objects and test on objects training never saw
# (docs/reproducing.md, "Unseen objects"). Resumable: rerun the same command after an
# interruption and every finished render, training step and evaluation is kept.
# Run from the repository root with ../shared/data beside the checkout (test meshes, HDR map).
# Usage: bash benchmarks/reproduce_unseen.sh [DATA_DIR] [RUN_DIR] [STEPS]
set -euo pipefail
DATA=${1:-data}
RUNS=${2:-runs}
STEPS=${3:-6000}
MSPS=${MSPS:-.venv/bin/msps}
PY=${PY:-.venv/bin/python}
R="--resume --quiet"

# 1. corpora: training (darkroom, robust), validation, unseen-object test sets
$MSPS render train --out "$DATA/train" --workers 2 $R
$MSPS render val --out "$DATA/val" --workers 2 $R
$MSPS render train-robust --out "$DATA/train-robust" --workers 2 $R
for set in unseen-test unseen-test-grey unseen-robust-env unseen-robust-slant; do
  $MSPS render $set --out "$DATA/$set" --workers 2 $R
done

# 2. training: dual-cue, its two single-cue ablations and the robust-trained dual net, equal steps,
#    one thread each (four runs share the two cores); cosine decay over STEPS; best val checkpoint kept
train() {  # name corpus [extra --set ...]
  local name=$1 corpus=$2; shift 2
  local resume=""; [ -f "$RUNS/$name/last.pt" ] && resume="--resume"
  $MSPS train cpu --data "$DATA/$corpus" --val "$DATA/val" --out "$RUNS/$name" --threads 1 $resume \
    --set train.max_steps=$STEPS --set train.val_every=500 --set train.val_max_patches=1500 "$@"
}
train dual train &
train scn train --set net.mode=scn &
train pcn train --set net.mode=pcn &
train dual-robust train-robust &
wait

# 3. evaluation: per-object tables and normal maps, robustness (MAE and alpha)
$PY benchmarks/unseen_report.py --data "$DATA/unseen-test" --data "$DATA/unseen-test-grey" \
  --model dual="$RUNS/dual/best.pt" --model scn="$RUNS/scn/best.pt" --model pcn="$RUNS/pcn/best.pt" \
  --model dual-robust="$RUNS/dual-robust/best.pt" --out "$RUNS/report-unseen"
for set in unseen-robust-env unseen-robust-slant; do
  for m in dual dual-robust; do
    $MSPS eval --data "$DATA/$set" --checkpoint "$RUNS/$m/best.pt" --out "$RUNS/eval-$set-$m"
  done
  $MSPS eval --data "$DATA/$set" --method lambertian --out "$RUNS/eval-$set-lambertian"
done
