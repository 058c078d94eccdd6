"""``CubeInsertion-v1``: a Panda grasps a cube and inserts it into a tight square hole in a fixed mount.

Scene (metres, world frame; the table top is z = 0, the robot base stands at x = -0.615):

* cube: side ``2 * cube_half_size`` (default 0.04), spawned flat with its centre uniformly in
  x ∈ [-0.10, 0.05], y ∈ [-0.20, -0.05] and yaw uniformly in [-π/4, π/4] (the cube's 90° symmetry
  makes this every distinct yaw);
* mount: a fixed block at ``HOLE_XY`` = (0.0, 0.12), ``mount_height`` tall (default 0.025), with a
  square through-hole of side ``2 * (cube_half_size + clearance)`` (default clearance 0.002 per side),
  axis-aligned (yaw 0);
* cameras: ``front`` (facing the robot across the table), ``side`` (from the robot's left) and ``wrist``
  (on the hand, looking down between the fingers), all ``camera_size`` px square (default 224).

Observations (``gym.make("CubeInsertion-v1", obs_mode=...)``, any ManiSkill mode): ManiSkill's ``agent``
(qpos, qvel) and, for camera modes, ``sensor_data`` / ``sensor_param``; ``extra`` holds ``proprio`` (the
10-D proprio wamplan's policies see, :meth:`CubeTaskEnv.proprio`), ``tcp_pose`` and ``hole_pos``,
plus the privileged ``cube_pose`` only in the ``state`` / ``state_dict`` modes (ManiSkill's convention).

Stages, per step (``evaluate``): ``grasped`` (both fingers press the cube), ``lifted`` (cube bottom
> 1 cm above the table), ``aligned`` (cube bottom above the mount top, centre within 4 mm of the
hole axis, yaw error < 0.1 rad), ``descended`` (cube bottom below the mount top, centre within
clearance + 2 mm of the hole axis), ``seated`` (cube bottom within 1.5 mm of the table inside the
hole, tilt < 0.1 rad). Success is ``seated``.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import sapien
import torch
from mani_skill.envs.sapien_env import BaseEnv
from mani_skill.sensors.camera import CameraConfig
from mani_skill.utils import sapien_utils
from mani_skill.utils.building import actors
from mani_skill.utils.registration import make, register_env
from mani_skill.utils.scene_builder.table import TableSceneBuilder
from mani_skill.utils.structs.pose import Pose

from wamplan.envs.adapters import ManiSkillAdapter
from wamplan.envs.agent import CONTROL_MODE, REST_QPOS, PandaInsertion
from wamplan.envs.config import EnvConfig
from wamplan.envs.contract import ALIGN_XY_TOL, ENV_ID, HOLE_XY, MAX_EPISODE_STEPS, STAGES
from wamplan.envs.spec import TaskSpec

CUBE_X_RANGE = (-0.10, 0.05)
CUBE_Y_RANGE = (-0.20, -0.05)
CUBE_YAW_RANGE = (-np.pi / 4, np.pi / 4)
WALL = 0.025  # thickness of the mount's walls


def yaw_of_quat(q: torch.Tensor) -> torch.Tensor:
    """Yaw (rotation about world z) of wxyz quaternions (..., 4) -> (...)."""
    w, x, y, z = q.unbind(-1)
    return torch.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def wrap_quarter(angle: torch.Tensor) -> torch.Tensor:
    """Wrap an angle to [-π/4, π/4): the yaw error of a square, which looks the same every 90°."""
    return torch.remainder(angle + np.pi / 4, np.pi / 2) - np.pi / 4


def make_env(**kwargs: Any) -> BaseEnv:
    """The entry point of the lazy gymnasium registration made by ``import wamplan.envs`` (by the time it
    runs, importing this module has put ManiSkill's own registration in its place)."""
    return make(ENV_ID, **kwargs)


gym.registry.pop(ENV_ID, None)  # the lazy placeholder from wamplan.envs: ManiSkill's registration replaces it


@register_env(ENV_ID, max_episode_steps=MAX_EPISODE_STEPS)
class CubeTaskEnv(BaseEnv):
    SUPPORTED_ROBOTS = ["panda_insertion"]
    agent: PandaInsertion

    def __init__(self, *args, robot_uids="panda_insertion", cube_half_size: float = 0.02,
                 clearance: float = 0.002, mount_height: float = 0.025, camera_size: int = 224,
                 robot_init_qpos_noise: float = 0.02, control_mode: str = CONTROL_MODE, **kwargs):
        if not 0 < clearance < cube_half_size:
            raise ValueError(f"clearance must be in (0, cube_half_size={cube_half_size}), got {clearance}")
        if not 0 < mount_height < 2 * cube_half_size:
            raise ValueError(f"mount_height must be in (0, cube side {2 * cube_half_size}) so the cube can be "
                             f"grasped when seated, got {mount_height}")
        self.cube_half_size = cube_half_size
        self.clearance = clearance
        self.mount_height = mount_height
        self.camera_size = int(camera_size)
        self.robot_init_qpos_noise = robot_init_qpos_noise
        super().__init__(*args, robot_uids=robot_uids, control_mode=control_mode, **kwargs)

    # ------------------------------------------------------------------ cameras
    @property
    def _default_sensor_configs(self):
        s, fov = self.camera_size, np.deg2rad(55)
        front = sapien_utils.look_at(eye=[0.36, -0.04, 0.34], target=[-0.04, -0.02, 0.0])
        side = sapien_utils.look_at(eye=[0.16, 0.44, 0.34], target=[-0.05, -0.05, 0.0])
        # On the hand, 5 cm off its x side, looking along the approach axis (hand +z) at the fingers.
        wrist_pose = sapien.Pose(p=[0.06, 0.0, 0.02], q=[0.0, 0.7071068, 0.0, 0.7071068])
        return [
            CameraConfig("front", front, s, s, fov, 0.01, 10),
            CameraConfig("side", side, s, s, fov, 0.01, 10),
            CameraConfig("wrist", wrist_pose, s, s, np.deg2rad(80), 0.01, 10,
                         mount=self.agent.robot.links_map["panda_hand"]),
        ]

    @property
    def _default_human_render_camera_configs(self):
        pose = sapien_utils.look_at(eye=[0.5, 0.4, 0.45], target=[-0.05, 0.0, 0.05])
        return CameraConfig("render_camera", pose, 512, 512, 1, 0.01, 10)

    # ------------------------------------------------------------------ scene
    def _load_agent(self, options: dict):
        super()._load_agent(options, sapien.Pose(p=[-0.615, 0, 0]))

    def _load_scene(self, options: dict):
        self.table_scene = TableSceneBuilder(self, robot_init_qpos_noise=self.robot_init_qpos_noise)
        self.table_scene.build()
        h = self.cube_half_size
        self.cube = actors.build_cube(self.scene, half_size=h, color=[0.85, 0.15, 0.1, 1], name="cube",
                                      initial_pose=sapien.Pose(p=[0, 0, h]))
        self.mount = self._build_mount()

    def _build_mount(self):
        """Four walls around a square hole of side 2 * (cube_half_size + clearance)."""
        hole = self.cube_half_size + self.clearance  # half side of the hole
        hz = self.mount_height / 2
        b = self.scene.create_actor_builder()
        mat = sapien.render.RenderMaterial(base_color=[0.25, 0.45, 0.85, 1])
        along, across = hole + WALL, WALL / 2
        for p, half in (([hole + across, 0, 0], [across, along, hz]), ([-hole - across, 0, 0], [across, along, hz]),
                        ([0, hole + across, 0], [hole, across, hz]), ([0, -hole - across, 0], [hole, across, hz])):
            b.add_box_collision(pose=sapien.Pose(p=p), half_size=half)
            b.add_box_visual(pose=sapien.Pose(p=p), half_size=half, material=mat)
        b.initial_pose = sapien.Pose(p=[HOLE_XY[0], HOLE_XY[1], hz])
        return b.build_static(name="mount")

    def _initialize_episode(self, env_idx: torch.Tensor, options: dict):
        with torch.device(self.device):
            n = len(env_idx)
            self.table_scene.initialize(env_idx)  # places the table; leaves our robot uid alone
            rng = self._episode_rng
            qpos = REST_QPOS[None] + rng.normal(0, self.robot_init_qpos_noise, (n, len(REST_QPOS)))
            qpos[:, -2:] = 0.04
            self.agent.reset(torch.as_tensor(qpos, dtype=torch.float32))
            self.agent.robot.set_pose(sapien.Pose([-0.615, 0, 0]))
            xy = np.stack([rng.uniform(*CUBE_X_RANGE, n), rng.uniform(*CUBE_Y_RANGE, n)], -1)  # (n, 2)
            yaw = rng.uniform(*CUBE_YAW_RANGE, n)  # (n,)
            p = torch.zeros(n, 3)
            p[:, :2] = torch.as_tensor(xy, dtype=torch.float32)
            p[:, 2] = self.cube_half_size
            q = torch.zeros(n, 4)
            q[:, 0], q[:, 3] = torch.as_tensor(np.cos(yaw / 2)), torch.as_tensor(np.sin(yaw / 2))
            self.cube.set_pose(Pose.create_from_pq(p, q))

    # ------------------------------------------------------------------ evaluation
    @property
    def hole_xy(self) -> torch.Tensor:
        return torch.tensor(HOLE_XY, device=self.device)

    def evaluate(self) -> dict[str, Any]:
        h = self.cube_half_size
        p, q = self.cube.pose.p, self.cube.pose.q  # (B, 3), (B, 4)
        bottom = p[:, 2] - h  # (B,) ignoring tilt: good enough for stage labels
        xy_err = torch.linalg.norm(p[:, :2] - self.hole_xy, dim=1)  # (B,)
        yaw_err = wrap_quarter(yaw_of_quat(q)).abs()  # (B,)
        up = self.cube.pose.to_transformation_matrix()[:, :3, 2]  # (B, 3) cube z axis in world
        tilt = torch.arccos(torch.clamp(up[:, 2].abs(), max=1.0))  # (B,)
        grasped = self.agent.is_grasping(self.cube)
        lifted = bottom > 0.01
        aligned = (bottom > self.mount_height - 0.002) & (xy_err < ALIGN_XY_TOL) & (yaw_err < 0.1)
        descended = (bottom < self.mount_height - 0.002) & (xy_err < self.clearance + 0.002)
        seated = (bottom < 0.0015) & (xy_err < self.clearance + 0.002) & (tilt < 0.1)
        return dict(success=seated, grasped=grasped, lifted=lifted, aligned=aligned, descended=descended,
                    seated=seated, cube_xy_error=xy_err, cube_yaw_error=yaw_err, cube_bottom=bottom, cube_tilt=tilt)

    def proprio(self) -> torch.Tensor:
        """(B, 10) float32: gripper width, TCP xyz, first two columns of the TCP rotation matrix."""
        qpos = self.agent.robot.get_qpos()  # (B, 9)
        pose = self.agent.tcp_pose
        rot = pose.to_transformation_matrix()[:, :3, :3]  # (B, 3, 3)
        six = rot[:, :, :2].transpose(1, 2).reshape(-1, 6)  # (B, 6): column 0, then column 1
        return torch.cat([(qpos[:, -2] + qpos[:, -1])[:, None], pose.p, six], dim=1)  # (B, 10)

    def _get_obs_extra(self, info: dict):
        hole = torch.cat([self.hole_xy, torch.tensor([self.mount_height], device=self.device)])  # (3,)
        extra = dict(proprio=self.proprio(), tcp_pose=self.agent.tcp_pose.raw_pose,
                     hole_pos=hole[None].expand(self.num_envs, 3))
        if self.obs_mode_struct.use_state:  # privileged: only in the state modes, as in ManiSkill's tasks
            extra["cube_pose"] = self.cube.pose.raw_pose
        return extra

    def compute_dense_reward(self, obs: Any, action: torch.Tensor, info: dict):
        # Planning in wamplan uses no reward; a simple shaped one keeps ManiSkill's RL tooling usable.
        tcp_to_cube = torch.linalg.norm(self.cube.pose.p - self.agent.tcp_pose.p, dim=1)
        return (1 - torch.tanh(5 * tcp_to_cube)) + info["grasped"].float() + 2 * (1 - torch.tanh(10 * info["cube_xy_error"])) \
            * info["lifted"].float() + 5 * info["success"].float()

    def compute_normalized_dense_reward(self, obs: Any, action: torch.Tensor, info: dict):
        return self.compute_dense_reward(obs, action, info) / 9.0


class CubeInsertionAdapter(ManiSkillAdapter):
    """The cube task's reading: its 10-D proprio, and the cube, TCP and hole poses as privileged state."""

    @staticmethod
    def make_kwargs(spec: TaskSpec, config: EnvConfig) -> dict[str, Any]:
        kw = {k: v for k, v in config.task_kwargs().items() if k not in ("task", "env_id")}
        return dict(spec.env_kwargs, **kw)

    def proprio(self) -> np.ndarray:
        return self.base.proprio()[0].numpy().astype(np.float32)  # (10,): the task's obs["extra"]["proprio"]

    def privileged_state(self, evaluation: dict[str, Any]) -> dict[str, np.ndarray]:
        b = self.base
        return dict(tcp_pose=b.agent.tcp_pose.raw_pose[0].numpy().copy(),
                    cube_pose=b.cube.pose.raw_pose[0].numpy().copy(),
                    hole_pos=np.array([*b.hole_xy.tolist(), b.mount_height], dtype=np.float32),
                    cube_half_size=np.float32(b.cube_half_size),
                    stages=np.array([evaluation.get(s, False) for s in STAGES], bool))
