"""The planners' settings, and the registry of those settings by planner name, importable without torch: a
command builds its options from them and refuses bad settings before torch loads. Each planner's module
(``cem``, ``mppi``, ``cem_gripper``, ``defaults``) holds its search and takes its config from here;
``register_planner`` (``wamplan.planning.base``) enters a new planner's config in :data:`PLANNER_CONFIGS`, so its
options appear on the command line as the built-in planners' do. ``TEMPERATURE`` pins the temperature of wamplan's
default planner (MPPI, ``DEFAULT_PLANNER``) here, so that it stays the same planner if MPPI's default changes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from wamplan.config import ConfigError, check_numbers, field, require, with_default
from wamplan.registry import DuplicateName, Registry

if TYPE_CHECKING:
    from wamplan.envs.spec import TaskSpec


@dataclass(frozen=True)
class SamplingConfig:
    """Fields shared by the Gaussian sampling planners (CEM, MPPI). Defaults follow the paper."""

    num_candidates: int = field(32, "candidates scored per iteration (the current mean included)")
    iterations: int = field(4, "optimisation iterations")
    init_std: float = field(0.10, "initial sigma for every action dimension")
    init_std_per_dim: tuple[float, ...] = field(
        (), "initial sigma per action dimension (length A), overriding init_std; e.g. "
        "0.1 0.1 0.1 0.1 0.0 freezes the gripper at the WAM's value. Empty = uniform init_std")
    min_std: float = field(
        0.0, "floor on sigma after each update (0 = none, as in the paper); dimensions whose initial "
        "sigma is 0 stay frozen")
    include_mean: bool = field(True, "score the current mean as candidate 0 of every iteration")
    num_optimized: int | None = field(
        None, "optimise the first N actions of the chunk and keep the rest from the seed "
        "(None = all; 15 for the paper's frameskip 5 with 16-step chunks)")
    action_low: float = field(-1.0, "lower action bound; candidates are clipped to it")
    action_high: float = field(1.0, "upper action bound; candidates are clipped to it")

    def __post_init__(self) -> None:
        check_numbers(self)
        require(self.num_candidates >= 2, f"num_candidates must be >= 2, got {self.num_candidates}")
        require(self.iterations >= 1, f"iterations must be >= 1, got {self.iterations}; "
                "to skip planning, execute the WAM's chunk directly")
        require(self.init_std > 0, f"init_std must be > 0, got {self.init_std}; use init_std_per_dim "
                "to freeze single dimensions")
        require(all(s >= 0 for s in self.init_std_per_dim) and
                (not self.init_std_per_dim or max(self.init_std_per_dim) > 0),
                f"init_std_per_dim entries must be >= 0 with at least one > 0, got {self.init_std_per_dim}")
        require(self.min_std >= 0, f"min_std must be >= 0, got {self.min_std}")
        require(self.num_optimized is None or self.num_optimized >= 1,
                f"num_optimized must be None (all) or >= 1, got {self.num_optimized}")
        require(self.action_low < self.action_high,
                f"action_low ({self.action_low}) must be < action_high ({self.action_high})")

    def for_task(self, task: TaskSpec) -> SamplingConfig:
        """This config with the settings it leaves to the task (None, or an empty tuple where documented) filled
        from ``task``; a config that leaves none returns itself. One line when the task cannot fill them.
        Here: an empty ``init_std_per_dim`` becomes ``init_std`` times the task's ``sigma_scale`` (an explicit
        ``init_std_per_dim`` is taken as it is): one line if it has not one entry per action entry, or if
        ``num_optimized`` exceeds the task's chunk."""
        require(not self.init_std_per_dim or len(self.init_std_per_dim) == task.action_dim,
                f"init_std_per_dim has {len(self.init_std_per_dim)} entries but task '{task.name}' has "
                f"{task.action_dim}-D actions; give one std per action entry")
        require(self.num_optimized is None or self.num_optimized <= task.chunk_len,
                f"num_optimized={self.num_optimized} exceeds task '{task.name}''s {task.chunk_len}-step chunk; "
                f"set it to at most {task.chunk_len} (or None for all)")
        if self.init_std_per_dim or all(s == 1 for s in task.sigma_scale):
            return self
        scaled = tuple(round(self.init_std * s, 12) for s in task.sigma_scale)  # (A,)
        return dataclasses.replace(self, init_std_per_dim=scaled)


@dataclass(frozen=True)
class CEMConfig(SamplingConfig):
    """CEM hyperparameters; defaults are the paper's (32 candidates = mean + 31, 8 elites, 4 iterations,
    sigma0 = 0.10). Set ``num_optimized=15`` for frameskip 5 (the trailing action stays the WAM's)."""

    num_elites: int = field(8, "lowest-cost candidates mu and sigma are refit to")
    std_ddof: int = field(0, "delta degrees of freedom of the elite std: 0 = population std, "
                             "1 = sample std as in DINO-WM")

    def __post_init__(self) -> None:
        check_numbers(self)
        super().__post_init__()
        require(self.std_ddof in (0, 1), f"std_ddof must be 0 or 1, got {self.std_ddof}")
        require(self.std_ddof < self.num_elites <= self.num_candidates,
                f"num_elites must be in [{self.std_ddof + 1}, num_candidates={self.num_candidates}], "
                f"got {self.num_elites}; lower num_elites or raise num_candidates")


