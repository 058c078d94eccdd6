"""A ManiSkill task other than the cube, end to end at tiny sizes: a trajectory file made here by ManiSkill's own
recorder (``RecordEpisode``, ``pd_joint_pos``, as ManiSkill's motion planner writes) -> ``wamplan data import`` (converted to the task's
``pd_ee_delta_pose`` by ManiSkill's replay tool, replayed and rendered) -> TinyWAM and world model trained a few
steps -> conditions 1 and 6 evaluated on one episode; and the one-line errors for a task mismatch."""

import json

import gymnasium as gym
import numpy as np
import pytest

from wamplan.cli import main
from wamplan.data.store import EpisodeStore
from wamplan.evaluation.records import read_records

TASK, ENV_ID, SIZE = "push-cube", "PushCube-v1", 64


@pytest.fixture(scope="module")
def trajectory(tmp_path_factory, small_env):
    """Two short episodes of PushCube-v1 with joint targets wandering from the start, in ManiSkill's trajectory
    format. (``small_env`` stays alive meanwhile: while one env lives, SAPIEN keeps its compiled shaders, so the
    envs each import builds and drops render at once instead of compiling them again, about 10 s each here.)"""
    import mani_skill.envs  # noqa: F401
    from mani_skill.utils.wrappers.record import RecordEpisode

    import wamplan.envs  # noqa: F401  (Vulkan set-up)

    root = tmp_path_factory.mktemp("traj")
    env = gym.make(ENV_ID, obs_mode="none", control_mode="pd_joint_pos", sim_backend="physx_cpu",
                   render_backend="none")
    env = RecordEpisode(env, output_dir=str(root), trajectory_name="demo", save_video=False, save_on_reset=False)
    rng = np.random.default_rng(0)
    for seed in (11, 12):
        env.reset(seed=seed)
        target = env.unwrapped.agent.robot.get_qpos()[0, :8].numpy().copy()  # (8,): 7 joints + the gripper
        for _ in range(12):
            target[:7] += rng.uniform(-0.02, 0.02, 7)
            env.step(target.astype(np.float32))
        env.flush_trajectory()
    env.close()
    return root / "demo.h5"


@pytest.fixture(scope="module")
def store(trajectory, tmp_path_factory):
    out = tmp_path_factory.mktemp("imported") / "store"
    assert main(["data", "import", "--format", "maniskill", str(trajectory), str(out), "--keep-failed",
                 "--camera-size", str(SIZE), "--image-every", "2"]) == 0
    return out


def test_import_converts_replays_and_records_the_task(store, trajectory):
    s = EpisodeStore(store)
    assert s.task.name == TASK and s.cameras == ("base_camera",)
    report = json.loads((store / "import.json").read_text())
    assert report["controller"] == "pd_ee_delta_pose" and report["episodes"] == 2
    assert report["replay_success"] + len(report["failed_seeds"]) == 2
    assert trajectory.with_name("demo.none.pd_ee_delta_pose.physx_cpu.h5").is_file()  # ManiSkill's conversion
    eps = [s.load(p) for p in s.episode_paths()]
    assert sorted(e.seed for e in eps) == [11, 12]
    for e in eps:
        assert e.actions.shape[1] == 7 and e.proprio.shape[1] == 16
        assert e.images["base_camera"].shape[1:] == (SIZE, SIZE, 3)


def test_train_plan_and_evaluate_on_the_imported_task(store, tmp_path, capsys):
    assert main(["wam", "train", "--data", str(store), "--out", str(tmp_path / "wam"), "--epochs", "1",
                 "--max-steps", "2", "--batch-size", "4", "--channels", "8", "16", "--latent-dim", "32",
                 "--trunk-dim", "64", "--no-progress", "--sources", "demo"]) == 0
    assert main(["wm", "train", "--data", str(store), "--out", str(tmp_path / "wm"), "--epochs", "1",
                 "--max-steps", "2", "--batch-size", "4"]) == 0
    out = tmp_path / "eval"
    assert main(["eval", "--task", TASK, "--conditions", "1,6", "--episodes", "1", "--seed-start", "3",
                 "--out", str(out), "--wam", str(tmp_path / "wam"), "--wm-plain", str(tmp_path / "wm"),
                 "--camera-size", str(SIZE), "--max-steps", "20", "--num-candidates", "4", "--iterations", "1"]) == 0
    recs = {r["condition"]: r for r in read_records(out)}
    assert set(recs) == {1, 6} and recs[6]["planned_chunks"] == 1
    assert recs[1]["outcome"] in ("success", "failure")
    capsys.readouterr()
    # the same checkpoints on another task: one line naming both tasks
    assert main(["eval", "--conditions", "1", "--episodes", "1", "--out", str(tmp_path / "eval_cube"),
                 "--wam", str(tmp_path / "wam"), "--camera-size", str(SIZE), "--max-steps", "4"]) == 2
    err = capsys.readouterr().err.strip()
    assert "push-cube" in err and "cube-insertion" in err and len(err.splitlines()) == 1


