#!/usr/bin/env bash
# Idempotent set-up for a fresh Debian bookworm machine (CPU) or a GPU machine.
#  1. the Vulkan software renderer (Mesa >= 24.3 lavapipe from bookworm-backports) unless Vulkan already works;
#  2. a virtual environment in .venv with a CPU build of torch (only where no torch is present) and wamplan;
#  3. headless Chromium from Debian's packages (the report page's browser test) unless a chromium is present.
# The backports source is derived from the mirror already configured in apt; no host is written here.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${WAMPLAN_VENV:-.venv}
PY=${PYTHON:-python3}
UV_VERSION=0.13.10  # the installer of wamplan's dependencies (pip's if it cannot be installed)
log() { printf '[setup %3ds] %s\n' "$SECONDS" "$*"; }

mesa_ok() {
  # True when a GPU Vulkan driver is installed or lavapipe from Mesa >= 24.3 is.
  ls /usr/share/vulkan/icd.d/nvidia_icd.json /etc/vulkan/icd.d/nvidia_icd.json \
     /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json >/dev/null 2>&1 && return 0
  local v
  v=$(dpkg-query -W -f='${Version}' mesa-vulkan-drivers 2>/dev/null || true)
  [ -n "$v" ] && dpkg --compare-versions "$v" ge 24.3 && [ -f /usr/share/vulkan/icd.d/lvp_icd.json ]
}

install_renderer() {
  if mesa_ok; then log "Vulkan driver present"; return; fi
  if ! command -v apt-get >/dev/null || [ "$(id -u)" != 0 ]; then
    log "cannot install Mesa lavapipe (need root and apt); run 'wamplan env check' for what to do"; return
  fi
  local src=/etc/apt/sources.list.d/wamplan-backports.sources
  if [ ! -f "$src" ]; then
    # The first Debian mirror URI of the existing sources (deb822 or one-line format).
    local uri
    uri=$(grep -hE '^URIs:' /etc/apt/sources.list.d/*.sources 2>/dev/null | awk '{print $2}' | grep -v -- '-security' | grep -E '/debian/?$' | head -n1 || true)
    [ -n "$uri" ] || uri=$(grep -hE '^deb ' /etc/apt/sources.list 2>/dev/null | awk '{print $2}' | grep -E '/debian/?$' | head -n1 || true)
    [ -n "$uri" ] || { log "no Debian mirror found in apt sources; cannot add bookworm-backports"; return 1; }
    printf 'Types: deb\nURIs: %s\nSuites: bookworm-backports\nComponents: main\nSigned-By: /usr/share/keyrings/debian-archive-keyring.gpg\n' "$uri" >"$src"
    log "added bookworm-backports from the configured mirror"
  fi
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq -t bookworm-backports mesa-vulkan-drivers libvulkan1 >/dev/null
  log "installed mesa-vulkan-drivers $(dpkg-query -W -f='${Version}' mesa-vulkan-drivers)"
}

install_browser() {
  # `wamplan report` writes report.html; tests/test_report_page.py loads it in this browser (skipped without one).
  if command -v chromium >/dev/null || command -v chromium-browser >/dev/null; then log "Chromium present"; return; fi
  if ! command -v apt-get >/dev/null || [ "$(id -u)" != 0 ]; then
    log "cannot install Chromium (need root and apt); the report page's browser test will be skipped"; return
  fi
  local t0=$SECONDS
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium >/dev/null \
    || { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium >/dev/null; }
  log "installed chromium $(dpkg-query -W -f='${Version}' chromium) in $((SECONDS - t0)) s"
}

installer() {
  # uv resolves and installs the same versions as pip in a fraction of the time (torch stays pip's: uv does not
  # look for the CPU wheel on disk); pip where uv cannot be installed
  if [ -x "$VENV/bin/uv" ] || $VENV/bin/python -m pip install -q --disable-pip-version-check uv==$UV_VERSION >&2; then
    echo "$VENV/bin/uv pip install -q --python $VENV/bin/python"
  else
    echo "$VENV/bin/python -m pip install -q --no-compile --disable-pip-version-check"
  fi
}

install_python() {
  [ -x "$VENV/bin/python" ] || { log "creating $VENV"; "$PY" -m venv "$VENV"; }
  # --no-compile: pip does not byte-compile every module it installs (tens of seconds for torch, ray, transformers,
  # wandb); Python compiles the ones it imports, once
  local pip="$VENV/bin/python -m pip install -q --no-compile --disable-pip-version-check"
  if ! "$VENV/bin/python" -c 'import torch' 2>/dev/null; then
    # A CPU wheel of this version lies on the machine's disk; an unpinned torch pulls a multi-GB CUDA build.
    log "installing torch (CPU)"; $pip torch==2.13.0
  fi
  local stamp="$VENV/.wamplan-installed"
  if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    # with the logging extras, so that tests/test_train_log.py reads TensorBoard and W&B files back
    log "installing wamplan and its dependencies"; $(installer) -e '.[dev,tensorboard,wandb]'
    # compile, once and alone, the modules wamplan and its tests import (not every module installed)
    log "compiling the modules wamplan imports"
    "$VENV/bin/python" -c 'import torch, gymnasium, h5py, pyarrow, av, imageio, matplotlib.pyplot, fastapi, uvicorn
import websockets, requests, transformers, safetensors, wamplan.envs, mani_skill.envs, wamplan.cli, wamplan.api
import wamplan.planning.policy, wamplan.worldmodel.train, wamplan.wam.tinywam, wamplan.evaluation.runner
import wamplan.evaluation.report, wamplan.proxy.app, ray, wandb, tensorboard' && touch "$stamp"
  fi
  if ! "$VENV/bin/python" -c 'import openpi_client.action_chunk_broker' 2>/dev/null; then
    # openpi's own robot client, for the tests that drive the proxy with it: without its numpy<2 pin (the modules
    # used need only msgpack, numpy and websockets, which wamplan installs, and dm-tree for its ActionChunkBroker)
    log "installing openpi-client (tests)"; $(installer) --no-deps openpi-client==0.1.2
    $(installer) dm-tree==0.1.10
  fi
}

install_renderer
install_browser
install_python
log "done"
