"""CubeInsertion-v1: spaces, controller units, determinism, snapshots, the expert, bad actions."""

import json

import gymnasium as gym
import numpy as np
import pytest

from wamplan.config import ConfigError
from wamplan.envs.contract import CAMERAS
from wamplan.envs.config import EnvConfig
from wamplan.policies import make_policy
from wamplan.policies.expert import ExpertConfig, ExpertPolicy, quat_yaw, wrap_quarter
from wamplan.policies.rollout import run_episode


def test_spaces(env):
    obs = env.reset(0, with_images=True)
    assert env.base.single_action_space.shape == (5,)
    assert np.all(env.base.single_action_space.low == -1) and np.all(env.base.single_action_space.high == 1)
    assert obs.proprio.shape == (10,) and obs.proprio.dtype == np.float32
    assert set(obs.images) == set(CAMERAS)
    for img in obs.images.values():
        assert img.shape == (224, 224, 3) and img.dtype == np.uint8
        assert img.std() > 5  # a real picture, not a blank frame
    # 6-D rotation: two orthonormal columns
    c0, c1 = obs.proprio[4:7], obs.proprio[7:10]
    assert abs(np.linalg.norm(c0) - 1) < 1e-4 and abs(np.linalg.norm(c1) - 1) < 1e-4 and abs(c0 @ c1) < 1e-4
    assert 0.07 < obs.proprio[0] <= 0.081  # gripper open at reset
    assert env.observe().images is None  # no rendering unless asked


def test_registered_with_gym_and_rgb_obs():
    import wamplan.envs  # noqa: F401

    e = gym.make("CubeInsertion-v1", obs_mode="rgb", camera_size=64)
    obs, _ = e.reset(seed=1)
    assert obs["sensor_data"]["wrist"]["rgb"].shape == (1, 64, 64, 3)
    e.close()


def test_controller_units(env):
    env.reset(0)
    p0 = env.proprio()[1:4].copy()
    for _ in range(10):
        env.step(np.array([1, 0, 0, 0, 1], np.float32))
    dx = env.proprio()[1] - p0[0]
    assert 0.08 < dx <= 0.2 + 1e-3, dx  # at most 0.02 m per step, and it tracks most of it
    yaw0 = np.arctan2(env.proprio()[5], env.proprio()[4])
    for _ in range(5):
        env.step(np.array([0, 0, 0, 1, 1], np.float32))
    yaw1 = np.arctan2(env.proprio()[5], env.proprio()[4])
    dyaw = (yaw1 - yaw0 + np.pi) % (2 * np.pi) - np.pi
    assert 0.1 < dyaw <= 0.5 + 1e-2, dyaw  # +1 turns counter-clockwise about world z, at most 0.1 rad a step


def _run(env, seed, actions, snap=None):
    if snap is None:
        env.reset(seed)
    else:
        env.restore(snap)
    out = []
    for a in actions:
        obs, _ = env.step(a)
        out.append(np.concatenate([obs.proprio, obs.state["cube_pose"]]))
    return np.stack(out)


def test_determinism(env):
    acts = np.random.default_rng(0).uniform(-1, 1, (40, 5)).astype(np.float32)
    a = _run(env, 7, acts)
    b = _run(env, 7, acts)
    np.testing.assert_array_equal(a, b)
    c = _run(env, 8, acts)
    assert np.abs(a - c).max() > 1e-3  # another seed is another episode


def test_snapshot_restore_reproduces_rollout(env):
    rng = np.random.default_rng(1)
    env.reset(3)
    for a in rng.uniform(-1, 1, (15, 5)).astype(np.float32):
        env.step(a)
    snap = env.snapshot()
    acts = rng.uniform(-1, 1, (20, 5)).astype(np.float32)
    # continue from the live state once (never restored), then replay twice from the snapshot
    live = []
    for a in acts:
        obs, _ = env.step(a)
        live.append(np.concatenate([obs.proprio, obs.state["cube_pose"]]))
    live = np.stack(live)
    r1 = _run(env, None, acts, snap=snap)
    r2 = _run(env, None, acts, snap=snap)
    np.testing.assert_array_equal(r1, r2)  # repeated restores are bit-identical
    assert np.abs(r1 - live).max() < 5e-3  # and close to the never-restored rollout (PhysX hidden state)
    assert env.step_count == snap.step + len(acts)


def test_expert_succeeds(env):
    expert = make_policy("expert")
    for seed in (0, 1, 2):
        r = run_episode(env, expert, seed)
        assert r.success and r.outcome == "success", (seed, r)
        assert r.reached["grasped"] and r.reached["lifted"] and r.reached["aligned"] and r.reached["descended"]
        assert 60 < r.length < 250


