#!/usr/bin/env bash
# Load a `wamplan data export --format lerobot` (v3.0) with a reader we did not write: the LeRobotDataset class of
# the standalone `lerobot-dataset` 0.4.4 package (LeRobot's datasets code), in a virtual environment of its own.
#
#   scripts/check_lerobot_export.sh EXPORT_DIR [OUT_DIR]
#
# Prints LeRobot's frame and episode counts, compares its frames, actions and states with what wamplan's own
# reader decodes from the export (and with the store's frame, where the store is still there), and writes
# OUT_DIR/lerobot_vs_wamplan.png: the store's view, wamplan's decoded frame and LeRobot's, side by side.
#
# The environment (LEROBOT_VENV, default ~/.cache/wamplan/lerobot-venv) gets torch 2.13.0 (the CPU wheel; an
# unpinned torch pulls a multi-GB CUDA build), torchvision 0.16.2 without its dependencies (lerobot-dataset imports
# torchvision; the index serves only CUDA builds of it, whose compiled ops cannot load on a CPU torch, and 0.16 is
# the last release that imports without them; its VideoReader decodes through PyAV) and lerobot-dataset 0.4.4.
set -euo pipefail
cd "$(dirname "$0")/.."
[ $# -ge 1 ] || { echo "usage: $0 EXPORT_DIR [OUT_DIR]" >&2; exit 2; }
DS=$(realpath "$1"); OUT=${2:-lerobot_check}
[ -f "$DS/meta/info.json" ] || { echo "$0: $DS/meta/info.json is missing: pass a LeRobot export" >&2; exit 2; }
VENV=${LEROBOT_VENV:-$HOME/.cache/wamplan/lerobot-venv}
PY=${PYTHON:-python3}
WAMPLAN_PY=${WAMPLAN_PY:-.venv/bin/python}
log() { printf '[check_lerobot_export] %s\n' "$*"; }

if ! "$VENV/bin/python" -c 'import ledataset.datasets.lerobot_dataset' 2>/dev/null; then
  log "making $VENV (torch CPU, torchvision 0.16.2, lerobot-dataset 0.4.4)"
  "$PY" -m venv "$VENV"
  "$VENV/bin/python" -m pip install -q torch==2.13.0
  "$VENV/bin/python" -m pip install -q --no-deps torchvision==0.16.2
  "$VENV/bin/python" -m pip install -q lerobot-dataset==0.4.4
fi
mkdir -p "$OUT"
NPZ="$OUT/lerobot_frames.npz"

# 1. LeRobot's reader: counts, every frame's action and state, one frame of each camera mid-episode 0
"$VENV/bin/python" - "$DS" "$NPZ" <<'EOF' 2> >(grep -v -e "UserWarning" -e "warn(" >&2)
import sys
import numpy as np
from ledataset.datasets.lerobot_dataset import LeRobotDataset

root, npz = sys.argv[1:3]
ds = LeRobotDataset("wamplan/export", root=root, video_backend="pyav")
print(f"lerobot-dataset 0.4.4: {ds.num_frames} frames, {ds.num_episodes} episodes, fps {ds.fps}, "
      f"cameras {ds.meta.video_keys}, version {ds.meta.info['codebase_version']}")
k = int(ds.meta.episodes[0]["length"]) // 2
item = ds[k]
print(f"frame {k}: task {item['task']!r}, episode {int(item['episode_index'])}, timestamp {float(item['timestamp']):.3f}")
frames = {key: (item[key].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8) for key in ds.meta.video_keys}
actions = np.stack([ds.hf_dataset[i]["action"].numpy() for i in range(ds.num_frames)])
states = np.stack([ds.hf_dataset[i]["observation.state"].numpy() for i in range(ds.num_frames)])
np.savez(npz, index=k, actions=actions, states=states, **{f"img:{key}": v for key, v in frames.items()})
EOF

# 2. wamplan's reader and the store, beside LeRobot's
"$WAMPLAN_PY" - "$DS" "$NPZ" "$OUT" <<'EOF'
import json, sys
from pathlib import Path
import numpy as np
import pyarrow.parquet as pq
from PIL import Image
from wamplan.data.lerobot import layout as L
from wamplan.data.lerobot.video import read_span

root, npz, out = Path(sys.argv[1]), np.load(sys.argv[2]), Path(sys.argv[3])
info = json.loads((root / L.INFO).read_text())
data = pq.read_table(root / "data/chunk-000/file-000.parquet")
ours_a, ours_s = L.column_array(data, L.ACTION, root), L.column_array(data, L.STATE, root)
print(f"wamplan: {data.num_rows} frames; actions equal: {np.array_equal(ours_a, npz['actions'])}, "
      f"states equal: {np.array_equal(ours_s, npz['states'])}")
k, fps = int(npz["index"]), info["fps"]
meta = json.loads((root / L.WAMPLAN).read_text())
store = None
if Path(meta["store"]).is_dir():
    from wamplan.data.store import EpisodeStore
    s = EpisodeStore(meta["store"])
    store = s.load(s.episode_paths()[0]) if meta["image_size"] is None else None
rows = []
for key in [n[4:] for n in npz.files if n.startswith("img:")]:
    theirs = npz[f"img:{key}"]
    ours = read_span(root / info["video_path"].format(video_key=key, chunk_index=0, file_index=0), k / fps,
                     (k + 1) / fps, fps, key)[0]
    line = f"{key}: LeRobot vs wamplan decode, max |diff| {np.abs(theirs.astype(int) - ours).max()}"
    row = [ours, theirs]
    if store is not None:
        orig = store.images[key[len(L.IMAGES):]][k]
        line += f"; vs the store, mean |diff| {np.abs(theirs.astype(float) - orig).mean():.2f}"
        row.insert(0, orig)
    print(line)
    rows.append(np.concatenate(row, axis=1))
png = out / "lerobot_vs_wamplan.png"
Image.fromarray(np.concatenate(rows, axis=0)).resize((rows[0].shape[1] * 4, len(rows) * rows[0].shape[0] * 4),
                                                     Image.NEAREST).save(png)
print(f"wrote {png} (rows: cameras; columns: {'the store, ' if store is not None else ''}wamplan's decode, LeRobot's)")
EOF
