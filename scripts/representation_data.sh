#!/usr/bin/env bash
# The data of the representation runs (issue 56: the state head, the task-cnn encoder), re-created by one command:
#
#   scripts/representation_data.sh [OUT]       # OUT: default data/s56; about 40 min on two cores
#
#   OUT/expert     40 expert (seeds 1000-1039) + 40 noisy-expert (2000-2039) episodes of cube-insertion
#   OUT/branches   20 on-policy parents of checkpoints/mini/tinywam (5300-5319), 6 branches at every boundary
#
# Two collectors at once, one thread each; every collection resumes where it stopped when re-run.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-data/s56}
export OMP_NUM_THREADS=1
W=.venv/bin/wamplan
killtree() { local c; for c in $(pgrep -P "$1"); do killtree "$c"; done; kill "$1" 2>/dev/null || true; }
trap 'for j in $(jobs -p); do killtree "$j"; done' EXIT  # a stopped script leaves no collector writing behind it
(
  $W collect --source expert --episodes 40 --seed-start 1000 --out "$OUT/expert" --workers 1
  $W collect --source noisy-expert --episodes 40 --seed-start 2000 --out "$OUT/expert" --workers 1
) &
$W collect --source policy --policy checkpoints/mini/tinywam --episodes 20 --seed-start 5300 --branches 6 \
    --out "$OUT/branches" --workers 1 &
wait -n && wait -n
trap - EXIT
echo "$OUT: expert (80 episodes) and branches (20 parents) complete"
