#!/usr/bin/env bash
# World-model variants from scratch on one training set, judged on the fixed benchmark store (issue 41).
#
#   lab/wm-variants/wm_variants.sh [EPOCHS]         # EPOCHS: passes over the training set for every variant (default 4,
#                                           # the mini preset's)
#
# Every step is resumable (a finished one leaves NAME.done; NAME.seconds sums its attempts), so re-running
# after an interruption goes on where it stopped. Two processes at a time with one thread each:
#   1. data/wm_bench: the benchmark store (scripts/wm_benchmark_store.py, seeds 9000-9031)
#   2. data/wm41: the shipped TinyWAM's data recipe with counterfactual branches from the start:
#      100 expert (seeds 1000-1099) + 100 noisy-expert (2000-2099) episodes, 150 pink-noise (3000-3149),
#      50 on-policy parents of checkpoints/mini/tinywam with 6 branches each (5100-5149, in two stores)
#   3. runs/wm41/eEPOCHS/VARIANT: `wamplan wm train --preset mini` from scratch, the same data, epochs and
#      seed for each VARIANT (the default architecture is the control)
#   4. its bench.json, and runs/wm41/eEPOCHS/shipped/bench.json: `wamplan wm eval` on the store
# Then: `python lab/wm-variants/wm_variants_table.py runs/wm41/e4/*/bench.json` prints the variants table.
# DRY=1 lab/wm-variants/wm_variants.sh prints the commands that are still to run and runs nothing.
set -euo pipefail
cd "$(dirname "$0")/../.."
EPOCHS=${1:-4}
export OMP_NUM_THREADS=1
PY=.venv/bin/python
WP=.venv/bin/wamplan
RUNS=runs/wm41/e$EPOCHS
mkdir -p "$RUNS/shipped" data/wm41
killtree() { local c; for c in $(pgrep -P "$1"); do killtree "$c"; done; kill "$1" 2>/dev/null || true; }
trap 'for j in $(jobs -p); do killtree "$j"; done' EXIT  # a stopped recipe leaves no collector writing behind it

once() {  # once NAME CMD...: run CMD unless NAME.done exists; NAME.done on success, NAME.seconds += its time
  local name=$1; shift
  [ -e "$name.done" ] && return 0
  echo "[$(date +%H:%M:%S)] $name: $*"
  [ -n "${DRY:-}" ] && return 0
  local t0=$SECONDS status=0
  "$@" > "$name.log" 2>&1 || status=$?
  echo $((SECONDS - t0)) >> "$name.seconds"
  [ $status -eq 0 ] || { echo "$name failed (exit $status): see $name.log" >&2; return $status; }
  touch "$name.done"
}

both() {  # both PID PID: wait for two background steps; fail if either failed
  local status=0
  wait "$1" || status=1
  wait "$2" || status=1
  return $status
}

# 1 and 2: two processes
(
  once data/wm_bench $PY scripts/wm_benchmark_store.py --out data/wm_bench --workers 1
  once data/wm41/pink $WP collect --source pink --episodes 150 --seed-start 3000 --max-steps 100 \
      --out data/wm41/pink --workers 1
  once data/wm41/branches_b $WP collect --source policy --policy checkpoints/mini/tinywam --episodes 25 \
      --seed-start 5125 --branches 6 --out data/wm41/branches_b --workers 1
) & a=$!
(
  once data/wm41/expert $WP collect --source expert --episodes 100 --seed-start 1000 --out data/wm41/train --workers 1
  once data/wm41/noisy $WP collect --source noisy-expert --episodes 100 --seed-start 2000 --out data/wm41/train \
      --workers 1
  once data/wm41/branches_a $WP collect --source policy --policy checkpoints/mini/tinywam --episodes 25 \
      --seed-start 5100 --branches 6 --out data/wm41/branches_a --workers 1
) & b=$!
both $a $b
[ -n "${DRY:-}" ] || $PY scripts/wm_benchmark_store.py --out data/wm_bench --check > /dev/null  # the benchmark's own

train() {  # train NAME FLAGS...: one variant from scratch
  local name=$1; shift
  once $RUNS/$name $WP wm train --data data/wm41/train,data/wm41/pink,data/wm41/branches_a,data/wm41/branches_b \
      --preset mini --out $RUNS/$name --epochs "$EPOCHS" "$@"
  once $RUNS/$name/bench $WP wm eval --ckpt $RUNS/$name/checkpoint --data data/wm_bench --split all \
      --horizon 4 --json $RUNS/$name/bench.json
}

once $RUNS/shipped/bench $WP wm eval --ckpt checkpoints/mini/wm_augmented --data data/wm_bench --split all \
    --horizon 4 --json $RUNS/shipped/bench.json
# 3 and 4: two variants at a time
train control & a=$!; train adaln --action-conditioning adaln & b=$!; both $a $b
train adaln_change4 --action-conditioning adaln --change-weight 4 & a=$!; train tokens --action-tokens & b=$!; both $a $b
# the low-pass encoder and the sibling loss from scratch, then both
train adaln_dct --action-conditioning adaln --encoder-kwargs '{"basis": "dct"}' & a=$!
train adaln_sib4 --action-conditioning adaln --sibling-weight 4 & b=$!; both $a $b
train adaln_dct_sib4 --action-conditioning adaln --encoder-kwargs '{"basis": "dct"}' --sibling-weight 4 & a=$!
train adaln_dct_sib16 --action-conditioning adaln --encoder-kwargs '{"basis": "dct"}' --sibling-weight 16 & b=$!
both $a $b
echo "[$(date +%H:%M:%S)] done: $PY lab/wm-variants/wm_variants_table.py $RUNS/*/bench.json"
