"""The scripted policies read the action's layout from their task: pink noise acts in any task, the (noisy) expert
only in the cube task it scripts; without a task they act in the cube task as they always did."""

import colorednoise
import numpy as np
import pytest

from wamplan.envs.maniskill import maniskill_task
from wamplan.envs.spec import TASKS, Observation, get_task
from wamplan.errors import UserError
from wamplan.policies import PinkNoisePolicy, make_policy
from wamplan.policies.base import DEFAULT_TASK

CUBE = get_task("cube-insertion")
# a task without a gripper, in joint space: no gripper channel, no downward push
NO_GRIPPER = maniskill_task("PushT-v1", name="no-gripper", cameras=("base_camera",), action_dim=7, proprio_dim=7,
                            max_episode_steps=40, instruction="push", control_mode="pd_joint_delta_pos",
                            gripper_index=None)


def test_pink_noise_without_a_task_is_the_cube_tasks_as_before():
    """Same seed, same actions: the 5-D cube draw (dz pushed down, gripper = sign of its own channel)."""
    p, q = make_policy("pink"), make_policy("pink", task=CUBE)
    assert DEFAULT_TASK == CUBE.name and p.config_dict() == q.config_dict() and p.config.horizon == 300
    for seed in (0, 7):
        p.reset(seed)
        q.reset(seed)
        rng = np.random.default_rng(seed + 2_000_003)
        n = colorednoise.powerlaw_psd_gaussian(1.0, (5, 300), random_state=rng)  # (5, T)
        a = n.T * 0.6
        a[:, 2] -= 0.15
        a[:, 4] = np.sign(n[4]) + (n[4] == 0)
        want = np.clip(a, -1, 1).astype(np.float32)
        assert want.tobytes() == p.noise.tobytes() == q.noise.tobytes()


@pytest.mark.parametrize("name", sorted(TASKS))
def test_pink_noise_acts_in_every_registered_task(name):
    task = get_task(name)
    p = make_policy("pink", task=task)
    p.reset(3)
    assert p.noise.shape == (task.max_episode_steps, task.action_dim) and p.noise.dtype == np.float32
    a = p.act(Observation(step=5, proprio=np.zeros(task.proprio_dim, np.float32)))
    assert a.shape == (task.action_dim,) and np.all(np.abs(a) <= 1)
    if task.gripper_index is not None:
        assert set(np.unique(p.noise[:, task.gripper_index])) <= {task.gripper_open, task.gripper_closed}


def test_pink_noise_without_a_gripper_leaves_every_entry_noise():
    p = PinkNoisePolicy(task=NO_GRIPPER)
    p.reset(1)
    assert p.noise.shape == (40, 7) and len(np.unique(p.noise[:, 6])) > 2  # no gripper channel made binary
    assert p.dz is None  # joint deltas: no dz to push down
    assert p.act(Observation(step=99, proprio=np.zeros(7, np.float32))).tobytes() == p.noise[-1].tobytes()


def test_make_policy_gives_the_task_only_to_policies_that_take_one():
    peg = get_task("peg-insertion-side")
    assert make_policy("pink", task=peg).task is peg
    assert make_policy("pink").task == CUBE


@pytest.mark.parametrize("name", ["expert", "noisy-expert"])
def test_the_scripted_expert_refuses_a_task_it_does_not_script(name):
    assert make_policy(name, task=CUBE).task == CUBE
    with pytest.raises(UserError, match="peg-insertion-side' has no scripted expert") as e:
        make_policy(name, task=get_task("peg-insertion-side"))
    assert "\n" not in str(e.value)
