"""``InsertionEnv``: wamplan's wrapper around one ``CubeInsertion-v1`` instance (CPU simulator).

It speaks numpy and :class:`~wamplan.policies.base.Observation`, renders cameras only on demand
(physics ≈ 4 ms a step, three cameras ≈ 150 ms), tracks the furthest stage an episode reached, and
saves/restores complete snapshots, including what ManiSkill's ``get_state_dict`` leaves out
(controller targets, joint drive targets, the step counter).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from wamplan.config import field, require
from wamplan.envs.agent import CONTROL_MODE
from wamplan.envs.contract import ACTION_DIM, CAMERAS, ENV_ID, MAX_EPISODE_STEPS, OUTCOMES, STAGES, Observation


@dataclass(frozen=True)
class EnvConfig:
    camera_size: int = field(224, "rendered image side in pixels, all three cameras")
    clearance: float = field(0.002, "gap between cube and hole wall per side, metres")
    cube_half_size: float = field(0.02, "half the cube's side, metres")
    mount_height: float = field(0.025, "height of the mount (depth of the hole), metres")
    robot_init_qpos_noise: float = field(0.02, "std of the initial joint-angle noise, radians")
    max_episode_steps: int = field(MAX_EPISODE_STEPS, "episodes truncate after this many control steps")
    sim_backend: str = field("physx_cpu", "ManiSkill sim backend (one env per process on the CPU)")
    render_backend: str = field("cpu", "ManiSkill render backend: cpu (lavapipe) or gpu")

    def __post_init__(self):
        require(16 <= self.camera_size <= 1024, f"camera_size must be in [16, 1024], got {self.camera_size}")
        require(0 < self.clearance < self.cube_half_size,
                f"clearance must be in (0, cube_half_size={self.cube_half_size}), got {self.clearance}")
        require(self.max_episode_steps > 0, f"max_episode_steps must be > 0, got {self.max_episode_steps}")

    def task_kwargs(self) -> dict[str, Any]:
        """The kwargs that define the task's physics and pictures (what must match across a dataset)."""
        return dict(camera_size=self.camera_size, clearance=self.clearance, cube_half_size=self.cube_half_size,
                    mount_height=self.mount_height, robot_init_qpos_noise=self.robot_init_qpos_noise,
                    control_mode=CONTROL_MODE, env_id=ENV_ID)


@dataclass
class Snapshot:
    """Everything needed to put the simulator back exactly: physics, controllers, counters."""

    sim: dict
    controllers: dict[str, dict[str, torch.Tensor]]
    drive_targets: torch.Tensor
    step: int
    reached: dict[str, bool]


def _clone(x: Any) -> Any:
    if torch.is_tensor(x):
        return x.clone()
    if isinstance(x, dict):
        return {k: _clone(v) for k, v in x.items()}
    return copy.deepcopy(x)


