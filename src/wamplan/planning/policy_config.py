"""The planned policy's settings, :class:`PlannedPolicyConfig`, and the checks that refuse settings its planner,
dynamics or WAM cannot run (:func:`check_fits`); importable without torch, so a command checks them first."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from wamplan.config import check_numbers, field, require
from wamplan.errors import UserError
from wamplan.planning.gates import Gates

if TYPE_CHECKING:
    from wamplan.planning.base import Planner
    from wamplan.planning.dynamics import Dynamics


class PlanningError(UserError):
    """The planned policy cannot plan as driven or configured: a history frame it never saw, or settings that
    do not fit its dynamics or planner."""


WARM_STARTS = ("none", "residual")
FIRST_CHUNKS = ("open-loop", "rest-history")


@dataclass(frozen=True)
class PlannedPolicyConfig:
    """The planned policy's chunk rules; the defaults are the paper's (every chunk after the first planned, the
    plan executed whole).

    Contract: the search runs only for WAM-chunk costs between ``gate_threshold`` and ``gate_above`` (the first
    below the second); ``rank_gate`` needs a planner that scores its mean (``include_mean``); ``replan_every``
    K must divide the chunk, be shorter than it and be a multiple of a learned model's frameskip, needs a planner
    that optimises the whole chunk, and its re-plans run without gates, from the rest of the plan, toward the
    boundary's target (a chunk's ``search_s`` includes them; its costs and correction are the boundary search's);
    ``bias_correction`` needs a learned model whose frameskip divides the chunk and whole chunks (no
    ``replan_every``), is measured only from real histories, and the gates then compare corrected costs;
    ``disagreement_weight`` needs an ensemble of world models or one with a spread head.
    """

    first_chunk: str = field("open-loop", "chunk 1: open-loop (the paper) or rest-history (planned from a "
                             "synthesised rest-state history)", choices=FIRST_CHUNKS)
    plan_seed: int = field(0, "base seed of the planner's sampling (plus 1000 x the episode seed plus the step)")
    gate_threshold: float | None = field(None, "run the WAM's chunk without a search when its cost is at most this "
                                         "(see `wamplan gate-calibrate`); None = off")
    gate_above: float | None = field(None, "run the WAM's chunk without a search when its cost is above this; "
                                     "None = off")
    warm_start: str = field("none", "the search's initial mean: none (the WAM's chunk) or residual (plus "
                            "warm_weight x the previous planned chunk's correction, arm only)", choices=WARM_STARTS)
    warm_weight: float = field(0.5, "with warm_start=residual: the share of the previous correction carried over")
    disagreement_weight: float = field(0.0, "add this times the prediction's spread to the cost: an ensemble's "
                                       "disagreement plus its members' predicted variances, or one model's "
                                       "predicted variance (a spread head: at 1 the plain patch cost's expectation); "
                                       "0 = off")
    accept_margin: float | None = field(None, "run the plan only if its cost is at least this fraction below the "
                                        "WAM chunk's, else the WAM's chunk; None = always the plan")
    rank_gate: float | None = field(None, "run the plan only if at least this share of the search's first random "
                                    "candidates score below the WAM's chunk, else the WAM's chunk; None = off")
    bias_correction: float = field(0.0, "add this share of the world model's error on the chunk just run to every "
                                   "predicted outcome; 0 = off")
    replan_every: int | None = field(None, "re-plan the rest of a planned chunk every this many steps, toward the "
                                     "same target; None = execute whole chunks")
    correction_gain: float = field(1.0, "execute the WAM's chunk plus this multiple of the planned correction, "
                                   "clipped to the action bounds; 1 = the plan")

    def __post_init__(self):
        check_numbers(self, infinite=("gate_threshold", "gate_above"))
        require(self.first_chunk in FIRST_CHUNKS, f"first_chunk must be one of {FIRST_CHUNKS}, got {self.first_chunk!r}")
        require(self.warm_start in WARM_STARTS, f"warm_start must be one of {WARM_STARTS}, got {self.warm_start!r}")
        require(0.0 <= self.warm_weight <= 1.0, f"warm_weight must be in [0, 1], got {self.warm_weight}")
        require(self.disagreement_weight >= 0, f"disagreement_weight must be >= 0, got {self.disagreement_weight}")
        _ = self.gates  # the Gates validate the gate settings
        require(0.0 <= self.bias_correction <= 1.0, f"bias_correction must be in [0, 1], got {self.bias_correction}")
        require(self.replan_every is None or self.replan_every >= 1,
                f"replan_every must be >= 1 or None, got {self.replan_every}")
        require(0.0 < self.correction_gain <= 4.0, f"correction_gain must be in (0, 4], got {self.correction_gain} "
                "(1 executes the plan; for the WAM's own chunks, unplanned, run condition 1)")

    @property
    def gates(self) -> Gates:
        return Gates(threshold=self.gate_threshold, above=self.gate_above, rank=self.rank_gate,
                     accept_margin=self.accept_margin)


def check_frameskip(frameskip: int, chunk: int) -> None:
    """Refuse a learned model whose frameskip Δ exceeds the WAM's ``chunk``: one rollout step would run past the
    chunk. Δ = the chunk plans from the chunk boundaries alone; a Δ that does not divide the chunk plans its first
    Δ·floor(H/Δ) steps (the paper's Δ 5 with 16-step chunks)."""
    if frameskip > chunk:
        raise PlanningError(f"the world model's frameskip {frameskip} is longer than the WAM's {chunk}-step chunk; "
                            f"plan with a world model whose frameskip divides the chunk "
                            f"(`wamplan wm train --frameskip {chunk}`)")


def check_replan_every(k: int, chunk: int, frameskip: int | None) -> None:
    """Refuse a re-planning period that does not fit: K must divide the ``chunk`` and be shorter than it, and be
    a multiple of a learned model's ``frameskip`` (None: the simulator, any K) so the rest's rollout ends at
    the target's step."""
    if not (k < chunk and chunk % k == 0):
        raise PlanningError(f"replan_every={k} must divide the WAM's {chunk}-step chunk and be shorter than "
                            f"it, e.g. {chunk // 2}; or drop it to execute whole chunks")
    if frameskip is not None and k % frameskip:
        raise PlanningError(f"replan_every={k} must be a multiple of the world model's frameskip "
                            f"{frameskip}, so that the rest's rollout ends at the target's step")


def check_settings(cfg: PlannedPolicyConfig, chunk: int, planner_config: Any) -> None:
    """Refuse settings of ``cfg`` that the planner (its config ``planner_config``) or the WAM's ``chunk`` cannot
    run, in one line that names the fix: the part of :func:`check_fits` that needs no dynamics, so a command can
    check before it loads or runs anything."""
    if cfg.replan_every is not None:
        check_replan_every(cfg.replan_every, chunk, None)
        if getattr(planner_config, "num_optimized", None) is not None:
            raise PlanningError("replan_every re-plans the rest of a chunk, all of which the search optimises; "
                                "drop --num-optimized or --replan-every")
    if cfg.rank_gate is not None and not getattr(planner_config, "include_mean", False):
        raise PlanningError("rank_gate compares the WAM's chunk with the search's first samples, so the planner "
                            "must score it: drop --no-include-mean or the rank gate")


def check_fits(cfg: PlannedPolicyConfig, chunk: int, planner: Planner, dynamics: Dynamics) -> int:
    """Refuse settings of ``cfg`` that the ``planner``, the ``dynamics`` or the WAM's ``chunk`` cannot run, in one
    line that names the fix -> the steps between planning points (the chunk, or ``replan_every``)."""
    check_settings(cfg, chunk, planner.config)
    frameskip = getattr(dynamics, "frameskip", chunk)
    if dynamics.needs_history:
        check_frameskip(frameskip, chunk)
    period = chunk
    if cfg.replan_every is not None:
        period = cfg.replan_every
        check_replan_every(period, chunk, frameskip if dynamics.needs_history else None)
    if cfg.bias_correction > 0 and dynamics.needs_history:
        if dynamics.covered(chunk) != chunk:
            raise PlanningError(f"bias_correction compares the model's prediction with the frame at the next "
                                f"boundary, but its frameskip {frameskip} does not divide the "
                                f"{chunk}-step chunk; drop --bias-correction")
        if cfg.replan_every is not None:
            raise PlanningError("bias_correction measures the error of whole chunks; drop --replan-every or "
                                "--bias-correction")
    from wamplan.planning.dynamics import LearnedDynamics

    if cfg.disagreement_weight > 0 and isinstance(dynamics, LearnedDynamics) and not dynamics.spreads:
        raise PlanningError("disagreement_weight needs an ensemble of world models or one with a spread head, got one "
                            "without; pass several checkpoints joined by + (eval --wm-augmented A+B, serve "
                            "--world-model A+B), a model trained with `wm train --spread-weight`, or set it to 0")
    return period
