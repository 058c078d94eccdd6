#!/usr/bin/env bash
# The main job on this machine: show the task, then evaluate the WAM open loop (condition 1) against the
# WAM with world-model feedback planning (condition 7, or 6 when only the plain model ships) on a handful
# of seeds with the small pretrained checkpoints in checkpoints/mini, and write the report.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-out/demo}
SEEDS=${DEMO_SEEDS:-8}
W=.venv/bin/wamplan
CK=checkpoints/mini
mkdir -p "$OUT"
$W env check
$W env render --seed 0 --out "$OUT/views.png"
$W env rollout --policy expert --episodes 1 --seed-start 0 --json "$OUT/expert_rollout.json" --video "$OUT/videos"
if [ -f "$CK/tinywam/model.safetensors" ]; then
  # an out/demo/eval made with another planner (older demos ran the paper's CEM) is kept aside, not mixed in
  if [ -f "$OUT/eval/eval_config.json" ] && ! grep -q '"planner": "wamplan"' "$OUT/eval/eval_config.json"; then
    old="$OUT/eval.$(date +%Y%m%d-%H%M%S)"
    mv "$OUT/eval" "$old" && echo "an older demo evaluation (another planner) was kept in $old"
  fi
  args=(--wam "$CK/tinywam" --episodes "$SEEDS" --seed-start 0 --out "$OUT/eval" --workers 2)
  # the first 4 seeds of each condition are filmed into eval/videos; the decoder draws the plan videos' model columns
  [ -f "$CK/decoder/model.safetensors" ] && args+=(--decoder "$CK/decoder")
  if [ -f "$CK/wm_augmented/model.safetensors" ]; then
    $W eval --conditions 1,7 "${args[@]}" --wm-augmented "$CK/wm_augmented"
  elif [ -f "$CK/wm_plain/model.safetensors" ]; then
    $W eval --conditions 1,6 "${args[@]}" --wm-plain "$CK/wm_plain"
  else
    $W eval --conditions 1 "${args[@]}"
  fi
  $W report "$OUT/eval"
  # the episode-by-episode comparison of these seeds (the 100-seed table: README.md, "Results")
  awk '/^## /{show = /^## Episode by episode/} show' "$OUT/eval/report.md"
  echo "($SEEDS seeds cannot call a difference: the 100-seed test run of these checkpoints is README.md's 'Results' and docs/results.md)"
  if [ -f "$CK/decoder/model.safetensors" ] && [ -f "$CK/wm_augmented/model.safetensors" ]; then
    # the mechanism: one planned chunk, the WAM's target against the model's and the simulator's outcomes
    $W explain --wam "$CK/tinywam" --wm-augmented "$CK/wm_augmented" --decoder "$CK/decoder" \
      --seed "${DEMO_EXPLAIN_SEED:-7}" --chunk "${DEMO_EXPLAIN_CHUNK:-9}" --out "$OUT/mechanism.png"
  fi
else
  echo "no demo checkpoints in $CK: docs/results.md, 'The shipped checkpoints and the commands that made them', has the commands that make them"
fi
echo "demo outputs in $OUT: views.png, expert_rollout.json, videos/, eval/report.md, eval/report.html (open it in a browser), eval/figure3.png, eval/videos/ (docs/videos.md), mechanism.png"
