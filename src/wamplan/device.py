"""``--device auto`` resolution; nothing else in wamplan names a device literally."""

from __future__ import annotations

import torch

from wamplan.errors import UserError


def resolve_device(name: str = "auto") -> torch.device:
    """'auto' picks the accelerator torch sees (CUDA, MPS, ...), else the CPU. A device this machine does not
    have (``cuda`` where torch has no CUDA, ``cuda:3`` on a 2-GPU machine) or a misspelt one is a one-line
    :class:`UserError`; commands resolve ``--device`` before any work, so that is where they stop."""
    if name == "auto":
        acc = torch.accelerator.current_accelerator() if torch.accelerator.is_available() else None
        return acc if acc is not None else torch.device("cpu")
    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError) as e:
        raise UserError(f"--device {name!r} is not a torch device ({e}); pass auto, cpu, cuda, cuda:1, mps, ...") \
            from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            why = "this torch is built without CUDA" if torch.version.cuda is None else "torch finds no CUDA device"
            raise UserError(f"--device {name}: {why} (torch {torch.__version__}); pass --device cpu or auto")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise UserError(f"--device {name}: this machine has {torch.cuda.device_count()} CUDA device(s), "
                            f"cuda:0..cuda:{torch.cuda.device_count() - 1}; pass one of those or auto")
    elif dev.type == "mps" and not torch.backends.mps.is_available():
        raise UserError(f"--device {name}: MPS is not available here; pass --device cpu or auto")
    return dev
