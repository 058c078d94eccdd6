"""The task's stage and success thresholds, pinned on both sides of each: they decide every success rate
wamplan publishes, so a tolerance that drifts (doubled, halved, off by a millimetre) must fail a test.

The cube is placed by hand (no physics step) and the task's own ``evaluate`` judges it; the pose is 0.2 mm (or
0.002 rad) inside and outside each threshold of the default task (clearance 2 mm per side, mount 25 mm tall).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from wamplan.envs.contract import ALIGN_XY_TOL

H = 0.02  # the cube's half side
MOUNT, CLEAR = 0.025, 0.002
EPS, EPS_RAD = 0.0002, 0.002


def _judge(env, xy_err: float = 0.0, bottom: float = 0.0, yaw: float = 0.0, tilt: float = 0.0) -> dict[str, bool]:
    """The task's stage flags with the cube's centre ``xy_err`` m from the hole's axis (along x), its bottom at
    ``bottom`` m, turned ``yaw`` about z and tilted ``tilt`` about x."""
    from mani_skill.utils.structs.pose import Pose

    from wamplan.envs.task import HOLE_XY

    base = env.base
    p = torch.tensor([[HOLE_XY[0] + xy_err, HOLE_XY[1], bottom + H]], dtype=torch.float32)  # (1, 3)
    qz = np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])  # wxyz
    qx = np.array([np.cos(tilt / 2), np.sin(tilt / 2), 0.0, 0.0])
    w1, x1, y1, z1 = qz
    w2, x2, y2, z2 = qx
    q = [w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
         w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2]  # qz * qx
    base.cube.set_pose(Pose.create_from_pq(p, torch.tensor([q], dtype=torch.float32)))
    ev = base.evaluate()
    return {k: bool(ev[k][0]) for k in ("lifted", "aligned", "descended", "seated", "success")}


@pytest.fixture(scope="module")
def task(small_env):
    small_env.reset(0)
    assert (small_env.config.clearance, small_env.config.mount_height) == (CLEAR, MOUNT)
    yield small_env
    small_env.reset(0)  # put the cube back where an episode starts


def test_lifted_is_a_bottom_above_one_centimetre(task):
    assert _judge(task, xy_err=0.2, bottom=0.01 + EPS)["lifted"]
    assert not _judge(task, xy_err=0.2, bottom=0.01 - EPS)["lifted"]


def test_aligned_needs_the_cube_above_the_mount_within_4_mm_and_a_tenth_of_a_radian(task):
    above = MOUNT + 0.005
    assert ALIGN_XY_TOL == 0.004
    assert _judge(task, xy_err=ALIGN_XY_TOL - EPS, bottom=above)["aligned"]
    assert not _judge(task, xy_err=ALIGN_XY_TOL + EPS, bottom=above)["aligned"]
    assert _judge(task, bottom=above, yaw=0.1 - EPS_RAD)["aligned"]
    assert not _judge(task, bottom=above, yaw=0.1 + EPS_RAD)["aligned"]
    assert _judge(task, bottom=MOUNT - 0.002 + EPS)["aligned"]  # its bottom within 2 mm of the mount's top
    assert not _judge(task, bottom=MOUNT - 0.002 - EPS)["aligned"]


def test_descended_is_below_the_mount_top_within_clearance_plus_2_mm(task):
    inside = MOUNT - 0.01
    assert _judge(task, bottom=MOUNT - 0.002 - EPS)["descended"]
    assert not _judge(task, bottom=MOUNT - 0.002 + EPS)["descended"]
    assert _judge(task, xy_err=CLEAR + 0.002 - EPS, bottom=inside)["descended"]
    assert not _judge(task, xy_err=CLEAR + 0.002 + EPS, bottom=inside)["descended"]


def test_success_is_seated_within_1_5_mm_of_the_table_untilted(task):
    for flags in (_judge(task, bottom=0.0015 - EPS), _judge(task, xy_err=CLEAR + 0.002 - EPS),
                  _judge(task, tilt=0.1 - EPS_RAD)):
        assert flags["seated"] and flags["success"]
    for flags in (_judge(task, bottom=0.0015 + EPS), _judge(task, xy_err=CLEAR + 0.002 + EPS),
                  _judge(task, tilt=0.1 + EPS_RAD)):
        assert not flags["seated"] and not flags["success"]
