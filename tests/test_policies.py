"""The scripted policies read the action's layout from their task: pink noise acts in any task, the (noisy) expert
only in the cube task it scripts; without a task they act in the cube task as they always did."""

import json

import colorednoise
import h5py
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


# ------------------------------------------------------------------ demo replay
PUSH = get_task("push-cube")


def _demos(path, actions: dict[int, np.ndarray]):
    """A ManiSkill trajectory file: ``traj_<id>/actions`` in the .h5, each episode's id and seed in the .json."""
    with h5py.File(path, "w") as f:
        for i, a in enumerate(actions.values()):
            f.create_dataset(f"traj_{i}/actions", data=a)
    episodes = [dict(episode_id=i, episode_seed=s, reset_kwargs=dict(seed=s)) for i, s in enumerate(actions)]
    path.with_suffix(".json").write_text(json.dumps(dict(env_info={}, episodes=episodes)))
    return str(path)


def _play(policy, seed: int, steps: int) -> np.ndarray:
    policy.reset(seed)
    return np.stack([policy.act(Observation(step=t, proprio=np.zeros(PUSH.proprio_dim, np.float32)))
                     for t in range(steps)])  # (steps, A)


def test_demo_replay_plays_its_seeds_actions_in_order_then_holds_still(tmp_path):
    rng = np.random.default_rng(0)
    acts = {seed: rng.uniform(-0.9, 0.9, (n, 7)).astype(np.float32) for seed, n in ((11, 5), (12, 3))}
    acts[11][-1, PUSH.gripper_index] = -1.0  # the demonstration ends with the gripper closed
    policy = make_policy("demo-replay", task=PUSH, trajectory=_demos(tmp_path / "demo.h5", acts))
    for seed in (12, 11, 12):
        played = _play(policy, seed, len(acts[seed]) + 2)
        np.testing.assert_array_equal(played[:-2], acts[seed])  # step t runs the demonstration's action t
        hold = PUSH.hold_action.copy()
        hold[PUSH.gripper_index] = acts[seed][-1, PUSH.gripper_index]
        np.testing.assert_array_equal(played[-2:], [hold, hold])
    with pytest.raises(UserError, match="no episode of seed 13"):
        policy.reset(13)


def test_demo_replay_noise_moves_only_the_arm_by_its_std_the_same_for_a_seed(tmp_path):
    acts = np.zeros((400, 7), np.float32)
    acts[:, PUSH.gripper_index] = 0.5
    path = _demos(tmp_path / "demo.h5", {11: acts, 12: acts})
    exact = make_policy("demo-replay", task=PUSH, trajectory=path)
    np.testing.assert_array_equal(_play(exact, 11, 400), acts)
    noisy = make_policy("demo-replay", task=PUSH, trajectory=path, noise_std=0.1)
    played = _play(noisy, 11, 400)
    noise = played - acts  # (400, A)
    np.testing.assert_array_equal(noise[:, PUSH.gripper_index], 0.0)
    arm = noise[:, list(PUSH.arm)]  # (400, 6)
    assert abs(arm.mean()) < 0.01 and 0.095 < arm.std() < 0.105  # white noise of std 0.1 (2400 draws)
    np.testing.assert_array_equal(_play(noisy, 11, 400), played)  # a seed's noise is the same every time
    assert not np.allclose(_play(noisy, 12, 400), played)  # and another seed's other noise
