"""Behaviour no test pinned before (issue 75, item 5): each test asserts values, and fails with the small bug the
issue planted in it (named in each test's comment). Untrained tiny models: no training, a few seconds in all."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from wamplan.config import ConfigError

pytestmark = pytest.mark.usefixtures("one_thread")


def test_integer_config_fields_are_number_checked():
    """Planted: the number check skipping ``int`` fields (only ``float`` ones checked)."""
    from wamplan.worldmodel.config import TrainConfig

    assert TrainConfig(epochs=10, batch_size=8).epochs == 10
    for field, value in (("epochs", "10"), ("batch_size", 8.5j), ("epochs", float("nan"))):
        with pytest.raises(ConfigError, match=rf"TrainConfig\.{field} must be a finite number, got"):
            TrainConfig(**{field: value})
    with pytest.raises(ConfigError, match=r"TrainConfig\.lr must be a finite number, got '0.1'"):
        TrainConfig(lr="0.1")


def test_a_logged_episode_needs_its_last_frame_and_one_image_per_image_step():
    """Planted: ``EpisodeData.logged`` not requiring the frame at T, nor checking the image count against
    ``image_steps``."""
    import wamplan
    from wamplan.data.store import EpisodeData, StoreError

    task = wamplan.get_task("cube-insertion")
    t = 7  # frames every 4 steps: 0, 4, and the last, 7
    actions, proprio = np.zeros((t, task.action_dim)), np.zeros((t + 1, task.proprio_dim))

    def views(k: int) -> dict[str, np.ndarray]:
        return {c: np.zeros((k, 16, 16, 3), np.uint8) for c in task.cameras}

    ep = EpisodeData.logged(task, 0, actions, proprio, views(3), [0, 4, 7])
    assert ep.image_steps.tolist() == [0, 4, 7] and ep.images[task.cameras[0]].shape[0] == 3
    with pytest.raises(StoreError, match=r"image_steps must be 0, 4, 8, \.\.\. up to T=7 and T .*2 frames for 3"):
        EpisodeData.logged(task, 0, actions, proprio, views(2), [0, 4])  # the last frame left out
    with pytest.raises(StoreError, match=rf"images\['{task.cameras[0]}'\] is uint8 \(2, 16, 16, 3\), want uint8 "
                                         r"\(3, H, W, 3\)"):
        EpisodeData.logged(task, 0, actions, proprio, views(2), [0, 4, 7])  # one image short of image_steps
    with pytest.raises(StoreError, match=r"images\[.*\] is uint8 \(4, 16, 16, 3\), want uint8 \(3, H, W, 3\)"):
        EpisodeData.logged(task, 0, actions, proprio, views(4), [0, 4, 7])  # one too many


def test_eval_refuses_zero_episodes_with_a_wam_and_writes_nothing(tmp_path, refused):
    """Planted: ``--episodes 0`` accepted with ``--wam`` (the run exited 0 and wrote eval_config.json)."""
    from pathlib import Path

    wam = Path(__file__).resolve().parents[1] / "checkpoints" / "mini" / "tinywam"
    out = tmp_path / "eval"
    refused(["eval", "--conditions", "1", "--episodes", "0", "--wam", wam, "--out", out], "--episodes 0")
    assert not (out / "eval_config.json").exists() and not out.exists()
    out.mkdir()  # an existing directory stays as it was, too
    refused(["eval", "--conditions", "1", "--episodes", "0", "--wam", wam, "--out", out], "--episodes 0")
    assert list(out.iterdir()) == []
