"""TinyWAM: shapes, learning, checkpoints (round trip, exact resume), the `wam train` CLI, and running as a policy."""

import json
import shutil

import numpy as np
import pytest
import torch

from wamplan.cli import main
from wamplan.config import ConfigError
from wamplan.envs.contract import CAMERAS, Observation
from wamplan.errors import UserError
from wamplan.wam import WAMPolicy, load_wam, make_wam
from wamplan.wam.tinywam import TinyWAM, TinyWAMConfig, TinyWAMNet
from wamplan.wam.train import WAMTrainConfig, load_items, make_batch, train_tinywam, wam_loss

TINY = TinyWAMConfig(image_size=32, channels=(8, 16), latent_dim=32, trunk_dim=64)  # sizes from the task
CUBE_TINY = TINY.for_task("cube-insertion")  # A = 5, P = 10, front side wrist
TINY_ARGS = ["--image-size", "32", "--channels", "8", "16", "--latent-dim", "32", "--trunk-dim", "64"]
# seeds 0 and 1 of the expert: seed 0 lands in the training split, seed 1 in validation (val_fraction 0.1)
TRAIN = WAMTrainConfig(epochs=2, batch_size=8, shift_pixels=2, device="cpu")


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def store(expert_store):
    return expert_store  # the session's store, read-only here: `wam train` writes only under --out


def _obs(size: int = 48, step: int = 0) -> Observation:
    rng = np.random.default_rng(0)
    return Observation(step=step, proprio=rng.normal(size=10).astype(np.float32),
                       images={c: rng.integers(0, 256, (size, size, 3), dtype=np.uint8) for c in CAMERAS})


def test_forward_shapes_and_predict_contract():
    assert (CUBE_TINY.action_dim, CUBE_TINY.proprio_dim, CUBE_TINY.cameras) == (5, 10, CAMERAS)
    with pytest.raises(ConfigError, match="for_task"):
        TinyWAMNet(TINY)  # the task's sizes are not filled in
    net = TinyWAMNet(CUBE_TINY)
    actions, future = net(torch.rand(2, 3, 3, 32, 32), torch.randn(2, 10))
    assert actions.shape == (2, 16, 5) and future.shape == (2, 3, 3, 32, 32)
    assert actions.abs().max() <= 1.0
    # zero-initialised residual head: an untrained model predicts "nothing changes"
    x = torch.rand(1, 3, 3, 32, 32)
    assert torch.allclose(net(x, torch.randn(1, 10))[1], x)

    wam = make_wam("tinywam", config=TINY, device="cpu")
    out = wam.validate(wam.predict(_obs(48), "insert"))  # 48-px views are resized to 32
    assert out.actions.shape == (16, 5) and out.actions.dtype == np.float32
    assert all(out.images[c].shape == (32, 32, 3) and out.images[c].dtype == np.uint8 for c in CAMERAS)


def test_configs_reject_bad_values_with_the_fix():
    with pytest.raises(ConfigError, match="multiple of 2"):
        TinyWAMConfig(image_size=30, channels=(8, 16))
    with pytest.raises(ConfigError, match="cameras"):
        TinyWAMConfig(cameras=("front", "front"))
    with pytest.raises(ConfigError, match="cameras"):
        TinyWAMConfig(cameras=("front", "top")).for_task("cube-insertion")
    with pytest.raises(ConfigError, match="action_dim is 7 but task cube-insertion has 5"):
        TinyWAMConfig(action_dim=7).for_task("cube-insertion")
    assert TinyWAMConfig(cameras=("wrist",)).for_task("cube-insertion").cameras == ("wrist",)
    with pytest.raises(ConfigError, match="image_loss"):
        WAMTrainConfig(image_loss="l2")
    with pytest.raises(ConfigError, match="batch_size"):
        WAMTrainConfig(batch_size=0)


def test_training_steps_reduce_the_loss_on_a_fixed_batch(store):
    items = load_items([store], TINY, "train", 0.1)
    assert len(items) > 8 and items.frames.shape[1:] == (3, 3, 32, 32)
    torch.manual_seed(0)
    net = TinyWAMNet(CUBE_TINY)
    opt = torch.optim.AdamW(net.parameters(), lr=3e-3)
    batch = make_batch(items, torch.arange(8), torch.device("cpu"))
    losses = []
    for _ in range(25):
        loss, _ = wam_loss(net, batch, TRAIN)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0], losses


def test_checkpoint_round_trip_and_exact_resume(store, tmp_path):
    logs: list[str] = []
    full = train_tinywam([store], tmp_path / "full", TINY, TRAIN, progress=False, log=logs.append)
    assert full.state["epoch"] == 2 and len(full.state["history"]) == 2
    assert "val/action_mse" in full.state["history"][-1] and "val/copy_image_mse" in full.state["history"][-1]

    # interrupted after 2 steps, then the same call again: continues from step 2 and ends where "full" did
    part = train_tinywam([store], tmp_path / "part", TINY, TRAIN, max_steps=2, progress=False, log=logs.append)
    assert part.state["global_step"] == 2
    resumed = train_tinywam([store], tmp_path / "part", TINY, TRAIN, progress=False, log=logs.append)
    assert any("resuming" in m and "step 2" in m for m in logs)
    assert resumed.state["global_step"] == full.state["global_step"]
    a, b = full.net.state_dict(), resumed.net.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)

    # a finished run says so and trains nothing
    again = train_tinywam([store], tmp_path / "full", TINY, TRAIN, progress=False, log=logs.append)
    assert again.finished_before and "already finished 2 epochs" in logs[-1]

    # save -> load_wam -> identical predictions
    wam = load_wam(tmp_path / "full")
    assert isinstance(wam, TinyWAM) and wam.config == CUBE_TINY and wam.task.name == "cube-insertion"
    ref = TinyWAM(net=full.net, device="cpu").predict(_obs(64), "")
    out = wam.predict(_obs(64), "")
    np.testing.assert_array_equal(out.actions, ref.actions)
    for c in CAMERAS:
        np.testing.assert_array_equal(out.images[c], ref.images[c])
    assert wam.trained_camera_size == 64
    with pytest.warns(UserWarning, match="--camera-size 64"):  # a 48-px render is not what it was trained on
        wam.predict(_obs(48), "")
    saved = json.loads((tmp_path / "full" / "checkpoint" / "config.json").read_text())
    assert saved["kind"] == "tinywam" and saved["config"]["data"]["train_items"] == len(load_items([store], TINY, "train", 0.1))
    assert saved["config"]["data"]["task"] == "cube-insertion" and saved["config"]["model"]["action_dim"] == 5


