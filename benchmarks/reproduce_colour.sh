#!/usr/bin/env bash
# Stage 6 (issue 20, colour and appearance): corpora with the full albedo gamut, textures, measured
# blends and random rigs; a warm-started fine-tune of v0.4; the colour, texture, rig and real-capture
# evaluations (docs/history.md "Stage 6").  Resumable: rerun after an interruption and every
# finished shard, training step and report is kept.  Run from the repository root with ../shared/data
# beside the checkout (test meshes, DiLiGenT captures).
# Usage: bash benchmarks/reproduce_colour.sh [DATA_DIR] [RUN_DIR] [MINUTES]
set -euo pipefail
export MSPS_TEST_DATA=${MSPS_TEST_DATA:-../shared/data}  # the unseen-* presets read meshes/ and envmaps/ from it
DATA=${1:-data}
RUNS=${2:-runs}
MINUTES=${3:-65}
MSPS=${MSPS:-.venv/bin/msps}
PY=${PY:-.venv/bin/python}
R="--resume --quiet"

# 1. corpora (procedural shapes only; training-split measured materials only)
$MSPS render paper-train --out "$DATA/blobs-48" --seed 21 --set dataset.n_shards=48 --workers 2 $R
$MSPS render train-grey-30 --out "$DATA/train-grey-30" --set dataset.n_shards=64 --workers 2 $R
$MSPS render train-colour --out "$DATA/train-colour" --workers 2 $R
$MSPS render train-colour-env --out "$DATA/train-colour-env" --workers 2 $R
$MSPS render val --out "$DATA/val" --workers 2 $R
# test sets: the unseen meshes (never training shapes), held-out or analytic materials
for set in unseen-test unseen-test-grey unseen-test-colour unseen-test-texture unseen-test-smooth unseen-test-patches \
           unseen-robust-env \
           unseen-rig-crosstalk unseen-rig-jitter; do
  $MSPS render $set --out "$DATA/$set" --workers 2 $R
done

# 2. stage 6a: fine-tune v0.4 on the colour corpora + the grey and blob corpora of stage 5 (BatchNorm statistics
#    frozen, i.i.d. batches over the whole mix), lr 2e-4 cosine over MINUTES
resume=""; [ -f "$RUNS/colour/last.pt" ] && resume="--resume"
$MSPS train cpu --threads 2 --data "$DATA/train-colour" --data "$DATA/train-colour-env" --data "$DATA/train-grey-30" \
  --data "$DATA/blobs-48" --val "$DATA/val" --init models/dualcue-cpu-v0.4.pt --out "$RUNS/colour" $resume \
  --set train.freeze_bn=true --set train.shuffle_window=0 --set train.cache=true \
  --set train.max_minutes=$MINUTES --set train.lr=2e-4 --set train.val_every=500 --set train.val_max_patches=1500
NEW="$RUNS/colour/last.pt"
# stage 6b (measured, not shipped): a short grey-heavy last stage
resume=""; [ -f "$RUNS/colour-grey/last.pt" ] && resume="--resume"
$MSPS train cpu --data "$DATA/train-grey-30" --data "$DATA/blobs-48" --data "$DATA/train-colour" --val "$DATA/val" \
  --init "$NEW" --out "$RUNS/colour-grey" $resume --set train.freeze_bn=true --set train.shuffle_window=0 \
  --set train.cache=true --set train.max_minutes=13 --set train.lr=1e-4 --set train.val_every=500 \
  --set train.val_max_patches=1500

# 3. evaluation: v0.5 candidate vs v0.4 vs Lambertian on every unseen set, rigs, real captures
MODELS=(--model new="$NEW" --model v0.4=models/dualcue-cpu-v0.4.pt)
$PY benchmarks/unseen_report.py --data "$DATA/unseen-test" --data "$DATA/unseen-test-grey" \
  --data "$DATA/unseen-test-colour" --data "$DATA/unseen-test-texture" "${MODELS[@]}" --out "$RUNS/report-colour"
for set in unseen-robust-env unseen-rig-crosstalk unseen-rig-jitter; do  # all methods in one report each
  [ -f "$RUNS/eval-$set/metrics.json" ] || $MSPS eval --data "$DATA/$set" --checkpoint new="$NEW" \
    --checkpoint v0.4=models/dualcue-cpu-v0.4.pt --method lambertian --out "$RUNS/eval-$set"