class InsertionEnv:
    """One CubeInsertion-v1 episode at a time; numpy in, numpy out.

    The methods that change simulator or controller state run with inference mode off, whatever the caller's
    mode: a planner that steps the env inside ``torch.inference_mode()`` would otherwise leave inference tensors
    in the controller, and the next ordinary step would fail on an in-place update.
    """

    def __init__(self, config: EnvConfig | None = None):
        import wamplan.envs.task  # noqa: F401  (registers the task, configures Vulkan)

        self.config = config or EnvConfig()
        kw = self.config.task_kwargs()
        kw.pop("env_id")
        self._gym = gym.make(ENV_ID, obs_mode="state_dict", reward_mode="none", num_envs=1,
                             sim_backend=self.config.sim_backend, render_backend=self.config.render_backend, **kw)
        self.base = self._gym.unwrapped
        self.step_count = 0
        self.seed: int | None = None
        self.reached = {s: False for s in STAGES}
        self._last: dict[str, Any] = {}

    # ------------------------------------------------------------------ episode
    @torch.inference_mode(False)
    def reset(self, seed: int, with_images: bool = False) -> Observation:
        self.seed = int(seed)
        self.base.reset(seed=self.seed)
        self.step_count = 0
        self.reached = {s: False for s in STAGES}
        self._last = self._evaluate()
        return self.observe(with_images)

    @torch.inference_mode(False)
    def step(self, action: np.ndarray, with_images: bool = False) -> tuple[Observation, dict[str, Any]]:
        """Apply one 5-D action (clipped to [-1, 1]); returns the next observation and step info."""
        a = self.check_action(action)
        self.base.step(torch.as_tensor(a[None]))  # (1, 5)
        self.step_count += 1
        self._last = self._evaluate()
        info = dict(self._last, step=self.step_count, truncated=self.step_count >= self.config.max_episode_steps)
        return self.observe(with_images), info

    @staticmethod
    def check_action(action: Any) -> np.ndarray:
        """Validate one action: shape (5,), finite; values outside [-1, 1] are clipped (documented)."""
        a = np.asarray(action, dtype=np.float32)
        if a.shape != (ACTION_DIM,):
            raise ValueError(f"action must have shape ({ACTION_DIM},) = (dx, dy, dz, dyaw, gripper), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action must be finite, got {a.tolist()}; check the policy's output for NaN/inf")
        return np.clip(a, -1.0, 1.0)

    def _evaluate(self) -> dict[str, Any]:
        ev = self.base.evaluate()
        flags = {s: bool(ev[s][0]) for s in STAGES}
        for s in STAGES:
            self.reached[s] |= flags[s]
        return dict(flags, success=flags["seated"], cube_xy_error=float(ev["cube_xy_error"][0]),
                    cube_yaw_error=float(ev["cube_yaw_error"][0]))

    def outcome(self) -> str:
        """The episode's outcome so far: success, or the furthest stage reached before failing."""
        r = self.reached
        if self._last.get("success"):
            return "success"
        if r["descended"]:
            return "descended_not_seated"
        if r["aligned"]:
            return "aligned_not_descended"
        if r["lifted"]:
            return "lifted_not_aligned"
        return "never_lifted"

    @property
    def success(self) -> bool:
        return bool(self._last.get("success", False))

    # ------------------------------------------------------------------ observations
    def proprio(self) -> np.ndarray:
        """(10,) float32: gripper width, TCP xyz, first two columns of the TCP rotation matrix."""
        agent = self.base.agent
        qpos = agent.robot.get_qpos()[0]  # (9,)
        pose = agent.tcp_pose
        rot = pose.to_transformation_matrix()[0, :3, :3]  # (3, 3)
        six = rot[:, :2].T.reshape(6)  # columns 0 and 1, each (3,)
        return torch.cat([(qpos[-2] + qpos[-1]).reshape(1), pose.p[0], six]).numpy().astype(np.float32)

    def privileged_state(self) -> dict[str, np.ndarray]:
        b = self.base
        return dict(tcp_pose=b.agent.tcp_pose.raw_pose[0].numpy().copy(),
                    cube_pose=b.cube.pose.raw_pose[0].numpy().copy(),
                    hole_pos=np.array([*b.hole_xy.tolist(), b.mount_height], dtype=np.float32),
                    cube_half_size=np.float32(b.cube_half_size),
                    stages=np.array([self._last.get(s, False) for s in STAGES], bool))

    def sim_state(self) -> np.ndarray:
        """ManiSkill's flat physics state (S,) float32: enough to restore poses and velocities and re-render."""
        return self.base.get_state()[0].numpy().astype(np.float32)

    def drive_targets(self) -> np.ndarray:
        return self.base.agent.robot.get_drive_targets()[0].numpy().astype(np.float32)

    def render(self, cameras: tuple[str, ...] = CAMERAS) -> dict[str, np.ndarray]:
        """Render the current state: camera -> (H, W, 3) uint8."""
        b = self.base
        b.scene.update_render(update_sensors=True, update_human_render_cameras=False)
        out = {}
        for name in cameras:
            cam = b.scene.sensors[name]
            cam.capture()
            rgb = cam.get_obs(rgb=True, depth=False, position=False, segmentation=False)["rgb"]  # (1, H, W, 3)
            out[name] = rgb[0].numpy().copy()
        return out

    def observe(self, with_images: bool = False) -> Observation:
        return Observation(step=self.step_count, proprio=self.proprio(),
                           images=self.render() if with_images else None, state=self.privileged_state())

    # ------------------------------------------------------------------ snapshots
    def _controllers(self) -> dict[str, Any]:
        return self.base.agent.controller.controllers

    @torch.inference_mode(False)
    def snapshot(self) -> Snapshot:
        ctrl = {}
        for name, c in self._controllers().items():
            ctrl[name] = {k: _clone(getattr(c, k)) for k in ("_target_qpos", "_start_qpos", "_target_pose", "_step")
                          if getattr(c, k, None) is not None}
        return Snapshot(sim=_clone(self.base.get_state_dict()), controllers=ctrl,
                        drive_targets=self.base.agent.robot.get_drive_targets().clone(),
                        step=self.step_count, reached=dict(self.reached))

    @torch.inference_mode(False)
    def restore(self, snap: Snapshot) -> None:
        """Put the simulator back to ``snap``. Restore again before re-executing: PhysX keeps hidden
        solver state, so a restored rollout can differ by ~1e-3 m from one that was never restored."""
        self.base.set_state_dict(_clone(snap.sim))
        for name, c in self._controllers().items():
            for k, v in snap.controllers[name].items():
                setattr(c, k, _clone(v))
        robot = self.base.agent.robot
        robot.set_joint_drive_targets(snap.drive_targets.clone(), joints=robot.active_joints)
        self.base._elapsed_steps[:] = snap.step
        self.step_count = snap.step
        self.reached = dict(snap.reached)
        self._last = self._evaluate()

    def close(self) -> None:
        self._gym.close()
