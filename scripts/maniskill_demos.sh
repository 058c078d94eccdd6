#!/usr/bin/env bash
# ManiSkill's motion-planning demonstrations of a task, in ManiSkill's trajectory format:
#   scripts/maniskill_demos.sh --task peg-insertion-side --seeds 10000-10999 --out data/peg/mp
# ManiSkill 3.0.1's solutions need mplib; mplib 0.2.1 (the one that runs here) is built against NumPy 1 and crashes
# under the NumPy 2 of wamplan's environment, so this script keeps a second virtual environment, .venv-demos, with
# NumPy 1.26, mani-skill and mplib (created on first use, ~2 min), and runs `python -m wamplan.envs.demos` there.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${WAMPLAN_DEMOS_VENV:-.venv-demos}
PY=${PYTHON:-python3}
if [ ! -f "$VENV/.installed" ]; then
  echo "[demos] creating $VENV (NumPy 1, mani-skill, mplib 0.2.1)" >&2
  "$PY" -m venv "$VENV"
  "$VENV/bin/python" -m pip install -q torch==2.13.0 "numpy<2" mani-skill==3.0.1
  "$VENV/bin/python" -m pip install -q --no-deps mplib==0.2.1
  "$VENV/bin/python" -m pip install -q toppra transforms3d "numpy<2"
  touch "$VENV/.installed"
fi
PYTHONPATH=src OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} exec "$VENV/bin/python" -m wamplan.envs.demos "$@"
