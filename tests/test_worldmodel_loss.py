"""Eq. 2's two forms: per-element means (our default) and the paper's squared norms."""

import pytest
import torch

from wamplan.worldmodel.config import PredictorConfig
from wamplan.worldmodel.predictor import WorldModelPredictor
from wamplan.worldmodel.losses import per_horizon_mse, split_windows, window_loss


def test_sum_form_weights_proprio_by_its_share_of_the_elements():
    torch.manual_seed(0)
    cfg = PredictorConfig(num_patches=4, enc_dim=8, frameskip=4, context=3, depth=1, heads=2, head_dim=8,
                          mlp_dim=16, proprio_emb=8, action_emb=8)
    model = WorldModelPredictor(cfg).eval()
    batch = dict(z=torch.randn(2, 5, 3, 4, 8), q=torch.randn(2, 5, 10), a=torch.rand(2, 5, 20) * 2 - 1)
    mean, _ = window_loss(model, batch, horizon=2, gamma=0.5, loss_form="mean")
    paper, _ = window_loss(model, batch, horizon=2, gamma=0.5, loss_form="sum")
    (zc, qc, ac), af, (zt, qt) = split_windows(model, batch, 2)
    zp, qp = model.rollout(zc, qc, ac, af)
    ez, eq = per_horizon_mse(zp, zt).mean(0), per_horizon_mse(qp, qt).mean(0)  # (K,)
    w = torch.tensor([1.0, 0.5])
    torch.testing.assert_close(mean, (w * (ez + eq)).sum())
    # ||dz||^2 + ||dq||^2 over V·N·D = 96 feature elements: proprio weighted 10 / 96
    torch.testing.assert_close(paper, (w * (ez * 96 + eq * 10)).sum() / 96)


def test_sibling_loss_sees_only_how_the_prediction_moves_with_the_chunk():
    """Sibling windows share their context: an error common to the whole group cancels, an error in how one
    chunk's outcome differs from its siblings' does not."""
    from wamplan.worldmodel.losses import sibling_loss
    from wamplan.worldmodel.siblings import evaluate_siblings

    torch.manual_seed(0)
    cfg = PredictorConfig(num_patches=4, enc_dim=8, frameskip=4, context=3, depth=1, heads=2, head_dim=8,
                          mlp_dim=16, proprio_emb=8, action_emb=8)
    model = WorldModelPredictor(cfg).eval()
    b, g, k = 2, 3, 2
    ctx_z, ctx_q = torch.randn(b, 1, 3, 3, 4, 8), torch.randn(b, 1, 3, 10)
    z = torch.cat([ctx_z.expand(b, g, 3, 3, 4, 8), torch.zeros(b, g, k, 3, 4, 8)], 2)  # (B, G, T, V, N, D)
    q = torch.cat([ctx_q.expand(b, g, 3, 10), torch.zeros(b, g, k, 10)], 2)
    a = torch.rand(b, g, 3 + k, 20) * 2 - 1
    batch = dict(z=z, q=q, a=a)
    with torch.no_grad():
        (zc, qc, ac), af, _ = split_windows(model, {n: v.flatten(0, 1) for n, v in batch.items()}, k)
        zp, _ = model.rollout(zc, qc, ac, af)  # (B G, K, V, N, D)
    truth = zp.unflatten(0, (b, g)) + torch.randn(b, 1, k, 3, 4, 8)  # the model's futures + one shift per group
    batch["z"] = torch.cat([z[:, :, :3], truth], 2)
    with torch.no_grad():
        shared, logs = sibling_loss(model, batch, k, gamma=0.9)
        assert float(shared) < 1e-10 and logs["sib_rel_h2"] < 1e-5
        held_out = [{n: v[i] for n, v in batch.items()} for i in range(b)]  # a dataset of B groups
        assert evaluate_siblings(model, held_out, k, batch_size=1)["sib_rel_h2"] < 1e-5
        plain, _ = window_loss(model, {n: v.flatten(0, 1) for n, v in batch.items()}, k, gamma=0.9)
        assert float(plain) > 0.5  # the ordinary loss does see the shared error
        batch["z"][:, 0, 3:] += 0.5  # the first sibling's outcome moves away from the others'
        moved, logs = sibling_loss(model, batch, k, gamma=0.9)
    # deviation from the group mean: (1 - 1/G) * 0.5 for the moved one, 0.5 / G for the others
    want = ((0.5 * (g - 1) / g) ** 2 + (g - 1) * (0.5 / g) ** 2) / g * (1 + 0.9)
    torch.testing.assert_close(moved, torch.tensor(want), rtol=1e-4, atol=1e-6)
    held_out = [{n: v[i] for n, v in batch.items()} for i in range(b)]
    assert evaluate_siblings(model, held_out, k, batch_size=1)["sib_rel_h2"] == pytest.approx(
        logs["sib_rel_h2"], rel=1e-4)


