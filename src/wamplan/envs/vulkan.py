"""Point SAPIEN at a Vulkan driver that works on this machine before it is imported.

On a CPU-only machine the renderer is Mesa's lavapipe (>= 24.3, installed by ``scripts/setup.sh``).
If the user already chose a driver (``VK_ICD_FILENAMES``/``VK_DRIVER_FILES``) or a GPU driver is
installed, nothing is changed.
"""

from __future__ import annotations

import os
from pathlib import Path

LAVAPIPE_ICD = Path("/usr/share/vulkan/icd.d/lvp_icd.json")
GPU_ICDS = [Path("/usr/share/vulkan/icd.d/nvidia_icd.json"), Path("/etc/vulkan/icd.d/nvidia_icd.json"),
            Path("/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json")]


def configure_vulkan() -> None:
    if os.environ.get("VK_ICD_FILENAMES") or os.environ.get("VK_DRIVER_FILES"):
        return
    if any(p.exists() for p in GPU_ICDS):
        return
    if LAVAPIPE_ICD.exists():
        os.environ["VK_ICD_FILENAMES"] = str(LAVAPIPE_ICD)