@pytest.mark.parametrize("turn_in", ["descend", "approach"])
def test_expert_turns_the_fingers_where_its_config_says(env, turn_in):
    """'descend' turns only once above the cube (where a wrist camera sees its yaw), 'approach' from step 0."""
    expert = ExpertPolicy(ExpertConfig(turn_in=turn_in))
    obs = env.reset(1000)
    assert abs(wrap_quarter(quat_yaw(obs.state["cube_pose"][3:]))) > 0.1  # a seed whose cube needs a turn
    turning, over_cube = [], []
    for _ in range(40):
        a = expert.act(obs)
        turning.append(abs(a[3]) > 0.05)
        over_cube.append(np.linalg.norm(obs.state["tcp_pose"][:2] - obs.state["cube_pose"][:2]) < 0.005)
        obs, _ = env.step(a)
    first = turning.index(True)
    assert over_cube[first] if turn_in == "descend" else (first == 0 and not over_cube[0])
    r = run_episode(env, expert, 1000)
    assert r.success, r


def test_pink_explorer_outcome_and_reproducible(env):
    pink = make_policy("pink")
    r = run_episode(env, pink, 5)
    assert not r.success and r.outcome in ("never_lifted", "lifted_not_aligned") and r.length == 300
    pink.reset(5)
    first = [pink.noise[i].copy() for i in range(3)]
    pink.reset(5)
    np.testing.assert_array_equal(first, pink.noise[:3])
    assert np.all(np.abs(pink.noise) <= 1) and set(np.unique(pink.noise[:, 4])) <= {-1.0, 1.0}


def test_bad_actions(env):
    env.reset(0)
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(4))
    with pytest.raises(ValueError, match="finite"):
        env.step(np.array([0, np.nan, 0, 0, 0]))
    snap = env.snapshot()
    big, _ = env.step(np.array([5, -5, 3, 9, 2], np.float32))
    env.restore(snap)
    env.restore(snap)
    unit, _ = env.step(np.array([1, -1, 1, 1, 1], np.float32))
    env.restore(snap)
    big2, _ = env.step(np.array([5, -5, 3, 9, 2], np.float32))
    np.testing.assert_array_equal(unit.proprio, big2.proprio)  # out of range is clipped to [-1, 1]


def test_env_config_validation():
    with pytest.raises(ConfigError, match="clearance"):
        EnvConfig(clearance=0.05)
    with pytest.raises(ConfigError, match="--camera-size"):
        EnvConfig(camera_size=4)


def test_cli_render_and_rollout(tmp_path, capsys):
    """The CLI's main in-process (a subprocess would spend ~10 s per call importing; the kill -9 tests
    run `python -m wamplan.cli` for real)."""
    from wamplan.cli import main

    assert main(["env", "render", "--seed", "2", "--out", str(tmp_path / "v.png"), "--camera-size", "64"]) == 0
    import imageio.v3 as iio

    assert iio.imread(tmp_path / "v.png").shape == (64, 192, 3)
    assert main(["env", "rollout", "--policy", "expert", "--episodes", "1", "--seed-start", "4", "--camera-size", "64",
                 "--json", str(tmp_path / "r.json")]) == 0
    data = json.loads((tmp_path / "r.json").read_text())
    assert data["summary"]["episodes"] == 1 and data["episodes"][0]["seed"] == 4 and data["episodes"][0]["success"]
    capsys.readouterr()
    assert main(["env", "rollout", "--policy", "nonsense", "--episodes", "1"]) == 2
    err = capsys.readouterr().err
    assert "unknown policy 'nonsense'" in err and err.count("\n") == 1


@pytest.mark.gpu
def test_gpu_render_backend_returns_numpy_frames():
    """With ManiSkill's GPU renderer the camera buffers are CUDA tensors; ``render`` hands back host uint8 arrays
    like the CPU renderer (before, it called ``.numpy()`` on the CUDA tensor and every evaluation worker died)."""
    from wamplan.envs.core import TaskEnv

    env = TaskEnv(EnvConfig(camera_size=64, render_backend="gpu"))
    try:
        obs = env.reset(0, with_images=True)
        for name in CAMERAS:
            img = obs.images[name]
            assert isinstance(img, np.ndarray) and img.dtype == np.uint8 and img.shape == (64, 64, 3)
            assert img.std() > 0  # a real picture, not an empty buffer
    finally:
        env.close()


def test_a_cube_trace_shows_where_the_expert_lets_the_cube_go(env):
    """The evaluation's privileged trace, as the evaluation runs it (stopping at success): rows every 4 steps up
    to the last one, and the release found at the step it happens (the expert lets go of the cube inside the
    hole, on its axis, on the step it seats it)."""
    from wamplan.evaluation.trace import CubeTrace

    trace = CubeTrace(every=4)
    r = run_episode(env, make_policy("expert"), 0, on_obs=trace)
    out = trace.summary()
    rows = out["trace"]
    assert [x["t"] for x in rows[:3]] == [0, 4, 8] and rows[-1]["t"] == r.length and r.success
    assert not rows[0]["grasped"] and abs(rows[0]["bottom_mm"]) < 1 and rows[0]["xy_mm"] > 20
    let_go = out["release"]
    assert let_go is not None and out["releases"] >= 1 and any(x["grasped"] for x in rows if x["t"] < let_go["t"])
    xy, bottom = let_go["held_mm"]
    assert xy < 4 and bottom < 25, let_go  # inside the 25 mm mount, on the axis
    assert not out["held_at_end"] and rows[-1]["tilt"] < 0.1