def test_sibling_batches_resume_where_they_stopped():
    """Batch s of the branch groups depends on (seed, s) only: a resumed run continues the same sequence."""
    from itertools import islice

    from wamplan.worldmodel.config import TrainConfig
    from wamplan.worldmodel.train import _group_batches

    groups = [{"z": torch.full((2, 1), float(i))} for i in range(10)]
    cfg = TrainConfig(sibling_groups=3)
    whole = [b["z"][:, 0, 0].tolist() for b in islice(_group_batches(groups, cfg), 7)]
    resumed = [b["z"][:, 0, 0].tolist() for b in islice(_group_batches(groups, cfg, start=4), 3)]
    assert resumed == whole[4:] and sorted(sum(whole[:3], [])) == sorted(set(sum(whole[:3], [])))  # a pass: no repeats


def test_sibling_statistics_per_view_token_and_feature_split_the_pooled_ones():
    """Per view, each statistic is that view's share: the views' mean is the pooled figure (each view has as many
    elements), and a sibling difference in one view's truth shows in that view's spread alone; per token and per
    feature, the mean over a view's tokens or features is the view's figure, and a difference in one feature shows
    in that feature alone."""
    from wamplan.worldmodel.siblings import sibling_statistics

    torch.manual_seed(0)
    cfg = PredictorConfig(num_patches=4, enc_dim=8, frameskip=4, context=3, depth=1, heads=2, head_dim=8,
                          mlp_dim=16, proprio_emb=8, action_emb=8)
    model = WorldModelPredictor(cfg).eval()
    g, k = 3, 2
    ctx = torch.randn(1, 3, 3, 4, 8).expand(g, 3, 3, 4, 8)
    future = torch.randn(1, k, 3, 4, 8).repeat(g, 1, 1, 1, 1)  # (G, K, V, N, D): the same for every sibling
    future[0, :, 1] += 1.0  # but the first sibling differs from the others in view 1
    future[0, :, 2, :, 5] += 1.0  # and in view 2's feature 5
    groups = [dict(z=torch.cat([ctx, future], 1), q=torch.randn(1, 3 + k, 10).expand(g, 3 + k, 10),
                   a=torch.rand(g, 3 + k, 20) * 2 - 1)]
    pooled = sibling_statistics(model, groups, k)
    views = sibling_statistics(model, groups, k, per="view")
    tokens = sibling_statistics(model, groups, k, per="token")
    features = sibling_statistics(model, groups, k, per="feature")
    for name in pooled:
        assert views[name].shape == (1, k, 3) and tokens[name].shape == (1, k, 3, 4)
        assert features[name].shape == (1, k, 3, 8)
        torch.testing.assert_close(views[name].mean(-1), pooled[name])
        torch.testing.assert_close(tokens[name].mean(-1), views[name], rtol=1e-5, atol=1e-6)  # a view: its tokens
        torch.testing.assert_close(features[name].mean(-1), views[name], rtol=1e-5, atol=1e-6)  # and its features
    spread = views["spread"][0, -1]  # (V,)
    assert float(spread[1]) > 0.1 and float(spread[0]) < 1e-12 and float(spread[2]) > 0.01
    in_view2 = features["spread"][0, -1, 2]  # (D,)
    assert float(in_view2[5]) > 0.1 and float(torch.cat([in_view2[:5], in_view2[6:]]).abs().max()) < 1e-12
    with pytest.raises(ValueError, match="per must be one of"):
        sibling_statistics(model, groups, k, per="pixel")


