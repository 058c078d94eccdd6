#!/usr/bin/env bash
# The data of the boundary-history world models (Δ = the chunk, 16), re-created by one command per level:
#
#   scripts/boundary_data.sh [LEVEL] [OUT]   # LEVEL 1, 2, 4 or 8 (default 1); OUT default data/boundary/cube
#
#   OUT/expert       100 expert (seeds 1000-1099) + 100 noisy-expert (2000-2099) episodes: the shipped TinyWAM's recipe
#   OUT/parents_1    1x: 50 on-policy parents of checkpoints/mini/tinywam (60000-60049), 6 branches at every boundary
#   OUT/parents_2    2x adds 50 more (60050-60099); OUT/parents_4 4x adds 100 (60100-60199); OUT/parents_8 8x adds
#                    200 (60200-60399). Level L is every store up to L, so each level adds to the one below.
#
# Every store keeps the views every 16 steps (--image-every 16: a Δ = 16 model reads nothing else) and branches
# keep 48 steps of the parent's past (--branch-context 48). Two collectors at once, one thread each, niced
# (WORKERS=N: N processes each); every collection resumes where it stopped when re-run, with any WORKERS.
set -euo pipefail
cd "$(dirname "$0")/.."
LEVEL=${1:-1}
OUT=${2:-data/boundary/cube}
case $LEVEL in 1|2|4|8) ;; *) echo "boundary_data.sh: LEVEL must be 1, 2, 4 or 8, got '$LEVEL'" >&2; exit 2;; esac
WAM=checkpoints/mini/tinywam
export OMP_NUM_THREADS=1
W="nice -n 19 .venv/bin/wamplan"
C="--image-every 16 --workers ${WORKERS:-1}"
killtree() { local c; for c in $(pgrep -P "$1"); do killtree "$c"; done; kill "$1" 2>/dev/null || true; }
trap 'for j in $(jobs -p); do killtree "$j"; done' EXIT  # a stopped script leaves no collector writing behind it
parents() {  # level first-seed count
  $W collect --source policy --policy $WAM --episodes "$3" --seed-start $2 --branches 6 \
      --branch-context 48 --out "$OUT/parents_$1" $C
}
(
  parents 1 60000 50
  [[ $LEVEL -ge 2 ]] && parents 2 60050 50
  [[ $LEVEL -ge 4 ]] && parents 4 60100 100
  [[ $LEVEL -ge 8 ]] && parents 8 60200 200
  true
) & PARENTS=$!
(
  $W collect --source expert --episodes 100 --seed-start 1000 --out "$OUT/expert" $C
  $W collect --source noisy-expert --episodes 100 --seed-start 2000 --out "$OUT/expert" $C
) & EXPERT=$!
wait $PARENTS || { echo "boundary_data.sh: the parents' collection stopped; re-run to resume" >&2; exit 1; }
wait $EXPERT || { echo "boundary_data.sh: the expert collection stopped; re-run to resume" >&2; exit 1; }
trap - EXIT
echo "$OUT: level $LEVEL complete"
du -sh "$OUT"/*
