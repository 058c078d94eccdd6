"""The gates of the planned policy: when a chunk runs the WAM's own actions instead of a plan.

Before the search, on the WAM's chunk scored through the planning objective (``wam_cost``):
``threshold`` skips the search when that cost is at most it ("gated": already close enough to the target),
``above`` when it is above it ("gated-above": the model's prediction far from the target).
After the search: ``rank`` discards the plan when fewer than that share of the search's first random
candidates scored below the WAM's chunk ("rank-gated"); ``accept_margin`` discards it unless the plan's cost
is at least that fraction below ``wam_cost`` ("rejected"). A searched chunk runs its plan only if both pass.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from wamplan.config import check_numbers, require

SKIPPED = ("gated", "gated-above")  # open-loop reasons of chunks whose search was skipped
DISCARDED = ("rejected", "rank-gated")  # open-loop reasons of chunks that were searched, the plan then not executed


@dataclass(frozen=True)
class Gates:
    """The gate settings of a :class:`~wamplan.planning.policy.PlannedPolicyConfig` (None: that gate is off)."""

    threshold: float | None = None  # gate_threshold
    above: float | None = None  # gate_above
    rank: float | None = None  # rank_gate
    accept_margin: float | None = None

    def __post_init__(self):
        check_numbers(self, infinite=("threshold", "above"))  # a NaN gate, which no cost passes or fails: refused
        require(self.accept_margin is None or 0.0 <= self.accept_margin < 1.0,
                f"accept_margin must be in [0, 1) or None, got {self.accept_margin}")
        require(self.threshold is None or self.above is None or self.threshold < self.above,
                f"gate_threshold ({self.threshold}) must be below gate_above ({self.above}): "
                "the search runs only for costs between the two")
        require(self.rank is None or 0.0 < self.rank <= 1.0, f"rank_gate must be in (0, 1] or None, got {self.rank}")

    @property
    def needs_wam_cost(self) -> bool:
        """Whether a decision reads the WAM chunk's cost (then the caller scores it before the search)."""
        return self.threshold is not None or self.above is not None or self.accept_margin is not None

    def before_search(self, wam_cost: float | None) -> str | None:
        """Why the search is skipped for a chunk whose WAM chunk costs ``wam_cost`` ("gated", "gated-above"),
        or None to search."""
        if self.threshold is not None and wam_cost <= self.threshold:
            return "gated"
        if self.above is not None and wam_cost > self.above:
            return "gated-above"
        return None

    def after_search(self, seed_rank: float, wam_cost: float | None,
                     plan_cost: Callable[[], float]) -> tuple[str | None, float | None]:
        """Why the searched plan is discarded ("rank-gated", "rejected") or None to execute it, and the plan's cost
        where the accept test scored it (``plan_cost()`` is called only then). ``seed_rank``: the share of the
        search's first random candidates scored below the WAM's chunk (NaN, no rank: the rank gate discards
        the plan)."""
        if self.rank is not None and not seed_rank >= self.rank:
            return "rank-gated", None
        if self.accept_margin is None:
            return None, None
        cost = plan_cost()
        return ("rejected" if cost > (1.0 - self.accept_margin) * wam_cost else None), cost