done
[ -f "$RUNS/real/results.json" ] || $MSPS bench-real ../shared/data/diligent/*PNG --out "$RUNS/real" \
  --checkpoint new="$NEW" --checkpoint v0.4=models/dualcue-cpu-v0.4.pt

# 4. stage 6d: 6a's diet with train-colour (full gamut, random rig) replaced by train-colour-mixed (a third each
#    achromatic / moderate / full albedo, the paper's rig), from v0.4; 10,000 steps or 75 minutes
$MSPS render train-colour-mixed --out "$DATA/train-colour-mixed" --workers 2 $R
resume=""; [ -f "$RUNS/colour-mixed/last.pt" ] && resume="--resume"
$MSPS train cpu --threads 2 --data "$DATA/train-colour-mixed" --data "$DATA/train-colour-env" --data "$DATA/train-grey-30" \
  --data "$DATA/blobs-48" --val "$DATA/val" --init models/dualcue-cpu-v0.4.pt --out "$RUNS/colour-mixed" $resume \
  --set train.freeze_bn=true --set train.shuffle_window=0 --set train.cache=true --set train.max_minutes=75 \
  --set train.max_steps=10000 --set train.lr=2e-4 --set train.val_every=500 --set train.val_max_patches=1500
D="$RUNS/colour-mixed/last.pt"
[ -f "$RUNS/report-6d/report.json" ] || $PY benchmarks/unseen_report.py --data "$DATA/unseen-test-grey" \
  --data "$DATA/unseen-test-colour" --data "$DATA/unseen-test" --data "$DATA/unseen-test-texture" \
  --data "$DATA/unseen-test-smooth" --data "$DATA/unseen-test-patches" --model 6d="$D" --out "$RUNS/report-6d"
[ -f "$RUNS/real-6d/results.json" ] || $MSPS bench-real ../shared/data/diligent/*PNG --out "$RUNS/real-6d" \
  --checkpoint 6d="$D" --checkpoint 6a="$NEW" --checkpoint v0.4=models/dualcue-cpu-v0.4.pt
for set in unseen-robust-env unseen-rig-crosstalk unseen-rig-jitter; do
  [ -f "$RUNS/eval-6d-$set/metrics.json" ] || $MSPS eval --data "$DATA/$set" --checkpoint 6d="$D" \
    --checkpoint 6a="$NEW" --method lambertian --out "$RUNS/eval-6d-$set"
done

# 5. stage 6e: 6d exactly (diet, init, schedule, steps) plus the chroma cue (net.chroma_cue: each channel over its
#    own patch mean as extra inputs, zero-initialised from v0.4's weights); rule in runs/6e-decision.txt
resume=""; [ -f "$RUNS/chroma/last.pt" ] && resume="--resume"
$MSPS train cpu --threads 2 --data "$DATA/train-colour-mixed" --data "$DATA/train-colour-env" --data "$DATA/train-grey-30" \
  --data "$DATA/blobs-48" --val "$DATA/val" --init models/dualcue-cpu-v0.4.pt --out "$RUNS/chroma" $resume \
  --set net.chroma_cue=true --set train.freeze_bn=true --set train.shuffle_window=0 --set train.cache=true \
  --set train.max_minutes=90 --set train.max_steps=9388 --set train.lr=2e-4 --set train.val_every=500 \
  --set train.val_max_patches=1500
E="$RUNS/chroma/last.pt"
[ -f "$RUNS/report-6e/report.json" ] || $PY benchmarks/unseen_report.py --data "$DATA/unseen-test-grey" \
  --data "$DATA/unseen-test-colour" --data "$DATA/unseen-test" --data "$DATA/unseen-test-texture" \
  --data "$DATA/unseen-test-smooth" --data "$DATA/unseen-test-patches" --model 6e="$E" --out "$RUNS/report-6e"
[ -f "$RUNS/real-6e/results.json" ] || $MSPS bench-real ../shared/data/diligent/*PNG --out "$RUNS/real-6e" \
  --checkpoint 6e="$E" --checkpoint 6a=models/dualcue-cpu-colour.pt --checkpoint v0.4=models/dualcue-cpu-v0.4.pt
[ -f "$RUNS/eval-6e-unseen-robust-env/metrics.json" ] || $MSPS eval --data "$DATA/unseen-robust-env" \
  --checkpoint 6e="$E" --method lambertian --out "$RUNS/eval-6e-unseen-robust-env"
# stage 6e2: 6e continued for another 4,694 steps (lr 1e-4 cosine, seed 1): 1.5x 6d's step budget in all
resume=""; [ -f "$RUNS/chroma-long/last.pt" ] && resume="--resume"
$MSPS train cpu --threads 2 --data "$DATA/train-colour-mixed" --data "$DATA/train-colour-env" --data "$DATA/train-grey-30" \
  --data "$DATA/blobs-48" --val "$DATA/val" --init "$E" --out "$RUNS/chroma-long" $resume \
  --set net.chroma_cue=true --set train.freeze_bn=true --set train.shuffle_window=0 --set train.cache=true \
  --set train.max_minutes=60 --set train.max_steps=4694 --set train.lr=1e-4 --set train.val_every=500 \
  --set train.val_max_patches=1500 --set train.seed=1
E2="$RUNS/chroma-long/last.pt"
[ -f "$RUNS/report-6e2/report.json" ] || $PY benchmarks/unseen_report.py --data "$DATA/unseen-test-grey" \
  --data "$DATA/unseen-test-colour" --data "$DATA/unseen-test" --data "$DATA/unseen-test-texture" \
  --data "$DATA/unseen-test-smooth" --data "$DATA/unseen-test-patches" --model 6e2="$E2" --out "$RUNS/report-6e2"
[ -f "$RUNS/real-6e2/results.json" ] || $MSPS bench-real ../shared/data/diligent/*PNG --out "$RUNS/real-6e2" \
  --checkpoint 6e2="$E2"

# 6. stage 7 (docs/history.md "Stage 7"): object-level albedo-colour self-calibration (--selfcal, no training)
#    for the shipped models, then 7a = 6d's run plus the Lambertian cue (net.lambert_cue); rule in runs/7a-decision.txt
[ -f "$DATA/unseen-robust-env/dataset.json" ] || $MSPS render unseen-robust-env --out "$DATA/unseen-robust-env" --workers 2
[ -f "$RUNS/report-selfcal/report.json" ] || $PY benchmarks/unseen_report.py --selfcal --data "$DATA/unseen-test-grey" \
  --data "$DATA/unseen-test-colour" --data "$DATA/unseen-test-smooth" --data "$DATA/unseen-test-patches" \
  --data "$DATA/unseen-test-texture" --data "$DATA/unseen-test" --model v0.4=models/dualcue-cpu-v0.4.pt \
  --model 6a=models/dualcue-cpu-colour.pt --out "$RUNS/report-selfcal"
resume=""; [ -f "$RUNS/lambert/last.pt" ] && resume="--resume"
$MSPS train cpu --threads 2 --data "$DATA/train-colour-mixed" --data "$DATA/train-colour-env" --data "$DATA/train-grey-30" \
  --data "$DATA/blobs-48" --val "$DATA/val" --init models/dualcue-cpu-v0.4.pt --out "$RUNS/lambert" $resume \
  --set net.lambert_cue=true --set train.freeze_bn=true --set train.shuffle_window=0 --set train.cache=true \
  --set train.max_minutes=100 --set train.max_steps=9388 --set train.lr=2e-4 --set train.val_every=500 \
  --set train.val_max_patches=1500
A7="$RUNS/lambert/last.pt"
[ -f "$RUNS/report-7a/report.json" ] || $PY benchmarks/unseen_report.py --selfcal --data "$DATA/unseen-test-grey" \
  --data "$DATA/unseen-test-colour" --data "$DATA/unseen-test-smooth" --data "$DATA/unseen-test-patches" \
  --data "$DATA/unseen-test-texture" --data "$DATA/unseen-test" --model 7a="$A7" --out "$RUNS/report-7a"
[ -f "$RUNS/real-7a/results.json" ] || $MSPS bench-real ../shared/data/diligent/*PNG --out "$RUNS/real-7a" --steps none --steps selfcal \
  --checkpoint 7a="$A7" --checkpoint v0.4=models/dualcue-cpu-v0.4.pt --checkpoint 6a=models/dualcue-cpu-colour.pt
[ -f "$RUNS/eval-7a-unseen-robust-env/metrics.json" ] || $MSPS eval --data "$DATA/unseen-robust-env" --steps none --steps selfcal \
  --checkpoint 7a="$A7" --checkpoint v0.4=models/dualcue-cpu-v0.4.pt --method lambertian \
  --out "$RUNS/eval-7a-unseen-robust-env"
[ -f "$RUNS/blob-7a.txt" ] || $PY benchmarks/blob_check.py --model 7a="$A7" | tee "$RUNS/blob-7a.txt"

# 7. stage 8 (docs/history.md "Stage 8"): the Lambertian refinement (--refine, no training); thresholds chosen
#    on whole-frame validation sets (procedural shapes, training materials), then every test set scored once
for set in val-frames val-frames-grey val-frames-colour; do
  $MSPS render $set --out "$DATA/$set" --workers 2 $R
done
[ -f "$RUNS/8-valsweep.json" ] || $PY experiments/refine_sweep.py --data "$DATA/val-frames" --data "$DATA/val-frames-grey" \
  --data "$DATA/val-frames-colour" --model models/dualcue-cpu-v0.4.pt --out "$RUNS/8-valsweep.json"
[ -f "$RUNS/report-refine/report.json" ] || $PY benchmarks/unseen_report.py --selfcal --refine \
  --data "$DATA/unseen-test-grey" --data "$DATA/unseen-test-colour" --data "$DATA/unseen-test-smooth" \
  --data "$DATA/unseen-test-patches" --data "$DATA/unseen-test-texture" --data "$DATA/unseen-test" \
  --model v0.4=models/dualcue-cpu-v0.4.pt --model 6a=models/dualcue-cpu-colour.pt --out "$RUNS/report-refine"
[ -f "$RUNS/real-refine/results.json" ] || $MSPS bench-real ../shared/data/diligent/*PNG --out "$RUNS/real-refine" \
  --steps none --steps selfcal --steps refine --steps selfcal+refine --checkpoint v0.4=models/dualcue-cpu-v0.4.pt --checkpoint 6a=models/dualcue-cpu-colour.pt
[ -f "$RUNS/eval-refine-env/metrics.json" ] || $MSPS eval --data "$DATA/unseen-robust-env" --steps none --steps selfcal --steps refine --steps selfcal+refine \
  --checkpoint v0.4=models/dualcue-cpu-v0.4.pt --method lambertian --out "$RUNS/eval-refine-env"
[ -f "$RUNS/assumed-rig/assumed_rig.json" ] || $PY experiments/assumed_rig.py --data "$DATA/unseen-rig-crosstalk" \
  --data "$DATA/unseen-rig-jitter" --model v0.4=models/dualcue-cpu-v0.4.pt --out "$RUNS/assumed-rig"
# stage 7b (measured, not shipped): 7a plus net.cue_gain=10 (rule in runs/7b-decision.txt), 45-minute budget
resume=""; [ -f "$RUNS/lambert-gain/last.pt" ] && resume="--resume"
$MSPS train cpu --threads 2 --data "$DATA/train-colour-mixed" --data "$DATA/train-colour-env" --data "$DATA/train-grey-30" \
  --data "$DATA/blobs-48" --val "$DATA/val" --init models/dualcue-cpu-v0.4.pt --out "$RUNS/lambert-gain" $resume \
  --set net.lambert_cue=true --set net.cue_gain=10 --set train.freeze_bn=true --set train.shuffle_window=0 \
  --set train.cache=true --set train.max_minutes=45 --set train.max_steps=9388 --set train.lr=2e-4 \
  --set train.val_every=500 --set train.val_max_patches=1500
[ -f "$RUNS/report-7b/report.json" ] || $PY benchmarks/unseen_report.py --selfcal --refine --data "$DATA/unseen-test-grey" \
  --data "$DATA/unseen-test-colour" --data "$DATA/unseen-test-smooth" --data "$DATA/unseen-test-patches" \
  --data "$DATA/unseen-test-texture" --data "$DATA/unseen-test" --model 7b="$RUNS/lambert-gain/last.pt" --out "$RUNS/report-7b"

# 8. stage 9 (docs/history.md "Stage 9"): the self-calibration's one-albedo share chosen on the validation
#    frames (rule in runs/9-decision.txt; the stage 8 reports above, re-run with this code, already include it),
#    the bound on a local colour estimate, and the mirror ensemble (rule in runs/9b-decision.txt)
[ -f "$RUNS/9-valsweep.json" ] || $PY experiments/selfcal_share_sweep.py --data "$DATA/val-frames" \
  --data "$DATA/val-frames-grey" --data "$DATA/val-frames-colour" --model models/dualcue-cpu-v0.4.pt --out "$RUNS/9-valsweep.json"
[ -f "$RUNS/chroma-oracle.json" ] || $PY experiments/chroma_oracle.py --data "$DATA/unseen-test-smooth" \
  --data "$DATA/unseen-test-patches" --data "$DATA/unseen-test-texture" --data "$DATA/unseen-test-grey" \
  --model models/dualcue-cpu-v0.4.pt --out "$RUNS/chroma-oracle.json"
[ -f "$RUNS/9b-val/report.json" ] || $PY benchmarks/unseen_report.py --selfcal --mirror --refine --data "$DATA/val-frames" \
  --data "$DATA/val-frames-grey" --data "$DATA/val-frames-colour" --model v0.4=models/dualcue-cpu-v0.4.pt --out "$RUNS/9b-val"
[ -f "$RUNS/report-mirror/report.json" ] || $PY benchmarks/unseen_report.py --selfcal --mirror --refine \
  --data "$DATA/unseen-test-grey" --data "$DATA/unseen-test-colour" --data "$DATA/unseen-test-smooth" \
  --data "$DATA/unseen-test-patches" --data "$DATA/unseen-test-texture" --data "$DATA/unseen-test" \
  --model v0.4=models/dualcue-cpu-v0.4.pt --out "$RUNS/report-mirror"
# stage 9c (measured, not shipped): the mirror as a training augmentation (rule in runs/9c-decision.txt), 30 minutes
$MSPS render train-colour-env --out "$DATA/train-colour-env" --workers 2 $R
resume=""; [ -f "$RUNS/mirror-aug/last.pt" ] && resume="--resume"
$MSPS train cpu --threads 2 --data "$DATA/train-colour-env" --data "$DATA/train-grey-30" --data "$DATA/blobs-48" \
  --val "$DATA/val" --init models/dualcue-cpu-v0.4.pt --out "$RUNS/mirror-aug" $resume --set train.freeze_bn=true \
  --set train.shuffle_window=0 --set train.cache=true --set train.mirror_aug=0.5 --set train.max_minutes=30 \
  --set train.lr=1e-4 --set train.val_every=500 --set train.val_max_patches=1500
[ -f "$RUNS/report-9c/report.json" ] || $PY benchmarks/unseen_report.py --selfcal --refine --data "$DATA/unseen-test-grey" \
  --data "$DATA/unseen-test-colour" --data "$DATA/unseen-test-smooth" --data "$DATA/unseen-test-patches" \
  --data "$DATA/unseen-test-texture" --data "$DATA/unseen-test" --model 9c="$RUNS/mirror-aug/last.pt" --out "$RUNS/report-9c"
[ -f "$RUNS/real-9c/results.json" ] || $MSPS bench-real ../shared/data/diligent/*PNG --out "$RUNS/real-9c" \
  --steps none --steps selfcal --steps refine --steps selfcal+refine --checkpoint 9c="$RUNS/mirror-aug/last.pt"
# stage 10a: the albedo augmentation (rule in runs/10-decision.txt), the 9c control's run with train.albedo_aug=0.5
resume=""; [ -f "$RUNS/albedo-aug/last.pt" ] && resume="--resume"
$MSPS train cpu --threads 2 --data "$DATA/train-colour-env" --data "$DATA/train-grey-30" --data "$DATA/blobs-48" \
  --val "$DATA/val" --init models/dualcue-cpu-v0.4.pt --out "$RUNS/albedo-aug" $resume --set train.freeze_bn=true \
  --set train.shuffle_window=0 --set train.cache=true --set train.albedo_aug=0.5 --set train.max_minutes=30 \
  --set train.lr=1e-4 --set train.val_every=500 --set train.val_max_patches=1500
# stage 10s (selfcal: grey goes first, rule in runs/10s-decision.txt): validation, then the test sets for v0.4, the
# 9c control and 10a under the same code
[ -f "$RUNS/10s-val/report.json" ] || $PY benchmarks/unseen_report.py --selfcal --refine --data "$DATA/val-frames" \
  --data "$DATA/val-frames-grey" --data "$DATA/val-frames-colour" --model v0.4=models/dualcue-cpu-v0.4.pt --out "$RUNS/10s-val"
[ -f "$RUNS/report-10/report.json" ] || $PY benchmarks/unseen_report.py --selfcal --refine --data "$DATA/unseen-test-grey" \
  --data "$DATA/unseen-test-colour" --data "$DATA/unseen-test-smooth" --data "$DATA/unseen-test-patches" \
  --data "$DATA/unseen-test-texture" --data "$DATA/unseen-test" --model v0.4=models/dualcue-cpu-v0.4.pt \
  --model control="$RUNS/mirror-aug-control/last.pt" --model 10a="$RUNS/albedo-aug/last.pt" --out "$RUNS/report-10"
[ -f "$RUNS/real-10a/results.json" ] || $MSPS bench-real ../shared/data/diligent/*PNG --out "$RUNS/real-10a" \
  --steps none --steps selfcal --steps refine --steps selfcal+refine --checkpoint 10a="$RUNS/albedo-aug/last.pt"
# stage 11 (rule in runs/11-decision.txt): 10a with the tint only where it is exact and physical
# (train.albedo_aug_scope=lambertian), fixed in steps (10a's 7,685) so other work cannot change the run;
# 11a at share 0.5, 11b at share 1.0 (the dose: only 38.9 % of the patches are eligible)
for share in 0.5 1.0; do
  out="$RUNS/albedo-lamb"; [ "$share" = "1.0" ] && out="$RUNS/albedo-lamb-1"
  resume=""; [ -f "$out/last.pt" ] && resume="--resume"
  $MSPS train cpu --threads 2 --data "$DATA/train-colour-env" --data "$DATA/train-grey-30" --data "$DATA/blobs-48" \
    --val "$DATA/val" --init models/dualcue-cpu-v0.4.pt --out "$out" $resume --set train.freeze_bn=true \
    --set train.shuffle_window=0 --set train.cache=true --set train.albedo_aug=$share \
    --set train.albedo_aug_scope=lambertian --set train.max_minutes=60 --set train.max_steps=7685 \
    --set train.lr=1e-4 --set train.val_every=500 --set train.val_max_patches=1500
done
# stage 11-12 evaluation of one NAME=CHECKPOINT: the six unseen sets, DiLiGenT, blobs, environment light
evaluate_candidate() {
  local m=$1 n=${1%%=*}
  [ -f "$RUNS/report-11-$n/report.json" ] || $PY benchmarks/unseen_report.py --selfcal --refine \
    --data "$DATA/unseen-test-grey" --data "$DATA/unseen-test-colour" --data "$DATA/unseen-test-smooth" \
    --data "$DATA/unseen-test-patches" --data "$DATA/unseen-test-texture" --data "$DATA/unseen-test" \
    --model "$m" --out "$RUNS/report-11-$n"
  [ -f "$RUNS/real-11-$n/results.json" ] || $MSPS bench-real ../shared/data/diligent/*PNG --out "$RUNS/real-11-$n" \
    --selfcal --refine --checkpoint "$m"
  [ -f "$RUNS/blob-11-$n.txt" ] || $PY benchmarks/blob_check.py --model "$m" > "$RUNS/blob-11-$n.txt"
  [ -f "$RUNS/eval-11-env-$n/metrics.json" ] || $MSPS eval --data "$DATA/unseen-robust-env" --steps none --steps selfcal --steps refine --steps selfcal+refine \
    --checkpoint "$m" --method lambertian --out "$RUNS/eval-11-env-$n"
}
for m in v0.4=models/dualcue-cpu-v0.4.pt 11a="$RUNS/albedo-lamb/last.pt" 11b="$RUNS/albedo-lamb-1/last.pt"; do
  evaluate_candidate "$m"
done
# the field self-calibration probe (a negative result: the unit-norm constraint cannot pin a colour field)
[ -f "$RUNS/field-selfcal.json" ] || $PY experiments/field_selfcal_probe.py --data "$DATA/unseen-test-smooth" \
  --data "$DATA/unseen-test-patches" --out "$RUNS/field-selfcal.json"
# stage 11d and its control (no tint): v0.4 + 4,000 steps of its own last-stage diet (train-grey-30 + blobs-48)
for share in 0.25 0.0; do
  out="$RUNS/albedo-lamb-v04"; scope="--set train.albedo_aug_scope=lambertian"
  [ "$share" = "0.0" ] && { out="$RUNS/albedo-lamb-v04-control"; scope=""; }
  resume=""; [ -f "$out/last.pt" ] && resume="--resume"
  $MSPS train cpu --threads 2 --data "$DATA/train-grey-30" --data "$DATA/blobs-48" --val "$DATA/val" \
    --init models/dualcue-cpu-v0.4.pt --out "$out" $resume --set train.freeze_bn=true --set train.shuffle_window=0 \
    --set train.cache=true --set train.albedo_aug=$share $scope \
    --set train.max_minutes=60 --set train.max_steps=4000 --set train.lr=1e-4 --set train.val_every=500 \
    --set train.val_max_patches=1500
done
for m in 11d="$RUNS/albedo-lamb-v04/last.pt" 11dc="$RUNS/albedo-lamb-v04-control/last.pt"; do
  n=${m%%=*}
  [ -f "$RUNS/report-11-$n/report.json" ] || $PY benchmarks/unseen_report.py --selfcal --refine \
    --data "$DATA/unseen-test-grey" --data "$DATA/unseen-test-colour" --data "$DATA/unseen-test-smooth" \
    --data "$DATA/unseen-test-patches" --data "$DATA/unseen-test-texture" --data "$DATA/unseen-test" \
    --model "$m" --out "$RUNS/report-11-$n"
done

# ---- stage 12 (docs/history.md "Stage 12") ------------------------------------------------------------
# 12a / 12b: stage 11d's recipe at a smaller tint dose (12a: share 0.10, 4,000 steps; 12b: share 0.25, 2,000 steps)
for spec in s12a:0.10:4000 s12b:0.25:2000; do
  IFS=: read -r name share steps <<< "$spec"
  out="$RUNS/$name"; resume=""; [ -f "$out/last.pt" ] && resume="--resume"
  $MSPS train cpu --threads 2 --data "$DATA/train-grey-30" --data "$DATA/blobs-48" --val "$DATA/val" \
    --init models/dualcue-cpu-v0.4.pt --out "$out" $resume --set train.freeze_bn=true --set train.shuffle_window=0 \
    --set train.cache=true --set train.albedo_aug=$share --set train.albedo_aug_scope=lambertian \
    --set train.max_minutes=60 --set train.max_steps=$steps --set train.lr=1e-4 --set train.val_every=500 \
    --set train.val_max_patches=1500
done
for m in 12a="$RUNS/s12a/last.pt" 12b="$RUNS/s12b/last.pt"; do
  evaluate_candidate "$m"
done
# 12a ships as v0.5 (the rule in docs/history.md "Stage 12"): its claims, then the export
[ -f "$RUNS/claims-12a.json" ] || $PY benchmarks/shipped_claims.py --model 12a="$RUNS/s12a/last.pt" --out "$RUNS/claims-12a.json"
[ -f "$RUNS/dualcue-cpu-v0.5.pt" ] || $PY benchmarks/ship_model.py "$RUNS/s12a/last.pt" "$RUNS/dualcue-cpu-v0.5.pt" \
  --init models/dualcue-cpu-v0.4.pt
# the segment-wise self-calibration: its bound with the TRUE regions (test ground truth; chooses nothing),
# thresholds on validation frames only, then the test sets
$PY experiments/segment_oracle.py --data "$DATA/unseen-test-patches" --model models/dualcue-cpu-v0.4.pt
for p in val-frames-texture val-frames-grey val-frames-colour; do
  $MSPS render "$p" --out "$DATA/$p" --workers 2 --resume --quiet
done
[ -f "$RUNS/segment-sweep.json" ] || $PY experiments/segment_sweep.py --data "$DATA/val-frames-texture" \
  --data "$DATA/val-frames-grey" --data "$DATA/val-frames-colour" --model models/dualcue-cpu-v0.4.pt \
  --out "$RUNS/segment-sweep.json"
# tests_and_diligent TAG NAME=CKPT FLAGS...: the six unseen test sets (runs/report-TAG-NAME) and DiLiGenT
# (runs/real-TAG-NAME) with the given prediction flags, each skipped when its output exists
tests_and_diligent() {
  local tag=$1 m=$2; shift 2
  local n=${m%%=*}
  [ -f "$RUNS/report-$tag-$n/report.json" ] || $PY benchmarks/unseen_report.py "$@" \
    --data "$DATA/unseen-test-grey" --data "$DATA/unseen-test-colour" --data "$DATA/unseen-test-smooth" \
    --data "$DATA/unseen-test-patches" --data "$DATA/unseen-test-texture" --data "$DATA/unseen-test" \
    --model "$m" --out "$RUNS/report-$tag-$n"
  [ -f "$RUNS/real-$tag-$n/results.json" ] || $MSPS bench-real ../shared/data/diligent/*PNG \
    --out "$RUNS/real-$tag-$n" "$@" --checkpoint "$m"
}
for m in v04=models/dualcue-cpu-v0.4.pt 12a="$RUNS/s12a/last.pt" 6a=models/dualcue-cpu-colour.pt; do
  tests_and_diligent 12seg "$m" --selfcal --segments --refine
done

# ---- stage 13 (docs/history.md "Stage 13") ------------------------------------------------------------
# the colour read off the network's own normals (--netcal): settings on validation frames only, then the tests
$MSPS render val-frames --out "$DATA/val-frames" --workers 2 --resume --quiet
[ -f "$RUNS/netcal-sweep.json" ] || $PY experiments/netcal_sweep.py --data "$DATA/val-frames" \
  --data "$DATA/val-frames-grey" --data "$DATA/val-frames-colour" --data "$DATA/val-frames-texture" \
  --model models/dualcue-cpu.pt --out "$RUNS/netcal-sweep.json"
for m in v05=models/dualcue-cpu.pt v04=models/dualcue-cpu-v0.4.pt; do
  tests_and_diligent 13 "$m" --selfcal --refine --netcal
done
[ -f "$RUNS/eval-13-env-v05/metrics.json" ] || $MSPS eval --data "$DATA/unseen-robust-env" --steps none --steps selfcal --steps refine --steps selfcal+refine \
  --netcal --checkpoint v05=models/dualcue-cpu.pt --method lambertian --out "$RUNS/eval-13-env-v05"
# 13a: v0.5 + 5,000 steps with grey objects under environment light in the diet
$MSPS render train-grey-env --out "$DATA/train-grey-env" --workers 2 --resume --quiet
$MSPS train cpu --threads 2 --data "$DATA/train-grey-30" --data "$DATA/blobs-48" --data "$DATA/train-grey-env" \
  --val "$DATA/val" --init models/dualcue-cpu.pt --out "$RUNS/s13a" $([ -f "$RUNS/s13a/last.pt" ] && echo --resume) \
  --set train.freeze_bn=true --set train.shuffle_window=0 --set train.cache=true --set train.albedo_aug=0.10 \
  --set train.albedo_aug_scope=lambertian --set train.max_minutes=90 --set train.max_steps=5000 --set train.lr=1e-4 \
  --set train.val_every=500 --set train.val_max_patches=1500
# ... and the rule's measurements (docs/history.md "Stage 13": recorded, not shipped)
tests_and_diligent 13 13a="$RUNS/s13a/last.pt" --selfcal --refine --netcal
$PY benchmarks/blob_check.py --model 13a="$RUNS/s13a/last.pt"
[ -f "$RUNS/eval-13-env-13a/metrics.json" ] || $MSPS eval --data "$DATA/unseen-robust-env" --steps none --steps selfcal --steps refine --steps selfcal+refine \
  --netcal --checkpoint 13a="$RUNS/s13a/last.pt" --method lambertian --out "$RUNS/eval-13-env-13a"
