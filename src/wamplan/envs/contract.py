"""``CubeInsertion-v1``'s contract: what it shows a policy, what it accepts and what it reports, registered as the
task ``cube-insertion`` (:data:`CUBE_INSERTION`, a :class:`~wamplan.envs.spec.TaskSpec`).

Only the env layer reads these constants; everything above it reads the spec. This module imports neither
ManiSkill nor torch, so importing it is cheap.

* observation: :class:`Observation` per control step; ``proprio`` is ``PROPRIO_DIM`` = 10 floats
  (gripper width, TCP xyz, TCP 6-D rotation), images come from the ``CAMERAS`` (front, side, wrist);
* action: ``ACTION_DIM`` = 5 floats in [-1, 1], ``(dx, dy, dz, dyaw, gripper)``: the arm's entries ``ARM``,
  then the gripper at ``GRIPPER_INDEX``, ``GRIPPER_OPEN`` = +1, ``GRIPPER_CLOSED`` = -1 (see
  ``wamplan.envs.agent``); ``HOLD_ACTION`` keeps the arm still with the gripper open;
* report: the furthest of the ``STAGES`` an episode reached, summarised as one of the ``OUTCOMES``.
"""

from __future__ import annotations

import numpy as np

from wamplan.envs.spec import Observation, TaskSpec, register_task

ENV_ID = "CubeInsertion-v1"
MAX_EPISODE_STEPS = 300
CAMERAS = ("front", "side", "wrist")
ACTION_DIM = 5
GRIPPER_INDEX = 4  # the gripper's entry of an action; the entries before it move the arm
ARM = slice(0, GRIPPER_INDEX)  # the arm's entries of an action: (dx, dy, dz, dyaw)
GRIPPER_OPEN, GRIPPER_CLOSED = 1.0, -1.0
HOLD_ACTION = np.array([0.0, 0.0, 0.0, 0.0, GRIPPER_OPEN], np.float32)  # (A,) arm still, gripper open
HOLD_ACTION.setflags(write=False)
PROPRIO_DIM = 10
STAGES = ("grasped", "lifted", "aligned", "descended", "seated")
HOLE_XY = (0.0, 0.12)  # the mount's hole axis, metres (fixed in the task)
ALIGN_XY_TOL = 0.004  # metres: "aligned" needs the cube's centre this close to the hole's axis (and the yaw within 0.1 rad)
# the task's continuous measures of the cube, in every step's info: metres (xy from the hole's axis; bottom above
# the table) and radians (yaw from the hole's square; tilt of its axis from vertical)
CUBE_METRICS = ("cube_xy_error", "cube_yaw_error", "cube_bottom", "cube_tilt")
OUTCOMES = ("success", "never_lifted", "lifted_not_aligned", "aligned_not_descended", "descended_not_seated")


CONTROL_MODE = "pd_ee_delta_xyzyaw"  # the 5-D controller of wamplan.envs.agent (which imports ManiSkill)
INSTRUCTION = "insert the cube into the square hole"

CUBE_INSERTION = register_task(TaskSpec(
    name="cube-insertion", env_id=ENV_ID, cameras=CAMERAS, action_dim=ACTION_DIM, proprio_dim=PROPRIO_DIM,
    control_mode=CONTROL_MODE, max_episode_steps=MAX_EPISODE_STEPS, instruction=INSTRUCTION,
    adapter="wamplan.envs.task:CubeInsertionAdapter", gripper_index=GRIPPER_INDEX, gripper_open=GRIPPER_OPEN,
    gripper_closed=GRIPPER_CLOSED, chunk_len=16, stages=STAGES,
    outcomes=(("descended", "descended_not_seated"), ("aligned", "aligned_not_descended"),
              ("lifted", "lifted_not_aligned")),
    failure="never_lifted", metrics=CUBE_METRICS, expert="expert",
    config_kwargs=("clearance", "cube_half_size", "mount_height", "robot_init_qpos_noise"), params=(("align_xy_tol", ALIGN_XY_TOL), ("hole_x", HOLE_XY[0]), ("hole_y", HOLE_XY[1]))))
assert CUBE_INSERTION.outcome_names == OUTCOMES

__all__ = ["ACTION_DIM", "ARM", "CAMERAS", "CUBE_INSERTION", "CUBE_METRICS", "ENV_ID", "GRIPPER_INDEX", "HOLD_ACTION", "HOLE_XY",
           "MAX_EPISODE_STEPS", "OUTCOMES", "PROPRIO_DIM", "STAGES", "Observation"]
