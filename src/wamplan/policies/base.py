"""The policy interface every actor in wamplan implements: scripted experts, noise explorers,
WAMs run open loop, and planned WAMs.

A policy sees an :class:`~wamplan.envs.spec.Observation` per control step and returns one action of its
task: ``TaskSpec.action_dim`` entries in [-1, 1], the gripper's (where the task has one) +1 = open, -1 = close
(the cube task's: ``(dx, dy, dz, dyaw, gripper)``).
Images are rendered only on the steps a policy asks for (``wants_images``): rendering three
cameras costs ~150 ms on this CPU, stepping physics ~4 ms.

A registered policy that acts in one task takes it as the constructor argument ``task`` (a
:class:`~wamplan.envs.spec.TaskSpec`); :func:`make_policy` passes it on. Built without one, it acts in
:data:`DEFAULT_TASK`.
"""

from __future__ import annotations

import abc
import inspect
from typing import Any, ClassVar

import numpy as np

from wamplan.envs.spec import Observation, TaskSpec, get_task
from wamplan.registry import Registry


class Policy(abc.ABC):
    """One action per control step. Subclasses set ``name`` and register with ``@register_policy``."""

    name: ClassVar[str] = ""

    def reset(self, seed: int | None = None) -> None:
        """Start a new episode; ``seed`` makes any internal randomness reproducible."""

    def wants_images(self, step: int) -> bool:
        """Whether the observation at ``step`` must carry rendered images."""
        return False

    @abc.abstractmethod
    def act(self, obs: Observation) -> np.ndarray:
        """The action for ``obs``: (A,) float32 in [-1, 1]."""

    def info(self) -> dict[str, Any]:
        """Per-episode diagnostics (e.g. per-chunk timings); empty by default."""
        return {}

    def config_dict(self) -> dict[str, Any]:
        """The policy's configuration, stored as provenance with collected data."""
        return {"name": self.name}


POLICIES = Registry("policy", set_name=True, modules=("wamplan.policies.expert", "wamplan.policies.noise",
                                                     "wamplan.policies.replay"))
register_policy = POLICIES.register  # class decorator: make a policy constructible by name


from wamplan.envs.spec import DEFAULT_TASK  # noqa: E402,F401  (what a policy built without a task acts in)


def policy_task(task: TaskSpec | None) -> TaskSpec:
    """The task a policy built with ``task`` acts in (:data:`DEFAULT_TASK` for None)."""
    return get_task(task if task is not None else DEFAULT_TASK)


def make_policy(name: str, task: TaskSpec | None = None, **kwargs: Any) -> Policy:
    """The registered policy ``name`` built with ``kwargs``; one whose constructor takes ``task`` also gets the
    task it acts in (the others act the same in any task)."""
    cls = POLICIES.lookup(name)
    if task is not None and "task" in inspect.signature(cls).parameters:
        kwargs["task"] = task
    return cls(**kwargs)
