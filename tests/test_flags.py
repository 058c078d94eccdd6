"""A refused option names the flag typed and its value, and a command that has nothing to do says so (issue 75,
the minor list): one flag a range error, the alias typed (``--max-steps``), the count that runs past the last
seed (not the first seed), one store named twice, a task no plug-in registered, a finished training re-run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from wamplan.cli import main

MINI = Path(__file__).resolve().parents[1] / "checkpoints" / "mini"
EVAL = ["eval", "--conditions", "1", "--wam", MINI / "tinywam"]
COLLECT = ["collect", "--source", "expert"]


@pytest.mark.parametrize("argv, line", [
    ([*COLLECT, "--episodes", "1", "--workers", "0"], "--workers 0 must be at least 1"),
    ([*COLLECT, "--episodes", "0"], "--episodes 0 must be at least 1"),
    ([*COLLECT, "--episodes", "2", "--image-every", "-3"], "--image-every -3 must be at least 1"),
    ([*EVAL, "--episodes", "0"], "--episodes 0 must be at least 1"),
    ([*EVAL, "--episodes", "1", "--workers", "0"], "--workers 0 must be at least 1"),
    ([*EVAL, "--episodes", "1", "--max-steps", "0"], "--max-steps 0 must be at least 1"),
    ([*EVAL, "--episodes", "1", "--max-steps", "5", "--max-episode-steps", "6"],
     "--max-steps 5 and --max-episode-steps 6 say the same thing differently"),
    ([*EVAL, "--episodes", "99999999999"], "--episodes 99999999999: the seeds 0 .. 99999999998 (from --seed-start 0)"),
    ([*COLLECT, "--seed-start", "7", "--episodes", str(2**32)], f"--episodes {2**32}: the seeds 7 .. {2**32 + 6}"),
    ([*COLLECT, "--seed-start", str(2**32), "--episodes", "1"], f"--seed-start {2**32}: episode seeds must lie in"),
])
def test_a_range_error_names_the_flag_typed_and_its_value(tmp_path, refused, argv, line):
    out = tmp_path / "out"
    err = refused([*argv, "--out", out], line)
    assert err.count(" must ") <= 1 and not out.exists()
    if "--episodes 99" in line or f"--episodes {2**32}" in line:
        assert "pass at most" in err and not err.startswith("wamplan: error: --seed-start")


def test_one_store_named_twice_is_refused(tmp_path, refused):
    store = tmp_path / "store"
    spelled = f"{store},{tmp_path}/sub/../store"
    refused(["wm", "train", "--data", spelled, "--out", tmp_path / "wm"], f"--data names {store} and",
            "one store; name each store once")
    refused(["wam", "train", "--data", f"{store},{store}", "--out", tmp_path / "wam"], f"--data names {store} twice")


def test_a_store_of_an_unregistered_task_points_at_the_entry_point(tmp_path, refused):
    from wamplan.data.store import SCHEMA_VERSION

    store = tmp_path / "my-arm"
    store.mkdir()
    (store / "store.json").write_text(json.dumps(dict(
        format="wamplan-episode-store", schema_version=SCHEMA_VERSION, image_every=4, env={"task": "my-arm"},
        task={"task": "my-arm"}, cameras=["scene", "wrist"])))
    refused(["wm", "train", "--data", store, "--out", tmp_path / "wm"], "unknown task 'my-arm'; choose one of",
            "entry-point group 'wamplan.tasks'")


def test_a_finished_training_says_it_was_done(tmp_path):
    import torch

    import wamplan.train_loop as loop
    from wamplan.wam.train import WAMTrainConfig

    data = torch.utils.data.TensorDataset(torch.randn(4, 3))
    cfg = WAMTrainConfig(epochs=1, batch_size=2)

    def fit(said: list) -> loop.FitResult:
        return loop.fit(torch.nn.Linear(3, 1), loop.DatasetBatches(data), lambda m, b: (m(b[0]).pow(2).mean(), {}),
                        cfg, run_dir=tmp_path / "run", kind="test", config={}, progress=False, log=said.append,
                        resume=True)

    first, again = [], []
    assert not fit(first).finished_before and not any("already" in s for s in first)
    result = fit(again)
    assert result.finished_before and result.metrics["epoch"] == 1
    assert again == [f"{tmp_path / 'run'} has already finished 1 epochs (2 steps); nothing to do. Pass --epochs > 1 "
                     f"to train longer, or a new --out."]
