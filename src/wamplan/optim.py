"""What every trainer in wamplan shares: AdamW with decay on matrices only, warm-up + cosine, one step."""

from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import nn


def make_adamw(model: nn.Module, lr: float, weight_decay: float, betas: Sequence[float] = (0.9, 0.999)) -> torch.optim.AdamW:
    """AdamW with weight decay on >= 2-D parameters only (not biases, norms, per-channel scales)."""
    params = [p for p in model.parameters() if p.requires_grad]
    groups = [{"params": [p for p in params if p.ndim >= 2], "weight_decay": weight_decay},
              {"params": [p for p in params if p.ndim < 2], "weight_decay": 0.0}]
    return torch.optim.AdamW(groups, lr=lr, betas=tuple(betas))


def warmup_cosine(optimizer: torch.optim.Optimizer, warmup_steps: int, total_steps: int,
                  min_ratio: float = 0.0) -> torch.optim.lr_scheduler.LambdaLR:
    """lr factor: linear from 1/warmup to 1 over ``warmup_steps``, then cosine down to ``min_ratio``."""
    def factor(step: int) -> float:
        if step < warmup_steps:
            return (step + 1) / warmup_steps
        progress = min(1.0, (step - warmup_steps) / max(1, total_steps - warmup_steps))
        return min_ratio + (1.0 - min_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress))
    return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)


def optimizer_step(model: nn.Module, optimizer: torch.optim.Optimizer, scheduler, loss: torch.Tensor,
                   grad_clip: float) -> None:
    """Backward, clip the gradient norm (if ``grad_clip`` > 0), step the optimizer and the schedule."""
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    if grad_clip > 0:
        nn.utils.clip_grad_norm_(model.parameters(), grad_clip)
    optimizer.step()
    scheduler.step()
