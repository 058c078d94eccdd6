"""Eq. 2's two forms: per-element means (our default) and the paper's squared norms."""

import torch

from wamplan.worldmodel.config import PredictorConfig
from wamplan.worldmodel.predictor import WorldModelPredictor
from wamplan.worldmodel.train import _split, per_horizon_mse, window_loss


def test_sum_form_weights_proprio_by_its_share_of_the_elements():
    torch.manual_seed(0)
    cfg = PredictorConfig(num_patches=4, enc_dim=8, frameskip=4, context=3, depth=1, heads=2, head_dim=8,
                          mlp_dim=16, proprio_emb=8, action_emb=8)
    model = WorldModelPredictor(cfg).eval()
    batch = dict(z=torch.randn(2, 5, 3, 4, 8), q=torch.randn(2, 5, 10), a=torch.rand(2, 5, 20) * 2 - 1)
    mean, _ = window_loss(model, batch, horizon=2, gamma=0.5, loss_form="mean")
    paper, _ = window_loss(model, batch, horizon=2, gamma=0.5, loss_form="sum")
    (zc, qc, ac), af, (zt, qt) = _split(model, batch, 2)
    zp, qp = model.rollout(zc, qc, ac, af)
    ez, eq = per_horizon_mse(zp, zt).mean(0), per_horizon_mse(qp, qt).mean(0)  # (K,)
    w = torch.tensor([1.0, 0.5])
    torch.testing.assert_close(mean, (w * (ez + eq)).sum())
    # ||dz||^2 + ||dq||^2 over V·N·D = 96 feature elements: proprio weighted 10 / 96
    torch.testing.assert_close(paper, (w * (ez * 96 + eq * 10)).sum() / 96)
