"""``--device auto`` resolution; nothing else in wamplan names a device literally."""

from __future__ import annotations

import torch


def resolve_device(name: str = "auto") -> torch.device:
    """'auto' picks the accelerator torch sees (CUDA, MPS, ...), else the CPU."""
    if name != "auto":
        return torch.device(name)
    acc = torch.accelerator.current_accelerator() if torch.accelerator.is_available() else None
    return acc if acc is not None else torch.device("cpu")
