"""The task's contract: what ``CubeInsertion-v1`` shows a policy, what it accepts, and what it reports.

Everything above the env layer (policies, data, models, planning, evaluation) speaks these names; this
module imports neither ManiSkill nor torch, so importing it is cheap.

* observation: :class:`Observation` per control step; ``proprio`` is ``PROPRIO_DIM`` = 10 floats
  (gripper width, TCP xyz, TCP 6-D rotation), images come from the ``CAMERAS`` (front, side, wrist);
* action: ``ACTION_DIM`` = 5 floats in [-1, 1], ``(dx, dy, dz, dyaw, gripper)``: the arm's entries ``ARM``,
  then the gripper at ``GRIPPER_INDEX``, ``GRIPPER_OPEN`` = +1, ``GRIPPER_CLOSED`` = -1 (see
  ``wamplan.envs.agent``); ``HOLD_ACTION`` keeps the arm still with the gripper open;
* report: the furthest of the ``STAGES`` an episode reached, summarised as one of the ``OUTCOMES``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

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
ALIGN_XY_TOL = 0.004  # metres: "aligned" needs the cube's centre this close to the hole's axis (and the yaw within 0.1 rad)
# the task's continuous measures of the cube, in every step's info: metres (xy from the hole's axis; bottom above
# the table) and radians (yaw from the hole's square; tilt of its axis from vertical)
CUBE_METRICS = ("cube_xy_error", "cube_yaw_error", "cube_bottom", "cube_tilt")
OUTCOMES = ("success", "never_lifted", "lifted_not_aligned", "aligned_not_descended", "descended_not_seated")


@dataclass
class Observation:
    """What a policy sees at control step ``step``."""

    step: int
    proprio: np.ndarray  # (10,) float32: gripper width, TCP xyz (3), TCP 6-D rotation (6)
    images: dict[str, np.ndarray] | None = None  # camera -> (H, W, 3) uint8; None if not rendered
    state: dict[str, np.ndarray] = field(default_factory=dict)  # privileged sim state (experts only)