def test_import_drops_an_episode_whose_replay_fails(trajectory, tmp_path, capsys):
    """The wandering episode of seed 11 misses PushCube's goal: without --keep-failed the store does not keep it
    and the report names it, also after a re-run of the same import."""
    out = tmp_path / "store"
    argv = ["data", "import", "--format", "maniskill", str(trajectory), str(out), "--camera-size", "16",
            "--episodes", "1"]
    assert main(argv) == 0
    report = json.loads((out / "import.json").read_text())
    assert (report["episodes"], report["replay_success"], report["failed_seeds"], report["kept"]) == (1, 0, [11], 0)
    assert EpisodeStore(out).episode_paths() == []
    capsys.readouterr()
    assert main(argv) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["failed_seeds"] == [11]
    assert EpisodeStore(out).episode_paths() == []


def test_a_noisy_import_keeps_its_episodes_and_runs_the_noisy_actions(trajectory, tmp_path):
    """--noise-std: the episodes are exploration data, kept whatever their outcome, and what they ran is the
    converted demonstration plus noise on the arm's entries (the gripper's as recorded)."""
    import h5py

    from wamplan.policies.replay import trajectory_episodes

    out = tmp_path / "store"
    assert main(["data", "import", "--format", "maniskill", str(trajectory), str(out), "--camera-size", "16",
                 "--noise-std", "0.2", "--episodes", "1"]) == 0
    report = json.loads((out / "import.json").read_text())
    assert (report["source"], report["kept"], report["failed_seeds"]) == ("demo-noise0.2", 1, [11])
    s = EpisodeStore(out)
    [ep] = [s.load(p) for p in s.episode_paths()]
    converted = trajectory.with_name("demo.none.pd_ee_delta_pose.physx_cpu.h5")
    with h5py.File(converted, "r") as f:
        demo = f[f"traj_{trajectory_episodes(converted)[11]['episode_id']}"]["actions"][:]  # (T, 7)
    assert ep.seed == 11 and len(ep.actions) >= len(demo)
    noise = ep.actions[:len(demo)] - np.clip(demo, -1, 1)  # (T, 7)
    np.testing.assert_allclose(noise[:, 6], 0.0, atol=1e-6)
    assert 0.1 < np.abs(noise[:, :6]).mean() < 0.3  # |N(0, 0.2)| averages 0.16


def test_import_refuses_a_task_that_runs_another_env(trajectory, tmp_path, capsys):
    assert main(["data", "import", "--format", "maniskill", str(trajectory), str(tmp_path / "x"),
                 "--task", "cube-insertion"]) == 2
    err = capsys.readouterr().err.strip()
    assert "PushCube-v1" in err and "cube-insertion" in err and len(err.splitlines()) == 1


def test_peg_spec_matches_the_env_and_reads_its_grasp_flag():
    from wamplan.envs.config import EnvConfig
    from wamplan.envs.core import TaskEnv
    from wamplan.envs.maniskill import PEG_INSERTION_SIDE, spec_from_env

    read = spec_from_env("PegInsertionSide-v1", name="peg-probe", instruction="-")
    assert (read.cameras, read.action_dim, read.proprio_dim) == (PEG_INSERTION_SIDE.cameras, 7, 16)
    env = TaskEnv(EnvConfig(task="peg-insertion-side", camera_size=32))
    obs = env.reset(seed=1, with_images=True)
    assert env.metrics == {"grasped": False, "success": False} and env.outcome() == "never_grasped"
    assert obs.proprio.shape == (16,) and set(obs.images) == {"base_camera", "hand_camera"}
    views = env.simulate(env.snapshot(), np.zeros((2, 4, 7), np.float32))
    assert views.shape == (2, 2, 32, 32, 3)
    env.close()
