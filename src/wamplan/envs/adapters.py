"""How a :class:`~wamplan.envs.core.TaskEnv` reads a task from its ManiSkill env: proprioception, the evaluation
(success, stage flags, continuous metrics), privileged state, and the ``gym.make`` keyword arguments.

:class:`ManiSkillAdapter` serves any ManiSkill 3 task: proprio is the robot's joint positions followed by the TCP
pose (xyz + wxyz) where the agent has a TCP, success and stages come from ``evaluate()``. A task with more to say
subclasses it (``CubeInsertionAdapter``) and names the subclass in its spec's ``adapter``.
"""

from __future__ import annotations

import importlib
from typing import Any

import numpy as np

from wamplan.envs.config import EnvConfig
from wamplan.envs.spec import TaskSpec


def _first(x) -> np.ndarray:
    """The first (only) env's entry of a batched ManiSkill tensor, as numpy."""
    return x[0].detach().cpu().numpy()


class ManiSkillAdapter:
    def __init__(self, spec: TaskSpec, base: Any):
        self.spec, self.base = spec, base  # base: the unwrapped ManiSkill env

    @staticmethod
    def make_kwargs(spec: TaskSpec, config: EnvConfig) -> dict[str, Any]:
        """``gym.make`` keyword arguments beyond the id, obs/reward mode, backends and ``num_envs``."""
        kw = {k: v for k, v in config.task_kwargs().items() if k not in ("task", "env_id", "camera_size")}
        return dict(spec.env_kwargs, **kw, sensor_configs=dict(width=config.camera_size, height=config.camera_size))

    def proprio(self) -> np.ndarray:
        """(P,) float32: joint positions, then the TCP pose (xyz, wxyz) where the agent has a TCP."""
        agent = self.base.agent
        parts = [_first(agent.robot.get_qpos())]
        if hasattr(agent, "tcp"):
            parts.append(_first(agent.tcp.pose.raw_pose))
        return np.concatenate(parts).astype(np.float32)

    def raw_evaluation(self) -> dict[str, Any]:
        """The env's ``evaluate()`` (batched tensors); a subclass adds the flags its task lacks."""
        return self.base.evaluate()

    def evaluate(self) -> dict[str, Any]:
        """success, the spec's stage flags (bool) and metrics (float) of the current state."""
        ev = self.raw_evaluation()
        out = {s: bool(_first(ev[s])) for s in self.spec.stages}
        out.update({m: float(_first(ev[m])) for m in self.spec.metrics})
        out["success"] = bool(_first(ev["success"]))
        return out

    def privileged_state(self, evaluation: dict[str, Any]) -> dict[str, np.ndarray]:
        """What scripted experts and diagnostics may read (never a policy that acts from images)."""
        state = dict(stages=np.array([evaluation.get(s, False) for s in self.spec.stages], bool))
        if hasattr(self.base.agent, "tcp"):
            state["tcp_pose"] = _first(self.base.agent.tcp.pose.raw_pose).copy()
        return state


def adapter_class(spec: TaskSpec) -> type[ManiSkillAdapter]:
    """The adapter class a spec names (``module:Class``)."""
    module, _, name = spec.adapter.partition(":")
    return getattr(importlib.import_module(module), name)


class PegInsertionSideAdapter(ManiSkillAdapter):
    """PegInsertionSide-v1 plus a ``grasped`` flag (ManiSkill's own grasp test on the peg, fingers within 20° of
    its axis, as its dense reward uses), so an episode's outcome says whether the peg was ever held."""

    def raw_evaluation(self) -> dict[str, Any]:
        return dict(self.base.evaluate(), grasped=self.base.agent.is_grasping(self.base.peg, max_angle=20))


class StackCubeAdapter(ManiSkillAdapter):
    """StackCube-v1 plus its cubes as privileged state: ``cube_pose`` the cube to pick (cubeA), ``target_pose`` the
    cube to stack it on (cubeB), recorded in the stores."""

    def privileged_state(self, evaluation: dict[str, Any]) -> dict[str, np.ndarray]:
        state = super().privileged_state(evaluation)
        state["cube_pose"] = _first(self.base.cubeA.pose.raw_pose).copy()
        state["target_pose"] = _first(self.base.cubeB.pose.raw_pose).copy()
        return state
