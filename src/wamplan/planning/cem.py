"""The cross-entropy method exactly as in the paper (§3.3, Table 3).

Each iteration scores the current mean plus ``num_candidates - 1`` samples from N(mu, diag sigma^2),
all clipped to the action bounds; keeps the ``num_elites`` lowest-cost candidates; refits mu and sigma
to exactly those (clipped, scored) elites; after the last iteration it returns the final mean.

Decisions the paper leaves open:
- sigma is the POPULATION std of the elites (``std_ddof=0``, the Gaussian maximum-likelihood fit).
  DINO-WM's ``planning/cem.py`` uses torch's default ``std()`` (ddof=1), i.e. sqrt(8/7) ~ 1.07x wider
  with 8 elites; set ``std_ddof=1`` to match it.
- Clipping happens before scoring, so the refit sees exactly what was scored, and the refit mean of
  in-bounds elites is in bounds. The seed itself is clipped before it becomes mu0.
- Elite ties are broken by candidate index (stable sort), so the mean wins ties; NaN costs are never
  elites (they still show in the logged cost_mean).

The gripper dimension: its command is effectively binary (+1 open, -1 close) while the search is
Gaussian with sigma0 = 0.10 around the WAM's value. Half of the samples around +-1 are clipped back
to exactly +-1 and the rest move inward by ~0.08, and each iteration moves the mean by only about a
sigma, so CEM never flips the WAM's gripper decision. On toy costs a gripper-indifferent cost leaves
the refit mean at ~0.95, and even a cost that rewards closing as hard as possible only moves an open
(+1) gripper to ~0.7 after the paper's 4 iterations (tests/test_planning_optimizers.py): the paper's
"keeps the gripper close to the WAM's proposal". ``init_std_per_dim`` (e.g.
``(0.1, 0.1, 0.1, 0.1, 0.0)``) freezes it at the WAM's value; a large gripper sigma (e.g. 1.0) lets
the search flip it.
"""

from __future__ import annotations

import torch
from torch import Tensor

from wamplan.planning.base import SamplingPlanner, register_planner
from wamplan.planning.configs import CEMConfig


@register_planner("cem")
class CEMPlanner(SamplingPlanner):
    config_cls = CEMConfig
    config: CEMConfig

    def _update(self, cand: Tensor, costs: Tensor, mu: Tensor, sigma: Tensor
                ) -> tuple[Tensor, Tensor, Tensor]:
        ranked = torch.argsort(torch.nan_to_num(costs, nan=float("inf")), stable=True)  # (B,)
        idx = ranked[: self.config.num_elites]  # (K,)
        elites = cand[idx]  # (K, H_opt, A)
        new_mu = elites.mean(dim=0)  # (H_opt, A)
        new_sigma = elites.std(dim=0, correction=self.config.std_ddof)  # (H_opt, A)
        return new_mu, new_sigma, costs[idx].mean()
