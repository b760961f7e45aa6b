#!/usr/bin/env bash
# The full paper corpus (paper-train 232 shards + paper-val 26 shards), rendered end to end by two
# versions of the code back to back on the same machine, wall time each (docs/benchmarks.md).
#
#   bash benchmarks/bench_corpus.sh OLD_REF NEW_REF OUT [WORKERS]
#   e.g. bash benchmarks/bench_corpus.sh c72a7ec HEAD /tmp/corpus 2
#   FRESH_JIT=1 ...   each render starts with an empty drjit kernel disk cache (~/.drjit), as on a
#                     first run; by default the cache is whatever earlier runs left (warm)
#   TRAIN_SHARDS=24 VAL_SHARDS=4 ...   a reduced corpus (the first N shards of each preset), for a
#                     machine too busy for the full one
#   ROUNDS=3 ...      repeat old/new that many times, alternating which goes first (interleaved runs
#                     on a shared machine: compare medians)
#   NEW_SET="dataset.batch_frames=16" ...   a config override for the NEW ref's renders only
#
# Each ref is checked out into OUT/src-<ref> (git worktree) and run with this checkout's venv
# (`PYTHONPATH` = that tree, so presets, brdf/ and the code are the ref's own).  The baked
# Neural-BRDF tables are shared through one MSPS_CACHE_DIR, warmed before timing starts, so
# neither run pays the one-off bake.  Results: OUT/results.tsv (ref, preset, wall seconds, patches,
# jit cache, CPU seconds = user + sys of the render and its workers, round).  CPU seconds are the
# robust number on a machine shared with other jobs (wall time there measures the other jobs too).
set -euo pipefail
old=${1:?OLD_REF}; new=${2:?NEW_REF}; out=${3:?OUT}; workers=${4:-2}
root=$(cd "$(dirname "$0")/.." && pwd)
py="$root/.venv/bin/python"
mkdir -p "$out"
export MSPS_CACHE_DIR="$out/cache" OMP_WAIT_POLICY=PASSIVE
: >> "$out/results.tsv"

src() {  # a worktree of ref $1 under OUT (reused when present)
  local d="$out/src-$(git -C "$root" rev-parse --short "$1")"
  [ -d "$d" ] || git -C "$root" worktree add -q --detach "$d" "$1"
  echo "$d"
}

oldsrc=$(src "$old"); newsrc=$(src "$new")
# Every python runs with its cwd in the tree: `python -m` puts the cwd FIRST on sys.path, ahead
# of PYTHONPATH, so run from another checkout it would import that checkout's msps_render (and
# so would the spawned workers).  Checked here before anything is timed.
for s in "$oldsrc" "$newsrc"; do
  got=$(cd "$s" && PYTHONPATH="$s" "$py" -c 'import msps_render; print(msps_render.__file__)')
  case "$got" in "$s"/*) ;; *) echo "bench_corpus: $s imports $got, not its own code" >&2; exit 1;; esac
done
extra() {  # NEW_SET's override, for the new ref's tree only
  [ -n "${NEW_SET:-}" ] && [ "$1" = "$newsrc" ] && echo "--set $NEW_SET" || true
}

# warm the baked-table cache (and the import caches) with a 1-shard render of each, with the settings
# its timed renders use (NEW_SET too: else the new tree's first round compiles what the old one's loads)
for s in "$oldsrc" "$newsrc"; do
  (cd "$s" && PYTHONPATH="$s" "$py" -m msps_render.cli render paper-train --out "$out/warm" --force \
      --set dataset.n_shards=1 $(extra "$s") --workers 1 > /dev/null)
done
rm -rf "$out/warm"

shards() {  # --set override of a preset's shard count (empty: the full preset)
  case "$1" in paper-train) n=${TRAIN_SHARDS:-};; *) n=${VAL_SHARDS:-};; esac
  [ -n "$n" ] && echo "--set dataset.n_shards=$n" || true
}

for round in $(seq 1 "${ROUNDS:-1}"); do
  order="$oldsrc $newsrc"
  [ $((round % 2)) = 0 ] && order="$newsrc $oldsrc"
  for s in $order; do
    ref=$(git -C "$s" rev-parse --short HEAD)
    for preset in paper-train paper-val; do
      d="$out/$ref/$preset"
      rm -rf "$d"
      home=$HOME
      [ "${FRESH_JIT:-0}" = 1 ] && home=$(mktemp -d)
      t0=$(date +%s.%N)
      # user + sys CPU seconds of the render and every worker it waited for (bash `times`)
      cpu=$(cd "$s" && HOME="$home" PYTHONPATH="$s" bash -c '"$0" -m msps_render.cli render "$1" --out "$2" \
          --workers "$3" $4 > "$5" 2>&1; times' "$py" "$preset" "$d" "$workers" "$(shards "$preset") $(extra "$s")" \
          "$out/$ref-$preset.log" | awk 'NR==2 {print}')
      t1=$(date +%s.%N)
      cpus=$(echo "$cpu" | awk '{ s = 0; for (i = 1; i <= 2; i++) { split($i, a, "m"); sub("s", "", a[2]); s += a[1] * 60 + a[2] } printf "%.1f", s }')
      n=$("$py" -c "import json,sys; print(json.load(open(sys.argv[1]))['n_patches'])" "$d/dataset.json")
      printf '%s\t%s\t%.1f\t%s\t%s\t%s\t%s\n' "$ref" "$preset" "$(echo "$t1 - $t0" | bc)" "$n" \
          "$([ "${FRESH_JIT:-0}" = 1 ] && echo fresh-jit-cache || echo warm-jit-cache)" "$cpus" "$round" \
          | tee -a "$out/results.tsv"
    done
  done
done
