"""``CubeInsertion-v1`` as ManiSkill users make it: ``import wamplan.envs`` then ``gym.make``.

The checks are those of ManiSkill's own test suite (tests/test_envs.py in its repository: every obs mode
through ``CPUGymWrapper`` gives numpy/python types, seeded resets repeat, NaN actions raise, a restored
state dict gives the same observation) plus gymnasium's passive checker (spaces, obs in space, step types).
gymnasium's full ``check_env`` does not apply to ManiSkill tasks: ManiSkill registers them with the checker
disabled, and its ``BaseEnv`` (PickCube-v1 too) fails it on the first assertion (no ``np_random`` seeded).
"""

import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.passive_env_checker import env_reset_passive_checker, env_step_passive_checker

import wamplan.envs  # noqa: F401  (registers CubeInsertion-v1)
from wamplan.envs.contract import CAMERAS, ENV_ID, PROPRIO_DIM

SIZE = 64


def make(obs_mode: str, **kw):
    return gym.make(ENV_ID, obs_mode=obs_mode, camera_size=SIZE, render_backend="cpu", **kw)


def leaves(x):
    return [y for v in x.values() for y in leaves(v)] if isinstance(x, dict) else [x]


def test_import_registers_without_importing_maniskill():
    code = ("import sys, gymnasium as gym, wamplan.envs\n"
            "assert 'mani_skill' not in sys.modules\n"
            "e = gym.make('CubeInsertion-v1', obs_mode='state', render_backend='cpu')\n"
            "obs, _ = e.reset(seed=0)\n"
            "print(tuple(obs.shape), gym.spec('CubeInsertion-v1').max_episode_steps)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "(1, 45) 300"


def test_rgb_obs_has_proprio_beside_maniskills_keys(small_env):
    e = make("rgb")
    obs, _ = e.reset(seed=7)
    assert set(obs) == {"agent", "extra", "sensor_param", "sensor_data"}
    assert set(obs["extra"]) == {"proprio", "tcp_pose", "hole_pos"}  # no privileged cube pose in rgb mode
    assert set(obs["sensor_data"]) == set(CAMERAS)
    for cam in CAMERAS:
        assert obs["sensor_data"][cam]["rgb"].shape == (1, SIZE, SIZE, 3)
        assert obs["sensor_data"][cam]["rgb"].dtype == torch.uint8
    assert obs["extra"]["proprio"].shape == (1, PROPRIO_DIM) and obs["extra"]["proprio"].dtype == torch.float32
    # the same numbers wamplan's own wrapper (and so the episode store) records, bit for bit
    small_env.reset(7)
    np.testing.assert_array_equal(obs["extra"]["proprio"][0].numpy(), small_env.proprio())
    a = np.array([0.3, -0.2, 0.5, 0.4, -1.0], np.float32)
    for _ in range(3):
        obs, *_ = e.step(torch.as_tensor(a[None]))
        small_env.step(a)
    np.testing.assert_array_equal(obs["extra"]["proprio"][0].numpy(), small_env.proprio())
    e.close()


def test_state_modes():
    e = make("state_dict")
    obs, _ = e.reset(seed=1)
    assert set(obs) == {"agent", "extra"} and set(obs["agent"]) == {"qpos", "qvel"}
    assert set(obs["extra"]) == {"proprio", "tcp_pose", "hole_pos", "cube_pose"}
    proprio = obs["extra"]["proprio"]
    e.close()
    e = make("state")
    flat, _ = e.reset(seed=1)
    # ManiSkill flattens the state dict in key order: qpos 9, qvel 9, proprio 10, tcp 7, hole 3, cube 7
    assert flat.shape == (1, 45)
    torch.testing.assert_close(flat[:, 18:28], proprio, rtol=0, atol=0)
    e.close()


@pytest.mark.parametrize("obs_mode", ["state", "state_dict", "rgb"])
def test_maniskill_and_gymnasium_checks(obs_mode):
    from mani_skill.utils.wrappers.gymnasium import CPUGymWrapper

    e = CPUGymWrapper(make(obs_mode))
    obs, info = env_reset_passive_checker(e, seed=3)  # spaces, obs in observation_space, info a dict
    assert e.observation_space.contains(obs)
    assert all(isinstance(x, np.ndarray) for x in leaves(obs))
    e.action_space.seed(0)
    for _ in range(3):
        obs, rew, terminated, truncated, info = env_step_passive_checker(e, e.action_space.sample())
        assert e.observation_space.contains(obs)
        assert isinstance(rew, float) and isinstance(terminated, bool) and isinstance(truncated, bool)
    e.close()


def test_seeded_reset_repeats_and_nan_raises_and_states_restore():
    e = make("state")
    e.action_space.seed(0)
    first, _ = e.reset(seed=2000)
    for _ in range(5):
        e.step(e.action_space.sample())
    state = e.unwrapped.get_state_dict()
    mid = e.unwrapped.get_obs()
    for _ in range(10):
        e.step(e.action_space.sample())
    e.unwrapped.set_state_dict(state)
    torch.testing.assert_close(e.unwrapped.get_obs(), mid, rtol=0, atol=0)
    again, _ = e.reset(seed=2000)
    torch.testing.assert_close(again, first, rtol=0, atol=0)
    with pytest.raises(ValueError, match="NaN"):
        e.step(e.action_space.sample() * np.nan)
    e.close()


def test_time_limit_truncates():
    e = make("state", max_episode_steps=3)
    e.reset(seed=0)
    truncs = [bool(e.step(torch.zeros(1, 5))[3]) for _ in range(3)]
    assert truncs == [False, False, True]
    e.close()
