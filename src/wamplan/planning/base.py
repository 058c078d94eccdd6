"""The planner interface shared by CEM and MPPI, and the planner registry.

A planner is PURE: it gets the WAM's seed chunk and an ``objective`` and returns actions. It never
logs, steps a simulator or checks success; it returns plain statistics for the caller to log.

    planner = make_planner("cem", CEMConfig(num_optimized=15))
    result = planner.plan(wam_actions, objective, seed=0)   # wam_actions: (16, 5)
    env_actions = result.actions                             # (16, 5): 15 planned + the WAM's last

``objective(candidates)`` maps a batch of candidate (partial) chunks ``(B, H_opt, A)`` to costs
``(B,)``, lower is better. The caller builds it (dynamics rollout + cost, e.g.
``patch_cost(rollout(candidates), target)``); every candidate of one iteration arrives in ONE call,
so a world model can roll them out as one batch. When ``num_optimized < H`` the objective sees only
the optimised prefix: it appends the seed's trailing actions itself if its dynamics needs them.
"""

from __future__ import annotations

import abc
import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, ClassVar

import torch
from torch import Tensor

from wamplan.config import ConfigError, from_dict, require
from wamplan.planning.configs import SamplingConfig, register_planner_config
from wamplan.registry import Registry

if TYPE_CHECKING:
    from wamplan.envs.spec import TaskSpec

Objective = Callable[[Tensor], Tensor]  # candidates (B, H_opt, A) -> costs (B,)


@dataclass(frozen=True)
class IterationStats:
    """Cost statistics of one iteration's scored candidates (plain floats, ready to log)."""

    iteration: int
    cost_mean: float  # mean cost over all B candidates (NaN if the objective returned NaN)
    cost_min: float  # lowest cost this iteration
    elite_cost_mean: float  # CEM: mean cost of the elites; MPPI: weight-averaged cost
    mean_cost: float  # cost of the current mean (candidate 0); NaN when include_mean is False
    std_mean: float  # mean of sigma AFTER this iteration's update, over (H_opt, A)


@dataclass
class PlanResult:
    """What a planner returns. Tensors live on the device of the seed actions."""

    actions: Tensor  # (H, A): the final mean for the first H_opt steps, then the seed's trailing actions
    mean: Tensor  # (H_opt, A) final mean, clipped to the bounds (what the paper returns)
    std: Tensor  # (H_opt, A) final sigma
    best_actions: Tensor  # (H_opt, A) the lowest-cost candidate ever scored (NOT what is returned)
    best_cost: float  # its cost; the final mean itself is never scored (it is refit after the last scoring)
    history: list[IterationStats]
    num_evaluations: int  # candidates scored in total = iterations * num_candidates
    seed_rank: float = float("nan")  # share of iteration 0's samples scored below the seed; NaN without include_mean

    @property
    def seed_cost(self) -> float:
        """Cost of the (clipped) seed, scored as candidate 0 of iteration 0; NaN without include_mean."""
        return self.history[0].mean_cost

    def stats(self) -> dict[str, Any]:
        """Plain-data summary for logging (no tensors)."""
        return {"best_cost": self.best_cost, "seed_cost": self.seed_cost, "seed_rank": self.seed_rank,
                "num_evaluations": self.num_evaluations,
                "history": [dataclasses.asdict(h) for h in self.history]}


class Planner(abc.ABC):
    """Refines a seed chunk against an objective. Subclasses register with ``@register_planner``."""

    name: ClassVar[str] = ""
    config_cls: ClassVar[type] = SamplingConfig

    def __init__(self, config: Any = None) -> None:
        config = self.config_cls() if config is None else config
        require(isinstance(config, self.config_cls), f"planner '{self.name}' needs a "
                f"{self.config_cls.__name__}, got {type(config).__name__}")
        self.config = config

    def for_task(self, task: TaskSpec) -> Planner:
        """This planner for actions of ``task``: rebuilt with its config's task settings filled
        (``config.for_task``), or itself when its config leaves none to the task."""
        fill = getattr(self.config, "for_task", None)
        config = self.config if fill is None else fill(task)
        return self if config is self.config else type(self)(config)

    @abc.abstractmethod
    def plan(self, seed_actions: Tensor, objective: Objective, *,
             generator: torch.Generator | None = None, seed: int | None = None) -> PlanResult:
        """Refine ``seed_actions`` (H, A). ``generator`` or ``seed`` makes the sampling reproducible
        (neither: torch's global RNG)."""


