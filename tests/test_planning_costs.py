"""Planning costs: eq. 3 patch MSE, class-token MSE, view weights, registry, shape errors."""

from __future__ import annotations

import pytest
import torch

from wamplan.config import ConfigError
from wamplan.errors import UserError
from wamplan.planning.cost_config import COST_NAMES
from wamplan.planning import COSTS, CostConfig, cls_cost, make_cost, patch_cost, register_cost
from wamplan.planning.costs import build_cost

B, V, N, D = 4, 3, 6, 8  # candidates, views, patches, embedding dim


def _data(seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(B, V, N, D, generator=g), torch.randn(V, N, D, generator=g)  # pred, target


def test_patch_cost_is_eq3():
    pred, target = _data()
    got = patch_cost(pred, target)  # (B,)
    want = torch.stack([((p - target) ** 2).sum() / target.numel() for p in pred])  # ||.||^2 / |z|
    torch.testing.assert_close(got, want)
    assert got.shape == (B,)
    assert patch_cost(target[None].expand(B, -1, -1, -1), target).abs().max() == 0


def test_view_weights():
    pred, target = _data(1)
    uniform = make_cost("patch", (2.0, 2.0, 2.0))(pred, target)
    torch.testing.assert_close(uniform, patch_cost(pred, target))
    wrist_only = make_cost("patch", (0, 0, 1))(pred, target)
    torch.testing.assert_close(wrist_only, patch_cost(pred[:, 2:], target[2:]))
    mixed = make_cost("patch", (1, 3, 0))(pred, target)
    per_view = ((pred - target) ** 2).mean((2, 3))  # (B, V)
    torch.testing.assert_close(mixed, 0.25 * per_view[:, 0] + 0.75 * per_view[:, 1])
    with pytest.raises(ValueError, match="one weight per camera view"):
        make_cost("patch", (1, 1))(pred, target)
    with pytest.raises(ConfigError, match="view_weights"):
        make_cost("patch", (1, -1, 1))


def test_pooled_cost_matches_the_mean_of_each_block():
    from wamplan.planning.costs import pool_tokens

    g = torch.Generator().manual_seed(3)
    pred, target = torch.randn(B, V, 16, D, generator=g), torch.randn(V, 16, D, generator=g)  # 4 x 4 grids
    grid = pred.reshape(B, V, 4, 4, D)
    top_left = grid[:, :, :2, :2].mean(dim=(2, 3))  # (B, V, D): the first 2 x 2 block, by hand
    torch.testing.assert_close(pool_tokens(pred, 2)[:, :, 0], top_left)
    bottom_right = grid[:, :, 2:, 2:].mean(dim=(2, 3))
    torch.testing.assert_close(pool_tokens(pred, 2)[:, :, 3], bottom_right)
    cost = build_cost(CostConfig(pool=2, view_weights=(0, 0, 1)))
    want = (pool_tokens(pred, 2)[:, 2] - pool_tokens(target, 2)[2]).square().mean(dim=(1, 2))
    torch.testing.assert_close(cost(pred, target), want)
    torch.testing.assert_close(build_cost(CostConfig(pool=4))(pred, target), cls_cost(pred, target))  # 1 x 1: cls
    with pytest.raises(ValueError, match="lower --cost-pool"):
        build_cost(CostConfig(pool=3))(pred, target)
    with pytest.raises(ConfigError, match="pool must be an int >= 1"):
        CostConfig(pool=0)


def test_cls_cost_and_registry():
    g = torch.Generator().manual_seed(2)
    pred, target = torch.randn(B, V, D, generator=g), torch.randn(V, D, generator=g)
    torch.testing.assert_close(cls_cost(pred, target), ((pred - target) ** 2).mean((1, 2)))
    assert make_cost("cls") is cls_cost and build_cost(CostConfig(name="cls")) is cls_cost
    # patch tokens (a world model's predictions) are matched by their mean over the tokens, per view
    tokens, aim = torch.randn(B, V, 5, D, generator=g), torch.randn(V, 5, D, generator=g)
    torch.testing.assert_close(cls_cost(tokens, aim), cls_cost(tokens.mean(2), aim.mean(1)))
    with pytest.raises(ValueError, match=r"got \(4, 3, 1, 8\) and \(3, 8\); give the target the predictions' shape"):
        cls_cost(pred[:, :, None], target)
    with pytest.raises(ValueError, match="drop the target's batch"):
        patch_cost(*_data()[:1], _data()[1][None])
    with pytest.raises(UserError, match="unknown cost 'l1'"):
        make_cost("l1")
    with pytest.raises(ConfigError, match="unknown cost"):
        CostConfig(name="l1")

    @register_cost("test_l1")
    def l1(pred, target, view_weights=None):
        return (pred - target).abs().flatten(1).mean(1)

    try:
        assert make_cost("test_l1")(pred, target).shape == (B,)
        with pytest.raises(ValueError, match="registered twice"):
            register_cost("test_l1")(l1)
    finally:
        COSTS.pop("test_l1")
        COST_NAMES.discard("test_l1")


def test_low_precision_predictions_scored_in_float32():
    pred, target = _data(3)
    got = patch_cost(pred.bfloat16(), target.bfloat16())
    assert got.dtype == torch.float32
    torch.testing.assert_close(got, patch_cost(pred.bfloat16().float(), target.bfloat16().float()))
