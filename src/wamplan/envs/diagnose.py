"""Why rendering may fail on this machine: the Vulkan driver and the Mesa version lavapipe needs."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path


def mesa_version() -> str | None:
    """The installed ``mesa-vulkan-drivers`` package version, or None (not a Debian system, not installed)."""
    try:
        out = subprocess.run(["dpkg-query", "-W", "-f=${Version}", "mesa-vulkan-drivers"], capture_output=True,
                             text=True, timeout=10)
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def driver_file_problem() -> str | None:
    """Why the Vulkan driver files the environment names (``VK_ICD_FILENAMES``, else ``VK_DRIVER_FILES``: paths
    separated by ':') cannot be loaded, in one line naming the variable and the fix; None when one of them is a
    readable JSON file (or neither variable is set)."""
    import json

    for var in ("VK_ICD_FILENAMES", "VK_DRIVER_FILES"):
        value = os.environ.get(var)
        if not value:
            continue
        whys = []
        for path in value.split(os.pathsep):
            try:
                json.loads(Path(path).read_text(encoding="utf-8"))
                return None  # the loader reads only the first variable set, and any one driver file will do
            except (OSError, ValueError) as e:
                whys.append(f"{path} does not exist" if isinstance(e, FileNotFoundError) else
                            f"{path} cannot be read as JSON ({e})")
        return (f"{var}={value} names no usable Vulkan driver file ({whys[0]}); point {var} at your driver's ICD "
                f"json (e.g. /usr/share/vulkan/icd.d/lvp_icd.json) or unset it")
    return None


def diagnose_renderer() -> list[str]:
    """Human-readable reasons rendering may fail here (empty if nothing looks wrong)."""
    import wamplan.envs.vulkan as vk

    vk.configure_vulkan()
    problems = [p for p in (driver_file_problem(),) if p]
    icd = os.environ.get("VK_ICD_FILENAMES") or os.environ.get("VK_DRIVER_FILES")
    gpu = any(p.exists() for p in vk.GPU_ICDS)
    if not icd and not gpu:
        problems.append("no Vulkan driver found: run `make setup` (installs Mesa lavapipe >= 24.3 from "
                        "bookworm-backports) or set VK_ICD_FILENAMES to your driver's ICD json")
    mesa = mesa_version()
    if not gpu and mesa is not None:
        parts = mesa.split(".")
        if len(parts) >= 2 and parts[0].isdigit() and parts[1].isdigit() and (int(parts[0]), int(parts[1])) < (24, 3):
            problems.append(f"Mesa {mesa} is too old: SAPIEN needs VK_KHR_external_semaphore_fd, which lavapipe has "
                            f"from Mesa 24.3; run `make setup` to install 25.x from bookworm-backports")
    return problems
