"""Why rendering may fail on this machine: the Vulkan driver and the Mesa version lavapipe needs."""

from __future__ import annotations

import os
import subprocess


def mesa_version() -> str | None:
    """The installed ``mesa-vulkan-drivers`` package version, or None (not a Debian system, not installed)."""
    try:
        out = subprocess.run(["dpkg-query", "-W", "-f=${Version}", "mesa-vulkan-drivers"], capture_output=True,
                             text=True, timeout=10)
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def diagnose_renderer() -> list[str]:
    """Human-readable reasons rendering may fail here (empty if nothing looks wrong)."""
    import wamplan.envs.vulkan as vk

    vk.configure_vulkan()
    problems = []
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