@dataclass(frozen=True)
class MPPIConfig(SamplingConfig):
    """MPPI hyperparameters; sampling fields (candidates, iterations, sigma0, bounds) as in CEM."""

    temperature: float = field(0.1, "softmax temperature of the path-integral weights")
    normalize_costs: bool = field(True, "divide costs by this iteration's cost range before the "
                                        "softmax, so temperature is scale-free")
    momentum: float = field(0.0, "new mu = momentum * old mu + (1 - momentum) * weighted mean")
    update_std: bool = field(True, "refit sigma to the weighted std of the candidates; off = keep sigma0")

    def __post_init__(self) -> None:
        check_numbers(self)
        super().__post_init__()
        require(self.temperature > 0, f"temperature must be > 0, got {self.temperature}")
        require(0.0 <= self.momentum < 1.0, f"momentum must be in [0, 1), got {self.momentum}")


DEFAULT_PLANNER = "wamplan"  # what `wamplan eval` plans with when no --planner is given
TEMPERATURE = 0.1  # the softmax temperature of wamplan's MPPI


@dataclass(frozen=True)
class WamplanConfig(MPPIConfig):
    """MPPI's config with the temperature pinned at :data:`TEMPERATURE`; every MPPI option still applies."""

    temperature: float = with_default(MPPIConfig, "temperature", TEMPERATURE)


@dataclass(frozen=True)
class CEMGripperConfig(CEMConfig):
    """CEM over the continuous dimensions plus a categorical search over gripper switch times."""

    gripper_dim: int | None = field(None, "index of the gripper in the action vector (its Gaussian sigma is unused); "
                                          "None = the task's")
    gripper_open: float | None = field(None, "the gripper command that means open; None = the task's")
    gripper_closed: float | None = field(None, "the gripper command that means closed; None = the task's")
    gripper_prior_steps: float = field(
        16.0, "width of the initial categorical prior: logit = -(steps differing from the WAM's gripper) / this")
    gripper_smoothing: float = field(
        0.3, "categorical refit: p = (1 - s) * elite frequencies + s * previous p (0 = plain CEM refit)")

    def __post_init__(self) -> None:
        check_numbers(self)
        super().__post_init__()
        require(self.gripper_open is None or self.gripper_open != self.gripper_closed,
                "gripper_open and gripper_closed must differ")
        require(self.gripper_prior_steps > 0, f"gripper_prior_steps must be > 0, got {self.gripper_prior_steps}")
        require(0.0 <= self.gripper_smoothing < 1.0,
                f"gripper_smoothing must be in [0, 1), got {self.gripper_smoothing}")

    def for_task(self, task: TaskSpec) -> CEMGripperConfig:
        """The gripper settings left None filled from ``task``, and sigma scaled as in
        :meth:`SamplingConfig.for_task`; one line if the task has no gripper."""
        cfg = super().for_task(task)
        require(cfg.gripper_dim is None or -task.action_dim <= cfg.gripper_dim < task.action_dim,
                f"gripper_dim {cfg.gripper_dim} is not an entry of task '{task.name}''s {task.action_dim}-D actions; "
                f"give 0-{task.action_dim - 1} (or -1 for the last; none: the task's, {task.gripper_index})")
        unset = {k: v for k, v in (("gripper_dim", task.gripper_index), ("gripper_open", task.gripper_open),
                                   ("gripper_closed", task.gripper_closed)) if getattr(cfg, k) is None}
        if not unset:
            return cfg
        if task.gripper_index is None:
            raise ConfigError(f"planner cem-gripper searches when the gripper opens and closes, but task "
                              f"'{task.name}' has no gripper; use --planner cem (the same search without the "
                              f"gripper's categories)")
        return dataclasses.replace(cfg, **unset)



PLANNER_CONFIGS = Registry("planner")  # planner name -> its config class (the built-in ones above, then plug-ins)
PLANNER_CONFIGS.update({"cem": CEMConfig, "mppi": MPPIConfig, DEFAULT_PLANNER: WamplanConfig, "cem-gripper": CEMGripperConfig})


def register_planner_config(name: str, config_cls: Any) -> None:
    """Enter planner ``name``'s config class; the same class again is a no-op, another one a ``DuplicateName``."""
    have = dict.get(PLANNER_CONFIGS, name)
    if have is not None and have is not config_cls:
        raise DuplicateName(f"planner '{name}' is registered twice (configs {have.__name__}, {config_cls.__name__})")
    PLANNER_CONFIGS[name] = config_cls
