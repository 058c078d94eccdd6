#!/usr/bin/env bash
# benchmarks/gpu.py with src/ on the path: the venv's python here, the image's python3 on a GPU machine (docs/gpu.md).
cd "$(dirname "$0")/.." && py=${PYTHON:-$([ -x .venv/bin/python ] && echo .venv/bin/python || echo python3)}
PYTHONPATH="src${PYTHONPATH:+:$PYTHONPATH}" exec "$py" benchmarks/gpu.py "$@"