def test_rank_siblings_scores_a_planner_s_pick():
    """Ranking by the true outcomes is perfect (rho 1, regret 0, top-1 1); the reversed order is the worst
    (rho -1, the worst pick: regret above chance's 1); a shared offset in every prediction can reorder the
    siblings, which is what removing the shared error undoes."""
    from wamplan.worldmodel.siblings import _rank_siblings

    torch.manual_seed(0)
    true = torch.randn(5, 6, 12)  # (B, G, F)
    best = _rank_siblings(true, true)
    torch.testing.assert_close(best, torch.tensor([[1.0, 0.0, 1.0]] * 5, dtype=torch.float64))
    line = torch.arange(6, dtype=torch.float64)[None, :, None] * torch.ones(1, 1, 3)  # siblings on a line
    far = line[:, [5, 4, 3, 2, 1, 0]]  # each one predicted at its mirror image
    worst = _rank_siblings(far, line)[0]
    assert float(worst[0]) < 0 and float(worst[1]) > 1 and float(worst[2]) < 0.5
    shifted = _rank_siblings(true + 3.0, true)  # the same offset for every sibling
    assert float(shifted[:, 0].mean()) < 0.9
    target = torch.randn(5, 12)  # one target per group: every sibling ranked against it
    torch.testing.assert_close(_rank_siblings(true, true, target), best)
    beyond = torch.full((1, 3), -1.0)  # a target past sibling 0's end of the line
    assert float(_rank_siblings(far, line, beyond)[0, 1]) > 1  # the mirrored predictions pick the farthest


def test_sibling_ranking_per_group_with_and_without_the_shared_error():
    from wamplan.worldmodel.losses import sibling_futures
    from wamplan.worldmodel.siblings import RANKING, _rank_siblings, sibling_ranking

    torch.manual_seed(0)
    cfg = PredictorConfig(num_patches=4, enc_dim=8, frameskip=4, context=3, depth=1, heads=2, head_dim=8,
                          mlp_dim=16, proprio_emb=8, action_emb=8)
    model = WorldModelPredictor(cfg).train()
    g, k = 4, 2
    groups = [dict(z=torch.cat([torch.randn(1, 3, 3, 4, 8).expand(g, 3, 3, 4, 8), torch.randn(g, k, 3, 4, 8)], 1),
                   q=torch.randn(1, 3 + k, 10).expand(g, 3 + k, 10), a=torch.rand(g, 3 + k, 20) * 2 - 1)
              for _ in range(3)]
    r = sibling_ranking(model, groups, k)
    assert model.training  # left as it was
    targets = torch.randn(3, 3, 4, 8)
    own = sibling_ranking(model, groups, k, targets=targets)
    assert set(own) == set(r) and all(v.shape == (3,) for v in own.values())
    small = sibling_ranking(model, groups, k, batch_size=2, targets=targets)  # targets sliced across batches
    for name in own:
        torch.testing.assert_close(small[name], own[name])
    # group 2 by hand: its siblings ranked against its own target
    model.eval()
    with torch.no_grad():
        zp, zt, _ = sibling_futures(model, {n: x[None] for n, x in groups[2].items()}, k)
    by_hand = _rank_siblings(zp[:, :, -1].flatten(2), zt[:, :, -1].flatten(2), targets[2].flatten()[None])[0]
    torch.testing.assert_close(torch.stack([own[n][2] for n in RANKING]), by_hand)
    with pytest.raises(ValueError, match="2 targets for 3 groups"):
        sibling_ranking(model, groups, k, targets=torch.randn(2, 3, 4, 8))
    pairs = [{n: x[:2] for n, x in grp.items()} for grp in groups]
    with pytest.raises(ValueError, match="too few candidates"):
        sibling_ranking(model, pairs, k)
    assert set(r) == {*RANKING, *(f"{n}_sib" for n in RANKING)}
    for name, v in r.items():
        assert v.shape == (3,) and v.dtype == torch.float64
        low, high = (-1.0, 1.0) if "rho" in name else (0.0, 1.0) if "top1" in name else (0.0, float("inf"))
        assert bool(((v >= low - 1e-9) & (v <= high + 1e-9)).all()), name
