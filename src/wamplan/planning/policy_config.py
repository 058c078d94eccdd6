"""The planned policy's settings, :class:`PlannedPolicyConfig`, and the checks that refuse settings its dynamics or
WAM cannot run (:func:`check_fits`); importable without torch, so a command checks them first."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from wamplan.config import check_numbers, field, require
from wamplan.errors import UserError
from wamplan.planning.gates import Gates

if TYPE_CHECKING:
    from wamplan.planning.dynamics import Dynamics


class PlanningError(UserError):
    """The planned policy cannot plan as driven or configured: a history frame it never saw, or settings that
    do not fit its dynamics."""


WARM_STARTS = ("none", "residual")
FIRST_CHUNKS = ("open-loop", "rest-history")
HISTORIES = ("seen", "imagined")


@dataclass(frozen=True)
class PlannedPolicyConfig:
    """The planned policy's chunk rules; the defaults are the paper's (every chunk after the first planned, the
    plan executed whole).

    Contract: the search runs only for WAM-chunk costs above ``gate_threshold``.
    """

    first_chunk: str = field("open-loop", "chunk 1: open-loop (the paper) or rest-history (planned from a "
                             "synthesised rest-state history)", choices=FIRST_CHUNKS)
    history: str = field("seen", "a learned world model's history frames inside the last chunk: seen (the robot's "
                         "views every frameskip steps) or imagined (predicted by the model from the last boundary "
                         "with the actions run since: planning from chunk boundaries alone, what a client that posts "
                         "only at boundaries gives)", choices=HISTORIES)
    plan_seed: int = field(0, "base seed of the planner's sampling (plus 1000 x the episode seed plus the step)")
    gate_threshold: float | None = field(None, "run the WAM's chunk without a search when its cost is at most this "
                                         "(see `wamplan gate-calibrate`); None = off")
    warm_start: str = field("none", "the search's initial mean: none (the WAM's chunk) or residual (plus "
                            "warm_weight x the previous planned chunk's correction, arm only)", choices=WARM_STARTS)
    warm_weight: float = field(0.5, "with warm_start=residual: the share of the previous correction carried over")
    accept_margin: float | None = field(None, "run the plan only if its cost is at least this fraction below the "
                                        "WAM chunk's, else the WAM's chunk; None = always the plan")
    requery_every: int = field(0, "query the WAM and plan every K steps, running the first K actions of each planned "
                               "chunk (a robot that runs part of each chunk, e.g. openpi's LIBERO client's "
                               "replan_steps=5; serve: what a client that sends no executed_actions runs); "
                               "0 = the WAM's chunk")

    def __post_init__(self):
        check_numbers(self, infinite=("gate_threshold",))
        require(self.first_chunk in FIRST_CHUNKS, f"first_chunk must be one of {FIRST_CHUNKS}, got {self.first_chunk!r}")
        require(self.history in HISTORIES, f"history must be one of {HISTORIES}, got {self.history!r}")
        require(self.warm_start in WARM_STARTS, f"warm_start must be one of {WARM_STARTS}, got {self.warm_start!r}")
        require(0.0 <= self.warm_weight <= 1.0, f"warm_weight must be in [0, 1], got {self.warm_weight}")
        require(self.requery_every >= 0, f"--requery-every must be >= 0 (0: the WAM's chunk), got {self.requery_every}")
        _ = self.gates  # the Gates validate the gate settings

    @property
    def gates(self) -> Gates:
        return Gates(threshold=self.gate_threshold, accept_margin=self.accept_margin)


def check_frameskip(frameskip: int, chunk: int) -> None:
    """Refuse a learned model whose frameskip Δ exceeds the WAM's ``chunk``: one rollout step would run past the
    chunk. Δ = the chunk plans from the chunk boundaries alone; a Δ that does not divide the chunk plans its first
    Δ·floor(H/Δ) steps (the paper's Δ 5 with 16-step chunks)."""
    if frameskip > chunk:
        raise PlanningError(f"the world model's frameskip {frameskip} is longer than the WAM's {chunk}-step chunk; "
                            f"plan with a world model whose frameskip divides the chunk "
                            f"(`wamplan wm train --frameskip {chunk}`)")


def check_fits(cfg: PlannedPolicyConfig, chunk: int, dynamics: Dynamics) -> None:
    """Refuse settings of ``cfg`` that the ``dynamics`` or the WAM's ``chunk`` cannot run, in one line that names
    the fix."""
    if dynamics.needs_history:
        check_frameskip(getattr(dynamics, "frameskip", chunk), chunk)
    if cfg.requery_every > chunk:
        raise PlanningError(f"--requery-every {cfg.requery_every} is longer than the WAM's {chunk}-step chunk; a "
                            f"robot can run at most the {chunk} actions it was given before asking again")
    if cfg.history == "imagined":
        period, frameskip = cfg.requery_every or chunk, getattr(dynamics, "frameskip", None)
        if not dynamics.needs_history:
            raise PlanningError(f"--history imagined predicts a learned world model's history frames; "
                                f"{type(dynamics).__name__} keeps none: leave --history at seen")
        if period % frameskip:
            raise PlanningError(f"--history imagined rolls the world model from one planning point to the next in "
                                f"steps of its frameskip {frameskip}, which does not divide the {period} steps "
                                f"between them; use a model whose frameskip divides {period}, or --history seen")
