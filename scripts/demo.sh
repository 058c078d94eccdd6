#!/usr/bin/env bash
# The main job on this machine, until the evaluation lands: check the renderer, show the task,
# roll the scripted expert out, collect one episode and draw its contact sheet.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-out/demo}
W=.venv/bin/wamplan
mkdir -p "$OUT"
$W env check
$W env render --seed 0 --out "$OUT/views.png"
$W env rollout --policy expert --episodes 5 --seed-start 0 --json "$OUT/expert_rollout.json" --video "$OUT/videos"
rm -rf "$OUT/store"
$W collect --source expert --episodes 1 --out "$OUT/store"
$W data info "$OUT/store"
$W data view "$OUT/store" --episode 0 --out "$OUT/expert_sheet.png"
echo "demo outputs in $OUT: views.png, expert_rollout.json, videos/, expert_sheet.png"
