"""How long one chunk's search takes in a learned world model: the figure the world-model benchmark reports
beside its accuracy (``wamplan wm eval``) and ``benchmarks/wm_variants.py`` compares across variants.

The search is ``wamplan eval``'s: the default planner (32 candidates x 4 iterations unless told otherwise), the
patch cost (eq. 3), :class:`~wamplan.planning.dynamics.LearnedDynamics` (the KV-cached rollout), one chunk of
16 steps from a context of H_ctx frames. The median of ``repeats`` timed searches after one warm-up.
"""

from __future__ import annotations

import dataclasses
import statistics
import time
from typing import Any, Callable

import torch

from wamplan.planning.base import PLANNERS, make_planner
from wamplan.planning.costs import make_cost
from wamplan.planning.defaults import DEFAULT_PLANNER
from wamplan.planning.dynamics import LearnedDynamics, PlanningContext

CHUNK = 16  # steps of a WAM chunk


def planner_settings(name: str = DEFAULT_PLANNER, candidates: int = 32, iterations: int = 4) -> dict[str, Any]:
    """The planner's settings at ``candidates`` x ``iterations`` (CEM's elites: a quarter, the paper's 8 of 32)."""
    settings: dict[str, Any] = dict(num_candidates=candidates, iterations=iterations)
    if "num_elites" in {f.name for f in dataclasses.fields(PLANNERS.lookup(name).config_cls)}:
        settings["num_elites"] = max(1, candidates // 4)
    return settings


def sync(device: torch.device) -> None:
    """Wait for the work queued on ``device`` (an accelerator's; a CPU runs synchronously)."""
    if device.type != "cpu":
        torch.accelerator.synchronize(device)


def timed(fn: Callable[[], Any], device: torch.device) -> float:
    """Wall seconds of ``fn()``, ``device`` synchronised before and after."""
    sync(device)
    t0 = time.perf_counter()
    fn()
    sync(device)
    return time.perf_counter() - t0


def median_time(fn: Callable[[], Any], repeats: int, device: torch.device, warmup: int = 1) -> float:
    """Median wall seconds of ``fn()`` over ``repeats`` calls (:func:`timed`) after ``warmup`` untimed calls."""
    for _ in range(warmup):
        fn()
    return statistics.median(timed(fn, device) for _ in range(repeats))


def make_search(model, context: PlanningContext, target: torch.Tensor, planner: str = DEFAULT_PLANNER,
                candidates: int = 32, iterations: int = 4, chunk: int = CHUNK) -> Callable[[int], float]:
    """A function ``search(seed) -> seconds`` that runs and times one search over a ``chunk``-step chunk in
    ``model`` (a ``WorldModelPredictor``) from ``context`` towards ``target`` (V, N, D), prefix encoding included."""
    dyn = LearnedDynamics(model)
    optimiser = make_planner(planner, planner_settings(planner, candidates, iterations))
    cost = make_cost("patch")
    target = target.to(dyn.device, next(model.parameters()).dtype)
    seed_actions = torch.zeros(dyn.covered(chunk), model.cfg.action_dim, device=dyn.device)  # (L, A)

    def run(seed: int) -> None:
        dyn.prepare(context)
        optimiser.plan(seed_actions, lambda c: cost(dyn.terminal(c), target), seed=seed)

    def search(seed: int) -> float:
        return timed(lambda: run(seed), dyn.device)

    return search


def plan_seconds(model, context: PlanningContext, target: torch.Tensor, planner: str = DEFAULT_PLANNER,
                 candidates: int = 32, iterations: int = 4, repeats: int = 3, chunk: int = CHUNK) -> float:
    """Median seconds of one search (:func:`make_search`); the first of ``repeats`` + 1 searches is a warm-up."""
    search = make_search(model, context, target, planner, candidates, iterations, chunk)
    return statistics.median([search(i) for i in range(repeats + 1)][1:])