class SamplingPlanner(Planner):
    """The loop CEM and MPPI share: sample around mu, clip, score in one call, update (mu, sigma)."""

    config: SamplingConfig

    @abc.abstractmethod
    def _update(self, cand: Tensor, costs: Tensor, mu: Tensor, sigma: Tensor
                ) -> tuple[Tensor, Tensor, Tensor]:
        """From scored candidates (B, H_opt, A) and costs (B,): new mu, new sigma (H_opt, A) and the
        'elite' cost statistic (0-d tensor)."""

    # Hooks for planners that search some dimensions differently (e.g. a discrete gripper); no-ops here.
    def _begin(self, mu: Tensor, sigma: Tensor, frozen: Tensor) -> None:
        """Once per plan, before sampling: may set up state and edit mu, sigma, frozen (H_opt, A) in place."""

    def _shape_candidates(self, cand: Tensor, gen: torch.Generator | None) -> Tensor:
        """Each iteration, the candidates (B, H_opt, A) before clipping and scoring (candidate 0 = the mean
        when include_mean)."""
        return cand

    def _refit(self, cand: Tensor, costs: Tensor, mu: Tensor, sigma: Tensor) -> tuple[Tensor, Tensor]:
        """Each iteration, after the update: the final say on mu and sigma (H_opt, A)."""
        return mu, sigma

    def plan(self, seed_actions: Tensor, objective: Objective, *,
             generator: torch.Generator | None = None, seed: int | None = None) -> PlanResult:
        cfg = self.config
        lo, hi = cfg.action_low, cfg.action_high
        mu, sigma0 = self._initial_distribution(seed_actions)  # (H_opt, A) each, float32
        sigma, frozen = sigma0, sigma0 == 0  # (H_opt, A); frozen dims never get the min_std floor
        self._begin(mu, sigma, frozen)
        gen = _make_generator(generator, seed, seed_actions.device)
        n_sampled = cfg.num_candidates - int(cfg.include_mean)
        best_cost = torch.full((), float("inf"), device=mu.device)
        best = mu
        rows, seed_rank = [], torch.tensor(float("nan"))
        for it in range(cfg.iterations):
            noise = candidate_noise((n_sampled, *mu.shape), gen, mu.device)  # (B', H_opt, A)
            cand = mu + sigma * noise  # (B', H_opt, A)
            if cfg.include_mean:
                cand = torch.cat([mu.unsqueeze(0), cand])  # (B, H_opt, A), candidate 0 = mean
            cand = self._shape_candidates(cand, gen)  # (B, H_opt, A)
            cand = cand.clamp(lo, hi)  # clip BEFORE scoring: the refit sees what was scored
            costs = _score(objective, cand)  # (B,)
            if it == 0 and cfg.include_mean:  # how many random neighbours of the seed the objective prefers to it
                seed_rank = (costs[1:] < costs[0]).float().mean()
            i_min = torch.argmin(torch.nan_to_num(costs, nan=float("inf")))
            improved = costs[i_min] < best_cost
            best_cost = torch.where(improved, costs[i_min], best_cost)
            best = torch.where(improved, cand[i_min], best)  # (H_opt, A)
            mu, sigma, elite_stat = self._update(cand, costs, mu, sigma)
            sigma = torch.where(frozen, sigma, sigma.clamp_min(cfg.min_std))  # (H_opt, A)
            mu, sigma = self._refit(cand, costs, mu, sigma)
            mean_cost = costs[0] if cfg.include_mean else torch.tensor(float("nan"), device=mu.device)
            rows.append(torch.stack([costs.mean(), costs.min(), elite_stat, mean_cost, sigma.mean()]))
        mu = mu.clamp(lo, hi)  # a no-op for CEM (mean of clipped elites); kept for any update rule
        history = [IterationStats(i, *r) for i, r in enumerate(torch.stack(rows).tolist())]  # one sync
        n_opt = mu.shape[0]
        actions = seed_actions.clone()  # (H, A)
        actions[:n_opt] = mu.to(seed_actions.dtype)
        return PlanResult(actions=actions, mean=mu, std=sigma, best_actions=best,
                          best_cost=float(best_cost), history=history,
                          num_evaluations=cfg.iterations * cfg.num_candidates, seed_rank=float(seed_rank))

    def _initial_distribution(self, seed_actions: Tensor) -> tuple[Tensor, Tensor]:
        """mu0 = the seed's first H_opt actions (clipped), sigma0 = init std: (H_opt, A) each."""
        cfg = self.config
        if seed_actions.dim() != 2 or not seed_actions.is_floating_point():
            raise ValueError(f"seed_actions must be a float (H, A) tensor, got {seed_actions.dtype} "
                             f"{tuple(seed_actions.shape)}; pass one chunk, not a batch")
        h, a = seed_actions.shape
        n_opt = h if cfg.num_optimized is None else cfg.num_optimized
        if n_opt > h:
            raise ConfigError(f"num_optimized={n_opt} exceeds the chunk length {h}; "
                              f"set num_optimized <= {h} (or None for all)")
        std = cfg.init_std_per_dim or (cfg.init_std,) * a
        if len(std) != a:
            raise ConfigError(f"init_std_per_dim has {len(std)} entries but actions have {a} "
                              f"dimensions; give one std per dimension")
        mu = seed_actions[:n_opt].to(torch.float32).clamp(cfg.action_low, cfg.action_high)  # (H_opt, A)
        sigma = torch.tensor(std, dtype=torch.float32, device=mu.device).expand(n_opt, a)  # (H_opt, A)
        return mu, sigma.clone()


