#!/usr/bin/env bash
# Rebuild the shipped model, models/dualcue-cpu.pt (v0.5), from nothing: the corpora, the six
# warm-started training stages, the export, then the checks of its claims (docs/reproducing.md).
# Resumable: rerun the same command after an interruption; finished shards, training steps and
# reports are kept.  Run from the repository root after `bash scripts/setup.sh`; the checks need the
# third-party test meshes (MSPS_TEST_DATA, default ../shared/data).
# Usage: bash scripts/rebuild_model.sh [DATA_DIR] [RUN_DIR]
#        bash scripts/rebuild_model.sh classic [DATA_DIR] [RUN_DIR]   # models/classic-cpu.pt instead (~4 h)
set -euo pipefail
CLASSIC=0
if [ "${1:-}" = classic ]; then CLASSIC=1; shift; fi
DATA=${1:-data}
RUNS=${2:-runs}
MSPS=${MSPS:-.venv/bin/msps}
PY=${PY:-.venv/bin/python}
export MSPS_TEST_DATA=${MSPS_TEST_DATA:-../shared/data}
R="--workers 2 --resume --quiet"

if [ "$CLASSIC" = 1 ]; then
  # The classic (any-light) network, trained on msps renders only (docs/history.md stages 15-17):
  # classic-train (240 shards, 64 white hemisphere lights per frame; ~5-18 min on 2 cores), classic-val,
  # the 30-minute classic-cpu run, then the same run resumed with its budget raised to 120 minutes (the
  # cosine schedule picks up at 30/120), then to 220 (at 120/220; the epoch cap raised so that it runs
  # its time), its best.pt exported, then scored on DiLiGenT with all 96 lights.  A finished part resumed
  # again trains nothing.
  $MSPS render classic-train --out "$DATA/classic-train" $R
  $MSPS render classic-val --out "$DATA/classic-val" $R
  if [ ! -f "$RUNS/classic-cpu/.first-30-min-done" ]; then
    how=""
    [ -f "$RUNS/classic-cpu/last.pt" ] && how="--resume"
    OMP_WAIT_POLICY=PASSIVE $MSPS train classic-cpu --data "$DATA/classic-train" --val "$DATA/classic-val" \
      --out "$RUNS/classic-cpu" --threads 2 $how
    touch "$RUNS/classic-cpu/.first-30-min-done"
  fi
  OMP_WAIT_POLICY=PASSIVE $MSPS train classic-cpu --data "$DATA/classic-train" --val "$DATA/classic-val" \
    --out "$RUNS/classic-cpu" --threads 2 --resume --set train.max_minutes=120
  OMP_WAIT_POLICY=PASSIVE $MSPS train classic-cpu --data "$DATA/classic-train" --val "$DATA/classic-val" \
    --out "$RUNS/classic-cpu" --threads 2 --resume --set train.max_minutes=220 --set train.epochs=100
  [ -f "$RUNS/classic-cpu.pt" ] || $PY -m msps_render.models.classic export "$RUNS/classic-cpu/best.pt" "$RUNS/classic-cpu.pt"
  D=$MSPS_TEST_DATA/diligent
  rm -rf "$RUNS/classic-diligent"
  $MSPS bench-real "$D/ballPNG" "$D/catPNG" "$D/gobletPNG" "$D/pot1PNG" --lights all --out "$RUNS/classic-diligent" \
    --checkpoint rebuilt="$RUNS/classic-cpu.pt" --checkpoint shipped=models/classic-cpu.pt
  exit 0
fi

# 1. training corpora: procedural shapes, training-split measured materials (never a test mesh or a
#    held-out material: tests/test_presets.py), and the validation corpus
$MSPS render train-robust --out "$DATA/train-robust" $R
$MSPS render train-achromatic --out "$DATA/train-achromatic" $R
$MSPS render train-grey --out "$DATA/train-grey" $R
$MSPS render train --out "$DATA/train" $R
$MSPS render train-grey-30 --out "$DATA/train-grey-30" $R
$MSPS render train-grey-30 --out "$DATA/train-grey-30-64" --set dataset.n_shards=64 $R
$MSPS render paper-train --out "$DATA/blobs-48" --seed 21 --set dataset.n_shards=48 $R
$MSPS render val --out "$DATA/val" $R

# 2. training: each stage warm-starts from the one before (NAME INIT msps-train-arguments...)
stage() {
  local name=$1 init=$2; shift 2
  local how=""
  [ -n "$init" ] && how="--init $init"
  [ -f "$RUNS/$name/last.pt" ] && how="--resume"
  OMP_WAIT_POLICY=PASSIVE $MSPS train cpu --val "$DATA/val" --out "$RUNS/$name" --threads 2 $how "$@"
}
FROZEN=(--set train.freeze_bn=true --set train.shuffle_window=0 --set train.cache=true)
stage s1-robust "" --data "$DATA/train-robust" \
  --set train.max_steps=5000 --set train.val_every=500 --set train.val_max_patches=1500
stage s2-long "$RUNS/s1-robust/last.pt" --data "$DATA/train-robust" --data "$DATA/train-achromatic" \
  --set train.max_steps=100000 --set train.max_minutes=120 --set train.lr=5e-4 \
  --set train.val_every=500 --set train.val_max_patches=3000
stage s3-grey "$RUNS/s2-long/best.pt" --data "$DATA/train-robust" --data "$DATA/train-achromatic" \
  --data "$DATA/train-grey" --set train.max_minutes=95 --set train.max_steps=5000 --set train.lr=3e-4
stage s5a-mix "$RUNS/s3-grey/last.pt" --data "$DATA/train" --data "$DATA/train-grey-30" --data "$DATA/blobs-48" \
  "${FROZEN[@]}" --set train.max_minutes=80 --set train.max_steps=4500 --set train.lr=2e-4
stage s5b-grey "$RUNS/s5a-mix/last.pt" --data "$DATA/train-grey-30" --data "$DATA/blobs-48" \
  "${FROZEN[@]}" --set train.max_minutes=45 --set train.lr=1e-4                      # last.pt = v0.4
stage s12a-tint "$RUNS/s5b-grey/last.pt" --data "$DATA/train-grey-30-64" --data "$DATA/blobs-48" \
  "${FROZEN[@]}" --set train.albedo_aug=0.10 --set train.albedo_aug_scope=lambertian \
  --set train.max_minutes=60 --set train.max_steps=4000 --set train.lr=1e-4 \
  --set train.val_every=500 --set train.val_max_patches=1500                          # last.pt = v0.5

# 3. export: training state dropped, the light range of the whole chain kept
[ -f "$RUNS/dualcue-cpu.pt" ] || $PY benchmarks/ship_model.py "$RUNS/s12a-tint/last.pt" "$RUNS/dualcue-cpu.pt" \
  --init "$RUNS/s5b-grey/last.pt"

# 4. the claims, measured for the rebuilt and the shipped model on the same renders
for set in unseen-test unseen-test-grey unseen-test-colour unseen-test-texture; do
  $MSPS render $set --out "$DATA/$set" $R
done
for m in rebuilt="$RUNS/dualcue-cpu.pt" shipped=models/dualcue-cpu.pt; do
  n=${m%%=*}
  [ -f "$RUNS/claims-$n.json" ] || $PY benchmarks/shipped_claims.py --model "$m" --data-root "$DATA" \
    --out "$RUNS/claims-$n.json"
done
