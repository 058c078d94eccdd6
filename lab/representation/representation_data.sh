#!/usr/bin/env bash
# The data of the representation runs (issue 56: the state head, the task-cnn encoder), re-created by one command:
#
#   lab/representation/representation_data.sh [OUT] [SET]   # OUT: default data/s56; SET: default 0; about 35 min on two cores
#
#   OUT/expert     40 expert (seeds 1000-1039) + 40 noisy-expert (2000-2039) episodes of cube-insertion
#   OUT/branches   20 on-policy parents of checkpoints/mini/tinywam (5300-5319), 6 branches at every boundary
#
# SET k takes the next seeds: expert 1000+40k.., noisy-expert 2000+40k.., parents 5300+20k.. (SET 1: 1040-1079,
# 2040-2079, 5320-5339), so sets 0 and 1 together are twice the data with no episode twice.
#
# Two collectors at once, one thread each; every collection resumes where it stopped when re-run.
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT=${1:-data/s56}
SET=${2:-0}
[[ $SET =~ ^[0-9]+$ ]] || { echo "representation_data.sh: SET must be a whole number >= 0, got '$SET'" >&2; exit 2; }
E=$((1000 + 40 * SET)) N=$((2000 + 40 * SET)) P=$((5300 + 20 * SET))
export OMP_NUM_THREADS=1
W=.venv/bin/wamplan
killtree() { local c; for c in $(pgrep -P "$1"); do killtree "$c"; done; kill "$1" 2>/dev/null || true; }
trap 'for j in $(jobs -p); do killtree "$j"; done' EXIT  # a stopped script leaves no collector writing behind it
(
  $W collect --source expert --episodes 40 --seed-start $E --out "$OUT/expert" --workers 1
  $W collect --source noisy-expert --episodes 40 --seed-start $N --out "$OUT/expert" --workers 1
) &
$W collect --source policy --policy checkpoints/mini/tinywam --episodes 20 --seed-start $P --branches 6 \
    --out "$OUT/branches" --workers 1 &
wait -n && wait -n
trap - EXIT
echo "$OUT: expert (80 episodes) and branches (20 parents) of set $SET complete"