def _make_generator(generator: torch.Generator | None, seed: int | None,
                    device: torch.device) -> torch.Generator | None:
    if generator is not None and seed is not None:
        raise ValueError("pass either generator or seed to plan(), not both")
    if seed is not None:
        return torch.Generator(device=device).manual_seed(seed)
    return generator


def candidate_noise(shape: tuple[int, ...], gen: torch.Generator | None, device: torch.device) -> Tensor:
    """Standard normal noise (the paper's i.i.d. samples) on ``device``, drawn on the generator's own device
    (so a CPU generator gives the same numbers whatever the planning device)."""
    if gen is None:
        return torch.randn(shape, device=device)
    return torch.randn(shape, generator=gen, device=gen.device).to(device)


def _score(objective: Objective, cand: Tensor) -> Tensor:
    costs = objective(cand)
    if not isinstance(costs, Tensor) or costs.shape != (cand.shape[0],):
        got = tuple(costs.shape) if isinstance(costs, Tensor) else type(costs).__name__
        raise ValueError(f"the objective must return costs of shape ({cand.shape[0]},) for candidates "
                         f"{tuple(cand.shape)}, got {got}; reduce the cost to one scalar per candidate")
    return costs.to(device=cand.device, dtype=torch.float32)


class _PlannerRegistry(Registry):
    """The planners by name; registering one (``register_planner``) also enters its ``config_cls`` in
    ``PLANNER_CONFIGS``, the torch-free registry the command line's options and ``EvalConfig`` are built from."""

    def register(self, name: str) -> Callable[[type], type]:
        enter = super().register(name)

        def deco(cls: type) -> type:
            register_planner_config(name, cls.config_cls)
            return enter(cls)

        return deco


PLANNERS = _PlannerRegistry("planner", set_name=True, modules=(
    "wamplan.planning.cem", "wamplan.planning.mppi", "wamplan.planning.cem_gripper", "wamplan.planning.defaults"))
register_planner = PLANNERS.register  # class decorator: make a planner (with its config_cls) constructible by name


def make_planner(name: str, config: Any = None) -> Planner:
    """The planner ``name`` built from ``config``: its config dataclass, a dict of overrides, or None
    (the defaults)."""
    cls = PLANNERS.lookup(name)
    if isinstance(config, dict):
        config = from_dict(cls.config_cls, config)
    return cls(config)
