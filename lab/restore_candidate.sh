#!/usr/bin/env bash
# Restore a candidate checkpoint from git history:
#   lab/restore_candidate.sh NAME [DEST]     # writes DEST/checkpoints/candidates/NAME (DEST: the repository's root)
# NAME, the commit that holds it and the sha256 of its files come from lab/candidates.md. It needs a full clone
# (`git clone --depth 1` lacks that commit; `git fetch --unshallow` turns a shallow clone into a full one).
set -euo pipefail
cd "$(dirname "$0")/.."
MANIFEST=lab/candidates.md
if [ $# -lt 1 ] || [ $# -gt 2 ]; then
  echo "usage: lab/restore_candidate.sh NAME [DEST]   (the names: $MANIFEST)" >&2; exit 2
fi
NAME=$1
DEST=${2:-.}
ROW=$(awk -F' *\\| *' -v n="$NAME" '$2 == n {print $3, $4, $5; exit}' "$MANIFEST")
if [ -z "$ROW" ]; then
  echo "restore_candidate: no candidate named '$NAME' in $MANIFEST" >&2; exit 2
fi
read -r COMMIT SHA_MODEL SHA_CONFIG <<< "$ROW"
if ! git cat-file -e "$COMMIT^{commit}" 2>/dev/null; then
  echo "restore_candidate: commit $COMMIT is not in this clone; it needs a full clone (not --depth 1): git fetch --unshallow" >&2
  exit 1
fi
mkdir -p "$DEST"
git archive "$COMMIT" "checkpoints/candidates/$NAME" | tar -x -C "$DEST"
OUT="$DEST/checkpoints/candidates/$NAME"
check() {
  local got
  got=$(sha256sum "$OUT/$1" | cut -d' ' -f1)
  if [ "$got" != "$2" ]; then
    echo "restore_candidate: $OUT/$1 has sha256 $got, the manifest says $2" >&2; exit 1
  fi
}
check model.safetensors "$SHA_MODEL"
check config.json "$SHA_CONFIG"
echo "$OUT (sha256 checked)"
