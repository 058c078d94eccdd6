"""The expert oracle WAM: its chunk and images are what the expert really does from the same state,
and a query leaves the environment as it found it."""

import numpy as np
import pytest

from wamplan.envs.rollout import run_episode
from wamplan.policies.base import CAMERAS
from wamplan.policies.expert import ExpertPolicy
from wamplan.wam import WAMError, WAMPolicy, make_wam
from wamplan.wam.oracle import ExpertOracleWAM


def _advance(env, expert, seed: int, steps: int):
    expert.reset()
    obs = env.reset(seed)
    for _ in range(steps):
        obs, _ = env.step(expert.act(obs))
    return obs


def test_oracle_predicts_the_expert_rollout_and_restores_the_env(env):
    live = ExpertPolicy()
    obs = _advance(env, live, seed=3, steps=24)  # mid-episode, past the first phase change
    oracle = make_wam("expert-oracle", env=env)
    oracle.sync(live)
    before = (env.sim_state(), env.drive_targets(), env.step_count, env.proprio())
    out = oracle.validate(oracle.predict(env.observe(with_images=True), "insert"))

    after = (env.sim_state(), env.drive_targets(), env.step_count, env.proprio())
    np.testing.assert_allclose(after[0], before[0], atol=1e-6)  # restored (PhysX reads back ~1e-8 off)
    np.testing.assert_allclose(after[1], before[1], atol=1e-6)
    assert after[2] == before[2] == 24
    np.testing.assert_allclose(after[3], before[3], atol=1e-6)

    # the real rollout of the (live) expert from this state
    actions = []
    for _ in range(16):
        a = live.act(obs)
        actions.append(a)
        obs, _ = env.step(a)
    np.testing.assert_allclose(out.actions, np.stack(actions), atol=1e-5)
    assert out.extras["expert_phase"] == live.phase
    real = env.render()
    for c in CAMERAS:
        assert out.images[c].shape == real[c].shape
        diff = np.abs(out.images[c].astype(np.int16) - real[c].astype(np.int16)).mean()
        assert diff < 0.5, (c, diff)


def test_oracle_as_a_policy_succeeds_like_the_expert(env):
    oracle = ExpertOracleWAM(env, image_size=32)
    result = run_episode(env, WAMPolicy(oracle), seed=0)
    assert result.success, result.outcome
    steps = result.policy_info["query_steps"]
    assert steps == list(range(0, result.length, 16))
    assert oracle.expert.phase in ("insert", "retreat")


def test_oracle_rejects_misuse(env):
    with pytest.raises(WAMError, match="live InsertionEnv"):
        ExpertOracleWAM(object())
    oracle = ExpertOracleWAM(env, chunk=4, image_size=16)
    obs = env.reset(1)
    out = oracle.validate(oracle.predict(obs, ""))
    assert out.actions.shape == (4, 5) and out.images["wrist"].shape == (16, 16, 3)
    env.step(np.zeros(5, np.float32))
    with pytest.raises(WAMError, match="step 0"):
        oracle.predict(obs, "")  # stale observation: the env has moved on
