"""The planning cost's settings, :class:`CostConfig`, importable without torch (the costs themselves are in
:mod:`wamplan.planning.costs`, whose ``register_cost`` enters a new cost's name in :data:`COST_NAMES`, and whose
``build_cost`` makes the cost a config names)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

from wamplan.config import check_numbers, field, require

COST_NAMES = {"patch", "cls"}  # the names of costs.COSTS, known without importing it (register_cost adds to both)


@dataclass(frozen=True)
class CostConfig:
    """Which planning cost to use (paper: the patch cost over all three cameras)."""

    name: str = field("patch", "planning cost: 'patch' (eq. 3) or 'cls' (one vector per view: the mean of its "
                               "patch tokens, a global match)", choices=lambda: sorted(COST_NAMES))
    view_weights: tuple[float, ...] = field((), "per-camera weights (empty = uniform, the paper)")
    pool: int = field(1, "average each view's square token grid in blocks of pool x pool before the cost (2: a "
                         "4 x 4 grid to 2 x 2, a coarser spatial match that averages texture out; 1: off)")

    def __post_init__(self) -> None:
        check_numbers(self)
        require(self.name in COST_NAMES, f"unknown cost '{self.name}'; choose one of {sorted(COST_NAMES)}")
        require(all(w >= 0 for w in self.view_weights) and
                (not self.view_weights or sum(self.view_weights) > 0),
                f"view_weights must be >= 0 with a positive sum, got {self.view_weights}")
        require(isinstance(self.pool, int) and self.pool >= 1, f"pool must be an int >= 1 (1: off), got {self.pool}")

    def check_cameras(self, task: str, cameras: Sequence[str]) -> None:
        """Refuse, in one line, view weights that are not one per camera of ``task`` (its ``cameras``, in order)."""
        w = self.view_weights
        require(not w or len(w) == len(cameras),
                f"--cost-view-weights gives {len(w)} weights, but task '{task}' has {len(cameras)} cameras "
                f"({', '.join(cameras)}); give one weight per camera, in that order")
