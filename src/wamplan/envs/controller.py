"""A 4-D end-effector controller for the Panda: (dx, dy, dz, dyaw), plus the stock gripper.

ManiSkill's ``pd_ee_delta_pose`` takes 6-D deltas (xyz + XYZ Euler) and scales the rotation part by
its *lower* bound (a sign flip with the Panda's negative bound). This task needs exactly four arm
dimensions, so this subclass exposes them with plain, documented units:

* ``action[0:3]`` in [-1, 1] -> TCP translation of ``pos_bound`` metres per control step
  (default 0.02 m, i.e. up to 0.4 m/s at 20 Hz), in the robot's root frame;
* ``action[3]`` in [-1, 1] -> rotation of ``yaw_bound`` radians per control step (default 0.1 rad)
  about the world (root) z axis, applied on the left of the current TCP orientation, so a
  top-down gripper stays top-down.

Deltas are relative to the *current* TCP pose (``use_target=False``, as ManiSkill's default), so a
blocked arm does not wind up a hidden target. Values outside [-1, 1] are clipped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from gymnasium import spaces
from mani_skill.agents.controllers.pd_ee_pose import PDEEPoseController, PDEEPoseControllerConfig
from mani_skill.utils.geometry.rotation_conversions import axis_angle_to_quaternion, quaternion_multiply
from mani_skill.utils.structs import Pose


class EEDeltaXYZYawController(PDEEPoseController):
    config: "EEDeltaXYZYawControllerConfig"

    def _initialize_action_space(self):
        b = self.config
        low = np.float32([-b.pos_bound] * 3 + [-b.yaw_bound])
        self.single_action_space = spaces.Box(low, -low, dtype=np.float32)

    def _clip_and_scale_action(self, action: torch.Tensor) -> torch.Tensor:
        # (B, 4) in [-1, 1] -> (B, 4) metres / radians; clipping, then a symmetric scale (no sign quirk)
        scale = self.action_space_high  # (4,) = (pos, pos, pos, yaw) bounds
        return torch.clamp(action, -1.0, 1.0) * scale

    def compute_target_pose(self, prev_ee_pose_at_base: Pose, action: torch.Tensor) -> Pose:
        delta_pos, dyaw = action[:, 0:3], action[:, 3]  # (B, 3), (B,)
        axis_angle = torch.zeros_like(delta_pos)  # (B, 3)
        axis_angle[:, 2] = dyaw
        q = quaternion_multiply(axis_angle_to_quaternion(axis_angle), prev_ee_pose_at_base.q)  # (B, 4) wxyz
        return Pose.create_from_pq(prev_ee_pose_at_base.p + delta_pos, q)


@dataclass
class EEDeltaXYZYawControllerConfig(PDEEPoseControllerConfig):
    pos_bound: float = 0.02
    """metres of TCP translation per control step at action 1"""
    yaw_bound: float = 0.1
    """radians of TCP yaw per control step at action 1"""
    controller_cls = EEDeltaXYZYawController
