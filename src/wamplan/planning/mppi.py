"""MPPI (Williams et al., 2017) behind the same interface as CEM: a second optimiser, not the paper's.

Each iteration scores the current mean plus ``num_candidates - 1`` Gaussian samples (clipped to the
bounds, as in CEM), weights them by

    w = softmax(-(c - min c) / (temperature * scale)),   scale = max c - min c  if normalize_costs else 1

and moves mu to the weighted average (blended with the old mean by ``momentum``). With
``update_std`` sigma becomes the weighted std around that average (floored by ``min_std``);
otherwise sigma stays at its initial value. The final mean is returned.

``normalize_costs`` (default on) makes ``temperature`` scale-free: it is then a fraction of this
iteration's cost range, so the same value works for DINOv3 patch costs and for a CPU encoder's.
Small temperatures approach "pick the best candidate"; large ones approach the plain sample mean.
The gripper behaves as under CEM (see ``wamplan.planning.cem``).
"""

from __future__ import annotations

import torch
from torch import Tensor

from wamplan.planning.base import SamplingPlanner, register_planner
from wamplan.planning.configs import MPPIConfig


@register_planner("mppi")
class MPPIPlanner(SamplingPlanner):
    config_cls = MPPIConfig
    config: MPPIConfig

    def weights(self, costs: Tensor) -> Tensor:
        """Path-integral weights (B,) of costs (B,), summing to 1; NaN costs get weight 0."""
        cfg = self.config
        c = torch.nan_to_num(costs, nan=float("inf"))  # (B,)
        shifted = c - c.min()  # (B,) >= 0, the best candidate at 0
        if cfg.normalize_costs:
            finite = torch.isfinite(shifted)
            span = torch.where(finite, shifted, torch.zeros_like(shifted)).max()
            shifted = shifted / span.clamp_min(1e-12)
        w = torch.softmax(-shifted / cfg.temperature, dim=0)  # (B,)
        return torch.nan_to_num(w, nan=1.0 / w.numel())  # all costs NaN: uniform weights

    def _update(self, cand: Tensor, costs: Tensor, mu: Tensor, sigma: Tensor
                ) -> tuple[Tensor, Tensor, Tensor]:
        cfg = self.config
        w = self.weights(costs)  # (B,)
        wb = w[:, None, None]  # (B, 1, 1)
        avg = (wb * cand).sum(dim=0)  # (H_opt, A)
        if cfg.update_std:
            sigma = ((wb * (cand - avg) ** 2).sum(dim=0)).sqrt()  # (H_opt, A)
        new_mu = cfg.momentum * mu + (1.0 - cfg.momentum) * avg  # (H_opt, A)
        finite = torch.isfinite(costs)
        weighted_cost = (w * torch.where(finite, costs, torch.zeros_like(costs))).sum()
        return new_mu, sigma, weighted_cost
