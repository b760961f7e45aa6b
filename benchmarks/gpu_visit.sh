#!/usr/bin/env bash
# One visit to an offline GPU machine (docs/scaling.md "Running on a GPU"): install msps's missing
# dependencies from a carried wheelhouse, verify CUDA rendering, measure rendering and training, and train
# the `gpu` and `cpu` presets on corpora rendered there.  Every phase is time-boxed and logs to $OUT;
# a failing phase does not stop the next.  Prepare here first (what travels, checkout included, must stay
# under 64 MiB: the checkout ~19.5 MB, .gpu 2.5 MB, this wheelhouse 37.5 MB; 2026-12-05):
#   .venv/bin/python scripts/build_wheelhouse.py --out .whl --python 3.12 --no-hdf5plugin --no-msps \
#       --variants cuda_ad_rgb,scalar_rgb --have +kornia-rs,colour-science
#   .venv/bin/python benchmarks/gpu_check.py reference --out .gpu/ref
# RGB only: with cuda_ad_spectral (+ its 8.9 MB srgb.coeff) and colour-science (9.1 MB) the wheels are 62 MB,
# too many to carry, so the spectral checks (narrow-band test, gpu_check's spectral-train) fail here;
# every phase of issue 45 item 3 is RGB (renders and training run without colour-science: tested here).
# then run (carrying .whl and .gpu):  bash benchmarks/gpu_visit.sh   (OUT=dir; BUDGET_S=seconds;
# BATCH=frames per launch of the batched phases, 16; STEADY_S=130 adds >= 2-minute renders at 1, 4, 16 workers)
# PHASES=a,b,...: only these (default all; none: install and probe only): pytest bench-train gpu_check render
# steady corpora breakdown thr fit
# (install and probe always run; thr and fit render the corpora they train on).  No phase runs past BUDGET_S:
# one that would end past it is cut to the budget's end (logged "clamped"), or skipped ("skip" in phases.tsv)
# when under 30 s are left.  Issue 45 item 3 does not fit one session's 15 device-minutes (a start costs 1-2);
# one command of <= 600 s per session, in this order (each on a bare machine), measured sizes in brackets:
#   1. PHASES=steady,bench-train STEADY_S=125   frames/s over >= 2 min at 1, 4, 16 workers; the training step
#                                                alone (install ~30 s + 3 x ~140 s + <= 120 s)
#   2. PHASES=fit                                the gpu model and its cpu control, checkpoints back (corpora
#                                                ~250 s, then training in what is left, 3.5 min at most)
#   3. PHASES=gpu_check,thr                      CUDA against LLVM; training throughput, 6 runs of <= 60 s
#   4. PHASES=pytest,render,breakdown            tests on CUDA, batched launches, per-frame breakdowns
set -u
cd "$(dirname "$0")/.."
GROUPS_KNOWN=",pytest,bench-train,gpu_check,render,steady,corpora,breakdown,thr,fit,none,"
PHASES=${PHASES:-}
for g in ${PHASES//,/ }; do  # a misspelt phase would silently run nothing: one line, before any work
  [[ "$GROUPS_KNOWN" == *",$g,"* ]] || { echo "error: PHASES: unknown phase '$g' (known: ${GROUPS_KNOWN:1:-1})" >&2; exit 1; }
done
OUT=${OUT:-/tmp/gpu-out}; mkdir -p "$OUT"
T0=$(date +%s); BUDGET_S=${BUDGET_S:-560}; S=${SCALE:-1}  # SCALE=8: a CPU dry run of the script
W=${WORK:-/tmp/msps-gpu}; mkdir -p $W  # corpora and runs (WORK=dir: elsewhere)
LOG=$OUT/log.txt
export PYTHONUNBUFFERED=1 PYTHONPATH=/tmp/site:$PWD
MSPS="python3 -m msps_render.cli"
left() { echo $(( BUDGET_S - ($(date +%s) - T0) )); }
want() {  # want GROUP: is this group of phases in PHASES (default: all)?
  [ -z "${PHASES:-}" ] || [[ ",$PHASES," == *",$1,"* ]]
}
phase() {  # phase NAME TIMEOUT_S CMD...: run, log, record rc and seconds in phases.tsv (within the budget)
  local name=$1 t=$2; shift 2
  local a=$(date +%s.%N) l=$(left)
  if [ "$l" -lt 30 ]; then
    printf '%s\tskip\t0\n' "$name" | tee -a $OUT/phases.tsv | tee -a $LOG; return
  fi
  [ "$t" -gt $((l - 10)) ] && { t=$((l - 10)); echo "=== $name clamped to ${t}s by BUDGET_S" | tee -a $LOG; }
  echo "=== $name (timeout ${t}s, ${l}s left) $(date -u +%T)" | tee -a $LOG
  timeout -k 5 "$t" "$@" >>$LOG 2>&1; local rc=$?
  local dt=$(python3 -c "print(round($(date +%s.%N)-$a,2))")
  printf '%s\t%s\t%s\n' "$name" "$rc" "$dt" | tee -a $OUT/phases.tsv | tee -a $LOG
}
smi_start() { nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv,noheader,nounits -lms 200 \
  > $W/smi-$1.csv 2>/dev/null & SMI=$!; }
smi_stop() { kill $SMI 2>/dev/null; wait $SMI 2>/dev/null
  python3 - "$W/smi-$1.csv" "$1" >>$OUT/phases.tsv <<'EOF'
import sys
rows=[l.split(',') for l in open(sys.argv[1]) if l.count(',')==2]
u=[float(r[1]) for r in rows]; m=[float(r[2]) for r in rows]
print(f"gpu-busy:{sys.argv[2]}\t{(sum(u)/len(u) if u else -1):.1f}%\tmax_mem_MiB={max(m) if m else -1:.0f}\tsamples={len(u)}")
EOF
}

# 0. install, what the machine is
phase install 90 python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site ${WHL:-.whl}/*.whl
# kornia imports kornia_rs (5.3 MB, image file I/O only) at import time; msps uses kornia's SSIM alone, so a
# wheelhouse built with --have ...,kornia-rs (to fit a 64 MiB transfer) gets an empty stand-in here.
python3 -c "import kornia_rs" 2>/dev/null || { mkdir -p /tmp/site/kornia_rs; : > /tmp/site/kornia_rs/__init__.py; : > /tmp/site/kornia_rs/io.py; }
{ nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv; python3 -c "import torch,sys;print('python',sys.version.split()[0],'torch',torch.__version__,'cuda',torch.version.cuda)";
  python3 -c "import mitsuba,drjit;print('mitsuba',mitsuba.__version__,mitsuba.variants(),'drjit',drjit.__version__)"; nproc; free -g | head -2; } >>$LOG 2>&1
phase probe 90 python3 -c "
import msps_render.render.variant as V
for v in ('cuda_ad_rgb','cuda_ad_spectral','scalar_rgb','llvm_ad_rgb'): print(v, V.probe_variant(v))
print('resolved', V.resolve_variant('rgb'), V.resolve_variant('spectral'))"

complete() { python3 -c "import json,sys;sys.exit(0 if json.load(open('$W/data/$1/dataset.json')).get('complete') else 1)" 2>/dev/null; }
# 1. tests on the GPU (CUDA variant resolved; closed-form physics, baseline, GPU tests, accel)
if want pytest; then
phase pytest 110 env MSPS_TEST_JIT=${MSPS_TEST_JIT:-cuda} python3 -m pytest -q -p no:cacheprovider -rA \
  tests/test_gpu.py tests/test_accel.py tests/test_render_physics.py tests/test_baseline.py \
  tests/test_batch.py::test_each_batched_frame_matches_the_lambertian_closed_form \
  tests/test_batch.py::test_point_lights_batch_to_the_closed_form \
  tests/test_batch.py::test_narrowband_frames_batch_to_the_closed_form_of_their_own_leds 2>/dev/null \
  || true
grep -E "^(PASSED|FAILED|SKIPPED|ERROR)|passed|failed" $LOG | tail -60 > $OUT/pytest.txt
fi

# 1b. the training step alone on the device (no loader): the model's ceiling, and how long cuDNN's first
# steps take (the 2026-12-04 visit saw `msps train` record nothing in 35 s; this separates model from data)
BT_AFTER=""; [ -n "${STEADY_S:-}" ] && want steady && BT_AFTER=1  # the steady renders first: they need >= 2 min
want bench-train && [ -z "$BT_AFTER" ] && phase bench-train 120 python3 benchmarks/bench_train.py --device cuda --batch 24,256 --presets cpu,gpu,paper --steps 30

# 2. CUDA vs carried LLVM renders
want gpu_check && phase gpu_check 90 python3 benchmarks/gpu_check.py check --ref .gpu/ref --out $W/gpu_check.json

# 3. rendering: paper-train with 1, 4, 16 workers (frames/s, GPU busy), then the training corpora
render() {  # render NAME PRESET WORKERS SHARDS TIMEOUT [extra --set ...]
  local name=$1 preset=$2 w=$3 n=$4 t=$5; shift 5
  smi_start $name
  n=$(( (n + S - 1) / S ))
  phase render:$name:w$w:shards$n "$t" $MSPS render $preset --out $W/data/$name --workers $w --quiet \
    --set dataset.n_shards=$n --set dataset.storage.compression=lzf "$@"
  smi_stop $name
}
if want render; then
render pt-w1 paper-train 1 4 45                       # 32 frames
render pt-w4 paper-train 4 16 45                      # 128 frames
# frames in batches (issue 45): B paper-train frames per launch; a launch never spans shards, so shards of
# B frames (8 shards of 16: the same 128 frames as pt-w4)
render pt-b16-w4 paper-train 4 8 45 --set dataset.batch_frames=${BATCH:-16} --set dataset.frames_per_shard=${BATCH:-16}
fi
if [ -n "${STEADY_S:-}" ] && want steady; then  # STEADY_S=130: steady-state frames/s, each worker count rendering that long
  for w in 1 4 16; do  # 4,000 shards is more than any of them finishes; coarse patches keep the disk small
    steady_start=$(date +%s.%N)
    render steady-w$w paper-train $w 4000 $STEADY_S --set dataset.batch_frames=${BATCH:-16} \
      --set dataset.frames_per_shard=${BATCH:-16} --set dataset.patches.stride=40
    python3 - "$W/data/steady-w$w" "$steady_start" >>$OUT/phases.tsv <<'PY'
import json, sys, time
m = json.load(open(f"{sys.argv[1]}/dataset.json"))
n = sum(s.get("n_frames", 8) for s in m["shards"].values())
dt = time.time() - float(sys.argv[2])
print(f"steady:{sys.argv[1].rsplit('-', 1)[1]}\tframes={n}\tseconds={dt:.0f}\tframes_per_s={n / dt:.1f}")
PY
  done
fi
want bench-train && [ -n "$BT_AFTER" ] && phase bench-train 120 python3 benchmarks/bench_train.py \
  --device cuda --batch 24,256 --presets cpu,gpu,paper --steps 30
if want corpora || want thr || want fit; then
render blobs paper-train 16 64 60 --seed 21           # 512 frames (also a training corpus)
render val val 16 6 30                                # 48 frames
fi
if want corpora || want fit; then
render train train 16 48 70                           # 384 frames, 256x256, 32 spp
render grey30 train-grey-30 16 40 60                  # 320 frames
fi
if want breakdown; then
phase breakdown 45 env MSPS_THREADS=1 python3 benchmarks/bench_breakdown.py --preset paper-train --frames 48 --warmup 16
phase breakdown-b16 45 env MSPS_THREADS=1 python3 benchmarks/bench_breakdown.py --preset paper-train --frames 64 \
  --warmup 32 --set dataset.batch_frames=${BATCH:-16} --set dataset.frames_per_shard=${BATCH:-16}
fi
THR=""; for c in blobs pt-w4 pt-w1; do complete $c && { THR=$c; break; }; done
echo "throughput corpus: $THR" | tee -a $LOG

# 4. training throughput (patches/s from metrics.jsonl; 2nd window, after cuDNN autotuning)
thr() {  # thr NAME PRESET STEPS [--set ...]
  local name=$1 preset=$2 steps=$(( $3 / S )); shift 3
  smi_start thr-$name
  phase train-thr:$name 60 $MSPS train $preset --data $W/data/$THR --val $W/data/val --out $W/thr/$name \
    --set train.max_steps=$steps --set train.val_every=$((steps/2)) --set train.val_max_patches=256 \
    --set train.cache=true --set train.num_workers=0 --set train.shuffle_window=0 "$@"
  smi_stop thr-$name
  python3 -c "import json;r=[json.loads(l) for l in open('$W/thr/$name/metrics.jsonl')];print('throughput:$name',r[-1]['patches_per_s'])" >>$OUT/phases.tsv 2>>$LOG \
    || printf 'throughput:%s\tnone\n' "$name" >>$OUT/phases.tsv
}
if want thr; then
thr cpu-b24 cpu 400 --set train.batch_size=24
thr cpu-b256 cpu 200 --set train.batch_size=256
thr gpu-b64 gpu 200
thr paper-b24 paper 120 --set train.batch_size=24
thr paper-b128 paper 80 --set train.batch_size=128
thr paper-b128-fp32 paper 80 --set train.batch_size=128 --set train.precision=fp32 --set train.channels_last=false
fi

# 5. the larger network and a cpu-preset control, trained at once on the same corpora and minutes
if want fit && [ "$(left)" -lt 130 ]; then
  printf 'fit\tskip\t0\n' | tee -a $OUT/phases.tsv | tee -a $LOG
elif want fit; then
CORP=""; for c in train grey30 blobs; do complete $c && CORP="$CORP --data $W/data/$c"; done
[ -z "$CORP" ] && CORP="--data $W/data/$THR"
MIN=$(python3 -c "print(round(max(1.0, min(3.5, ($(left) - 45) / 60)), 2))")
echo "training on:$CORP for $MIN min" | tee -a $LOG
smi_start fit
for p in gpu cpu; do
  timeout -k 5 $(python3 -c "print(int($MIN*60+60))") $MSPS train $p $CORP --val $W/data/val --out $W/fit/$p \
    --set train.max_minutes=$MIN --set train.batch_size=64 --set train.albedo_aug=0.1 \
    --set train.albedo_aug_scope=lambertian --set train.shuffle_window=0 --set train.cache=true \
    --set train.num_workers=4 --set train.val_max_patches=1024 >$W/fit-$p.log 2>&1 &
done
wait; smi_stop fit
tail -3 $W/fit-gpu.log $W/fit-cpu.log >>$LOG
for p in gpu cpu; do
  python3 benchmarks/ship_model.py $W/fit/$p/best.pt $OUT/$p-gpu-trained.pt >>$LOG 2>&1
  cp $W/fit/$p/metrics.jsonl $W/fit-$p-metrics.jsonl 2>/dev/null
done
fi

# results: small files only (at most 8 come back)
cp $W/gpu_check.json $OUT/ 2>/dev/null
(cd $W && tar czf $OUT/extra.tgz smi-*.csv fit-*.log fit-*-metrics.jsonl thr/*/metrics.jsonl \
   data/*/card.json data/*/dataset.json 2>/dev/null)
echo "total $(( $(date +%s) - T0 )) s" | tee -a $LOG
