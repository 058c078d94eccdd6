"""The policy interface every actor in wamplan implements: scripted experts, noise explorers,
WAMs run open loop, and planned WAMs.

A policy sees an :class:`~wamplan.envs.contract.Observation` per control step and returns one 5-D
action in [-1, 1]: ``(dx, dy, dz, dyaw, gripper)``, gripper +1 = open, -1 = close (the task's
contract, ``wamplan.envs.contract``).
Images are rendered only on the steps a policy asks for (``wants_images``): rendering three
cameras costs ~150 ms on this CPU, stepping physics ~4 ms.
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar

import numpy as np

from wamplan.envs.contract import Observation
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
        """The action for ``obs``: (5,) float32 in [-1, 1]."""

    def info(self) -> dict[str, Any]:
        """Per-episode diagnostics (e.g. per-chunk timings); empty by default."""
        return {}

    def config_dict(self) -> dict[str, Any]:
        """The policy's configuration, stored as provenance with collected data."""
        return {"name": self.name}


POLICIES = Registry("policy", set_name=True, modules=("wamplan.policies.expert", "wamplan.policies.noise"))
register_policy = POLICIES.register  # class decorator: make a policy constructible by name


def make_policy(name: str, **kwargs: Any) -> Policy:
    return POLICIES.lookup(name)(**kwargs)
