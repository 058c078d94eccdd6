"""Behaviour no test pinned before (issue 75, item 5): each test asserts values, and fails with the small bug the
issue planted in it (named in each test's comment). Untrained tiny models: no training, a few seconds in all."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

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


def _spread_model():
    from wamplan.worldmodel import PredictorConfig, WorldModelPredictor

    cfg = PredictorConfig(num_views=1, num_patches=4, enc_dim=8, action_dim=3, frameskip=2, context=3, depth=2,
                          heads=2, head_dim=8, mlp_dim=32, proprio_emb=16, action_emb=16, spread_head=True)
    torch.manual_seed(0)
    model = WorldModelPredictor(cfg).eval()
    with torch.no_grad():
        for p in model.spread_head.parameters():  # a head whose log-variances vary from step to step
            p.normal_(0, 0.5)
        model.z_std.fill_(2.0)  # tokens spread twice the normalised unit: their variance is 4x
    return model


def test_token_variance_is_scaled_by_z_std_squared():
    """Planted: the spread scaled by ``z_std`` instead of ``z_std**2`` (worldmodel/predictor.py)."""
    model = _spread_model()
    lv = torch.tensor([[0.0, float(np.log(0.25))]]).repeat(1, 4)  # (1, 8): variances 1 and 0.25 in normalised units
    torch.testing.assert_close(model.token_variance(lv), torch.tensor([[4.0, 1.0] * 4]))


def test_the_planners_spread_is_read_from_the_last_rollout_step():
    """Planted: the spread read from the first rollout step instead of the last (planning/dynamics.py)."""
    from wamplan.planning.dynamics import LearnedDynamics, PlanningContext

    model = _spread_model()
    cfg = model.cfg
    g = torch.Generator().manual_seed(3)
    z = torch.randn(1, cfg.context, cfg.num_views, cfg.num_patches, cfg.enc_dim, generator=g)
    q, past = torch.zeros(1, cfg.context, cfg.proprio_dim), torch.zeros(1, cfg.context - 1, cfg.action_block_dim)
    dyn = LearnedDynamics(model)
    dyn.prepare(PlanningContext(z[0], q[0], past[0]))
    cands = torch.rand(4, 3 * cfg.frameskip, cfg.action_dim, generator=g) * 2 - 1  # (B, L, A): three blocks
    zp, spread = dyn.predict(cands)
    _, _, lv = model.rollout(z, q, past, cands.reshape(4, 3, -1), spread=True)  # (B, S=3, V, N, D)
    per_step = [model.token_variance(lv[:, s]).flatten(1).mean(1) for s in range(3)]  # (B,) each
    torch.testing.assert_close(spread, per_step[-1])
    assert not torch.allclose(spread, per_step[0], rtol=1e-2)  # the first step's differs: the test can tell
    torch.testing.assert_close(zp, dyn.terminal(cands))


def test_a_concat_encoders_input_size_is_its_largest_parts():
    """Planted: a concat encoder's ``input_size`` the smallest part's (encoders/concat.py)."""
    from wamplan.encoders import make_encoder

    small = dict(name="patch-pixels", input_size=32, patch_size=8, proj_dim=8)
    large = dict(name="patch-pixels", input_size=64, patch_size=16, proj_dim=4)
    for parts in ([small, large], [large, small]):
        assert make_encoder("concat", parts=parts).input_size == 64


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
