"""The Panda of ``CubeInsertion-v1``: the stock Panda plus the 5-D ``pd_ee_delta_xyzyaw`` control mode."""

from __future__ import annotations

from copy import deepcopy

import numpy as np
from mani_skill.agents.registration import register_agent
from mani_skill.agents.robots.panda.panda import Panda

from wamplan.envs.contract import CONTROL_MODE
from wamplan.envs.controller import EEDeltaXYZYawControllerConfig

# Joint angles of the rest pose: the TCP points straight down above the table centre.
REST_QPOS = np.array([0.0, np.pi / 8, 0.0, -np.pi * 5 / 8, 0.0, np.pi * 3 / 4, np.pi / 4, 0.04, 0.04])


@register_agent()
class PandaInsertion(Panda):
    uid = "panda_insertion"

    @property
    def _controller_configs(self):
        configs = super()._controller_configs
        gripper = deepcopy(configs["pd_ee_delta_pose"]["gripper"])
        arm = EEDeltaXYZYawControllerConfig(
            joint_names=self.arm_joint_names,
            pos_lower=-1.0, pos_upper=1.0,  # unused by this controller; it reads pos_bound / yaw_bound
            stiffness=self.arm_stiffness, damping=self.arm_damping, force_limit=self.arm_force_limit,
            ee_link=self.ee_link_name, urdf_path=self.urdf_path,
        )
        configs[CONTROL_MODE] = dict(arm=arm, gripper=gripper)
        return configs