def test_shipped_checkpoint_without_a_task_is_the_cube_and_policies_check_the_task():
    wam = load_wam("checkpoints/mini/tinywam", device="cpu")  # recorded no task: made before tasks
    assert wam.task.name == "cube-insertion" and wam.action_dim == 5 and wam.cameras == CAMERAS
    assert wam.default_instruction == wam.task.instruction
    WAMPolicy(wam, task="cube-insertion")
    with pytest.raises(UserError, match="made for task 'cube-insertion', but this run uses task 'push-cube'"):
        WAMPolicy(wam, task="push-cube")


def test_stores_of_different_tasks_are_refused_in_one_line(store, tmp_path):
    from wamplan.data.store import EpisodeStore
    from wamplan.envs.config import EnvConfig

    other = tmp_path / "push"
    EpisodeStore(other, create=True, env=EnvConfig(task="push-cube", camera_size=64).task_kwargs(), image_every=4)
    with pytest.raises(UserError, match="mixes tasks") as e:
        train_tinywam([store, other], tmp_path / "run", TINY, TRAIN, progress=False)
    assert "push-cube" in str(e.value) and "cube-insertion" in str(e.value) and "\n" not in str(e.value)


def test_cli_train_resume_and_errors(store, tmp_path, capsys):
    out = tmp_path / "ckpt"
    args = ["wam", "train", "--data", str(store), "--out", str(out), "--epochs", "1", "--batch-size", "8",
            "--no-progress", "--device", "cpu", *TINY_ARGS]
    assert main(args) == 0
    assert (out / "checkpoint" / "model.safetensors").is_file() and (out / "checkpoint" / "training_state").is_dir()
    capsys.readouterr()
    assert main(["wam", "train", "--data", str(store), "--out", str(out), "--epochs", "1"]) == 0  # saved options kept
    assert "already finished 1 epochs" in capsys.readouterr().out

    def one_line_error(argv: list[str], needle: str) -> None:
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("wamplan: error:") and needle in err and "\n" not in err, err

    one_line_error(["wam", "train", "--data", str(tmp_path), "--out", str(tmp_path / "x")], "is not an episode store")
    one_line_error(["wam", "train", "--data", str(store), "--out", str(store)], "is not a TinyWAM checkpoint")
    one_line_error([*args[:-len(TINY_ARGS)], "--image-size", "64", "--channels", "8", "16"], "different image_size")
    one_line_error([*args, "--lr", "0.5"], "different lr")


def test_cli_resume_on_different_data_is_refused(store, tmp_path, capsys):
    """A half-trained run continued on other data would mix two datasets in one model: refused, in one line.
    The same store spelled through a link is the same data and resumes."""
    out = tmp_path / "ckpt"
    base = ["wam", "train", "--out", str(out), "--epochs", "1", "--batch-size", "8", "--no-progress", "--device", "cpu",
            *TINY_ARGS]
    assert main([*base, "--data", str(store), "--max-steps", "1"]) == 0
    weights = (out / "checkpoint" / "model.safetensors").read_bytes()
    other = shutil.copytree(store, tmp_path / "other")  # another store (a copy to start with) ...
    for victim in sorted((other / "episodes").glob("*.h5"))[1:]:
        victim.unlink()  # ... holding different data: one episode fewer
    capsys.readouterr()
    for data in ([str(other)], [str(store), str(other)]):
        assert main([*base, "--data", ",".join(data), "--max-steps", "2"]) == 2
        err = capsys.readouterr().err.strip()
        assert "trained on different data" in err and "use another --out" in err and "\n" not in err, err
    assert main([*base, "--data", str(store), "--sources", "pink", "--max-steps", "2"]) == 2
    assert "different data" in capsys.readouterr().err
    assert (out / "checkpoint" / "model.safetensors").read_bytes() == weights  # the refused runs left the checkpoint alone
    (tmp_path / "link").symlink_to(store)
    assert main([*base, "--data", str(tmp_path / "link"), "--max-steps", "2"]) == 0
    assert "resuming" in capsys.readouterr().out and json.loads(
        (out / "checkpoint" / "training_state" / "state.json").read_text())["train_state"]["global_step"] == 2


def test_tinywam_runs_as_a_policy_and_queries_every_16_steps(small_env):
    from wamplan.policies.rollout import run_episode

    policy = WAMPolicy(make_wam("tinywam", config=TINY, device="cpu"))
    result = run_episode(small_env, policy, seed=0, max_steps=32, stop_on_success=False)
    assert result.length == 32
    assert result.policy_info["query_steps"] == [0, 16] and result.policy_info["chunks"] == 2
    assert policy.last_output is not None and policy.last_output.images["front"].shape == (32, 32, 3)
