"""The expert oracle WAM: its chunk and images are what the expert really does from the same state,
and a query leaves the environment as it found it."""

import numpy as np
import pytest

from wamplan.envs.contract import CAMERAS
from wamplan.policies.expert import ExpertPolicy
from wamplan.policies.rollout import run_episode
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
    assert live.phase_for(obs) == live.phase  # the live phase fits the state, so the oracle keeps it
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


@pytest.mark.parametrize("seed", [1, 2])
def test_resynchronised_oracle_keeps_the_expert_succeeding(env, seed):
    """Re-synchronising at every query must not break the expert when it drives itself (conditions 2-3)."""
    result = run_episode(env, WAMPolicy(ExpertOracleWAM(env, image_size=16)), seed=seed)
    assert result.success, result.outcome


def test_oracle_rejects_misuse(env):
    from types import SimpleNamespace

    from wamplan.envs.spec import get_task

    with pytest.raises(WAMError, match="live TaskEnv"):
        ExpertOracleWAM(object())
    push = SimpleNamespace(snapshot=None, restore=None, render=None, task=get_task("push-cube"))
    with pytest.raises(WAMError, match="task push-cube has none"):
        ExpertOracleWAM(push)  # the scripted expert is the cube's
    with pytest.raises(WAMError, match="among task cube-insertion's"):
        ExpertOracleWAM(env, cameras=("base_camera",))
    oracle = ExpertOracleWAM(env, chunk=4, image_size=16)
    assert oracle.task is env.task and oracle.cameras == CAMERAS and oracle.action_dim == 5
    assert ExpertOracleWAM(env, cameras=("wrist",)).cameras == ("wrist",)
    obs = env.reset(1)
    out = oracle.validate(oracle.predict(obs, ""))
    assert out.actions.shape == (4, 5) and out.images["wrist"].shape == (16, 16, 3)
    env.step(np.zeros(5, np.float32))
    with pytest.raises(WAMError, match="step 0"):
        oracle.predict(obs, "")  # stale observation: the env has moved on


# ---------------------------------------------------------------- the expert's phase follows the state
def _phase_fits(obs, phase: str) -> bool:
    """Independent of ExpertPolicy.phase_for: a gripper-open reaching phase while the cube is free on the table,
    a carrying phase while it is held above it."""
    grasped, lifted = bool(obs.state["stages"][0]), bool(obs.state["stages"][1])
    if not grasped and not lifted:
        return phase in ("approach", "descend", "close")
    if grasped and lifted:
        return phase in ("lift", "transport", "insert")
    return True


def test_oracle_resynchronises_after_chunks_it_did_not_execute(env):
    """Condition 4's situation: the oracle proposes a chunk, something else is executed. Here the expert is about
    to close on the cube, the oracle's own (never executed) chunk would grasp and start carrying it, and instead
    the arm rises with the gripper open, leaving the cube on the table. The next query must start from the phase
    that fits the state (reach for the cube again, gripper open), not carry an absent cube with a closed gripper,
    as the oracle did when it continued from the phase its own chunk had reached."""
    live = ExpertPolicy()
    obs = env.reset(3)
    while live.phase != "close":
        obs, _ = env.step(live.act(obs))
    oracle = ExpertOracleWAM(env, image_size=16)
    oracle.sync(live)
    first = oracle.predict(obs, "")
    assert first.extras["expert_phase"] in ("lift", "transport") and (first.actions[4:, 4] == -1).all()
    up = np.array([0, 0, 1, 0, 1], np.float32)
    for _ in range(16):
        obs, _ = env.step(up)
    assert not obs.state["stages"][0]  # the cube was not grasped
    out = oracle.predict(obs, "")
    assert out.extras["start_phase"] == "approach" and _phase_fits(env.observe(), out.extras["start_phase"])
    assert (out.actions[:, 4] == 1.0).all()  # gripper open while reaching for the cube again
    assert out.actions[0, 2] < 0  # back down towards it


def test_oracle_target_phase_fits_the_state_in_a_wam_driven_episode(env):
    """Condition 4 (WAM seed, expert target): a TinyWAM drives the robot, the oracle is queried at every chunk
    boundary; its start phase must fit the simulator state each time."""
    from wamplan.wam import load_wam

    wam = load_wam("checkpoints/mini/tinywam", device="cpu")
    oracle = ExpertOracleWAM(env, image_size=16)
    seen = []

    def check(e, obs, action):
        if obs.step % 16 == 0:
            out = oracle.predict(e.observe(with_images=False), "")
            seen.append((obs.step, out.extras["start_phase"], _phase_fits(e.observe(), out.extras["start_phase"])))

    run_episode(env, WAMPolicy(wam), seed=7, on_obs=check, max_steps=160)
    assert len(seen) >= 8 and all(fits for _, _, fits in seen), seen
    assert len({p for _, p, _ in seen}) >= 2, seen  # the episode went through more than one phase


def test_a_held_cube_is_lifted_not_closed_on_again(env):
    """The fingers press the cube at the grasp point and a planner held the arm still instead of lifting: the
    state says 'lift', so the oracle lifts at once. (Reading it as 'still closing' restarted the closing count at
    every chunk boundary, and a planner that kept cutting the lift short never lifted the cube.)"""
    live = ExpertPolicy()
    obs = env.reset(3)
    while live.phase != "lift":
        obs, _ = env.step(live.act(obs))
    hold = np.array([0, 0, 0, 0, -1], np.float32)  # still, gripper closed
    for _ in range(16):
        obs, _ = env.step(hold)
    assert obs.state["stages"][0] and not obs.state["stages"][1]  # grasped, not lifted
    assert live.phase_for(obs) == "lift"
    out = ExpertOracleWAM(env, image_size=16).predict(obs, "")
    assert out.extras["start_phase"] == "lift"
    assert (out.actions[:, 4] == -1).all() and (out.actions[:4, 2] > 0).all()  # keeps holding, rises at once
