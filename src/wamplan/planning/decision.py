"""What the planned policy decided at one chunk boundary: :class:`ChunkDecision`, and its record (the plain data
``PlannedPolicy.info()["chunks"]`` and the evaluation records keep)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from wamplan.config import require
from wamplan.planning.gates import DISCARDED, SKIPPED

OPEN_LOOP = ("first-chunk", "warm-up", *SKIPPED, *DISCARDED)  # why a chunk runs the WAM's actions


@dataclass(frozen=True)
class ChunkCosts:
    """A chunk's planning costs (eq. 3 against the WAM's target; lower is better), None where not computed."""

    seed: float | None = None  # the WAM's chunk as the planner scores it (NaN: a planner that does not score its mean)
    best: float | None = None  # the lowest cost the search scored
    plan: float | None = None  # the plan, as the accept test (accept_margin) scores it
    init: float | None = None  # the search's warm-started initial mean (warm_start)


@dataclass(frozen=True)
class ChunkTimings:
    """Seconds one chunk took."""

    wam_s: float = 0.0  # querying the seed WAM (and the target WAM)
    target_encode_s: float = 0.0  # encoding the target views
    search_s: float = 0.0  # from the encoded target to the decision: gates, search


@dataclass(frozen=True)
class ChunkDecision:
    """What the planned policy decided at the chunk boundary ``step``."""

    step: int
    seed: np.ndarray  # (H, A) float32: the WAM's chunk
    executed: np.ndarray  # (H, A): what the policy runs, the plan or the WAM's chunk
    reason: str | None = None  # why the WAM's chunk runs open loop (one of OPEN_LOOP); None: the plan runs
    target: torch.Tensor | None = None  # (V, N, D) the encoded target views, on the dynamics' device, or None
    plan: np.ndarray | None = None  # (H, A) the search's plan (with the WAM's uncovered tail); None: no search ran
    costs: ChunkCosts = ChunkCosts()
    seed_rank: float | None = None  # share of the search's first random candidates scored below the WAM's chunk
    correction: tuple[float, ...] | None = None  # (A,) plan minus the WAM's chunk, mean over the searched steps
    timings: ChunkTimings = ChunkTimings()

    def __post_init__(self):
        require(self.reason is None or self.reason in OPEN_LOOP, f"reason must be None or one of {OPEN_LOOP}, "
                f"got {self.reason!r}")
        require(self.reason is not None or self.plan is not None, "a chunk without an open-loop reason needs a plan")
        require(self.executed.shape == self.seed.shape, f"executed {self.executed.shape} and seed {self.seed.shape} "
                "must have one shape (H, A)")

    @property
    def planned(self) -> bool:
        """Whether the plan runs."""
        return self.reason is None

    def record(self) -> dict[str, Any]:
        """The chunk's record in ``info()["chunks"]`` (what evaluation records keep): plain data, its keys in a
        fixed order."""
        t = self.timings
        rec: dict[str, Any] = dict(step=self.step, planned=self.planned, wam_s=t.wam_s,
                                   target_encode_s=t.target_encode_s, search_s=t.search_s)
        if self.plan is None:  # no search: why, and the WAM chunk's cost where a gate read it
            rec["open_loop"] = self.reason
            if self.costs.seed is not None:
                rec["seed_cost"] = self.costs.seed
            return rec
        rec.update(seed_cost=self.costs.seed, best_cost=self.costs.best, seed_rank=self.seed_rank,
                   correction=list(self.correction))
        rec.update({k: v for k, v in (("init_cost", self.costs.init), ("plan_cost", self.costs.plan)) if v is not None})
        if self.reason is not None:
            rec["open_loop"] = self.reason
        return rec
