#!/usr/bin/env bash
# Reproduce the dual-cue vs ablations vs Lambertian comparison on toolkit-generated data
# (docs/history.md). ~85 min on a 2-core CPU: ~5 min rendering, 40 min of training
# (the three models train concurrently, one thread each), ~30 min for the equal-steps
# dual-cue run, ~3 min evaluation.
# Usage: bash benchmarks/reproduce.sh [DATA_DIR] [RUN_DIR]
set -euo pipefail
DATA=${1:-data}
RUNS=${2:-runs}
MSPS=${MSPS:-.venv/bin/msps}
FAMILIES='materials.families=["diffuse","plastic","roughplastic","principled"]'  # roughconductor held out

# --resume: finish (or skip) what an earlier run of this script rendered
R="--resume --quiet"
$MSPS render paper-train --out "$DATA/train" --set dataset.n_shards=100 --set "$FAMILIES" --set materials.merl_fraction=0.0 $R
$MSPS render paper-val --out "$DATA/val" --set dataset.n_shards=8 --set "$FAMILIES" --set materials.merl_fraction=0.0 $R
$MSPS render paper-test --out "$DATA/test" --set materials.merl_fraction=0.0 $R   # unseen shapes, all families
$MSPS render robust-env --out "$DATA/robust-env" --set dataset.n_shards=2 --set "$FAMILIES" $R
$MSPS render robust-slant --out "$DATA/robust-slant" --set dataset.n_shards=2 --set "$FAMILIES" $R

for mode in dual scn pcn; do
  $MSPS train cpu --data "$DATA/train" --val "$DATA/val" --out "$RUNS/cpu-$mode" --threads 1 \
    --set net.mode=$mode --set train.max_minutes=40 --set train.val_every=300 --set train.val_max_patches=1500 &
done
wait
# the dual net again, for as many steps as the SCN-only run made (equal-steps comparison)
STEPS=$(python3 -c "import json; print(json.loads(open('$RUNS/cpu-scn/metrics.jsonl').read().splitlines()[-1])['step'])")
$MSPS train cpu --data "$DATA/train" --val "$DATA/val" --out "$RUNS/cpu-dual-steps" --threads 2 \
  --set train.max_steps=$STEPS --set train.val_every=300 --set train.val_max_patches=1500

for mode in dual-steps dual scn pcn; do
  $MSPS eval --data "$DATA/test" --checkpoint "$RUNS/cpu-$mode/best.pt" --out "$RUNS/eval-$mode"
done
$MSPS eval --data "$DATA/test" --method lambertian --out "$RUNS/eval-lambertian"
for set in robust-env robust-slant; do
  $MSPS eval --data "$DATA/$set" --checkpoint "$RUNS/cpu-dual-steps/best.pt" --out "$RUNS/eval-$set-dual" --max-patches 1500
  $MSPS eval --data "$DATA/$set" --method lambertian --out "$RUNS/eval-$set-lambertian" --max-patches 1500
done
