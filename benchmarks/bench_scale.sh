#!/usr/bin/env bash
# Issue 21's speed measurements in one run, for a quiet machine (docs/benchmarks.md "Quiet-machine run"):
#   1. per-stage wall breakdown of paper-train frames (one process, one thread),
#   2. the full paper corpus end to end (paper-train + paper-val, 2 workers, warm tables and drjit cache),
#   3. streaming that corpus from disk as lzf and re-encoded as zstd (make_loader, 2 workers),
#   4. 60 paper-train shards side by side with v0.1 (f70fa30, the first shipped model's code).
#   bash benchmarks/bench_scale.sh OUT
set -euo pipefail
Q=${1:?OUT}
root=$(cd "$(dirname "$0")/.." && pwd)
cd "$root"
mkdir -p "$Q"
export OMP_WAIT_POLICY=PASSIVE
stamp() { echo "$1 $(date +%T) load $(cut -d' ' -f1-3 /proc/loadavg)" | tee -a "$Q/log"; }
stamp start
MSPS_THREADS=1 OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_breakdown.py --frames 64 --warmup 24 \
  --clock wall > "$Q/breakdown.txt" 2>&1
stamp breakdown
for p in paper-train paper-val; do
  rm -rf "${Q:?}/$p"
  /usr/bin/time -f "$p wall %e s user %U sys %S" .venv/bin/msps render $p --out "$Q/$p" --workers 2 --quiet 2>> "$Q/log"
  stamp "$p"
done
rm -rf "${Q:?}/paper-train-zstd"
.venv/bin/python benchmarks/bench_loader.py --repack "$Q/paper-train" --to zstd --out "$Q/paper-train-zstd" >> "$Q/log" 2>&1
OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_loader.py --compare "$Q/paper-train" "$Q/paper-train-zstd" \
  --rounds 3 --epochs 1 --workers 2 > "$Q/loader.txt" 2>&1
stamp loader
TRAIN_SHARDS=60 VAL_SHARDS=1 ROUNDS=${ROUNDS:-1} bash benchmarks/bench_corpus.sh f70fa30 HEAD "$Q/v01" 2 >> "$Q/log" 2>&1
stamp v0.1
