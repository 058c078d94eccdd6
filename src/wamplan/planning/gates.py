"""The gates of the planned policy: when a chunk runs the WAM's own actions instead of a plan.

Before the search, on the WAM's chunk scored through the planning objective (``wam_cost``): ``threshold`` skips
the search when that cost is at most it ("gated": already close enough to the target). After the search:
``accept_margin`` discards the plan unless its cost is at least that fraction below ``wam_cost`` ("rejected").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from wamplan.config import check_numbers, require

SKIPPED = ("gated",)  # open-loop reasons of chunks whose search was skipped
DISCARDED = ("rejected",)  # open-loop reasons of chunks that were searched, the plan then not executed


@dataclass(frozen=True)
class Gates:
    """The gate settings of a :class:`~wamplan.planning.policy.PlannedPolicyConfig` (None: that gate is off)."""

    threshold: float | None = None  # gate_threshold
    accept_margin: float | None = None

    def __post_init__(self):
        check_numbers(self, infinite=("threshold",))  # a NaN gate, which no cost passes or fails: refused
        require(self.accept_margin is None or 0.0 <= self.accept_margin < 1.0,
                f"accept_margin must be in [0, 1) or None, got {self.accept_margin}")

    @property
    def needs_wam_cost(self) -> bool:
        """Whether a decision reads the WAM chunk's cost (then the caller scores it before the search)."""
        return self.threshold is not None or self.accept_margin is not None

    def before_search(self, wam_cost: float | None) -> str | None:
        """Why the search is skipped for a chunk whose WAM chunk costs ``wam_cost`` ("gated"), or None to search."""
        if self.threshold is not None and wam_cost <= self.threshold:
            return "gated"
        return None

    def after_search(self, wam_cost: float | None, plan_cost: Callable[[], float]) -> tuple[str | None, float | None]:
        """Why the searched plan is discarded ("rejected") or None to execute it, and the plan's cost where the
        accept test scored it (``plan_cost()`` is called only then)."""
        if self.accept_margin is None:
            return None, None
        cost = plan_cost()
        return ("rejected" if cost > (1.0 - self.accept_margin) * wam_cost else None), cost
